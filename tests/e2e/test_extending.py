"""End-to-end layer of extending physgrad: the example scene trained with every variant that
applies, a user's own optimiser with backprop modes and clipping, the Python API, tab completion,
the wheel run from an unrelated folder, and a solver that gives up mid-step ending its run
diverged."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import physgrad
from physgrad.errors import UserError
from physgrad.results import read_run
from tests.helpers import PHYSGRAD, REPO
from tests.helpers import console as run_cli

EXAMPLE = REPO / "examples" / "custom_scene"

SHORT = [
    "trainer.iterations=60",
    "trainer.eval_every=30",
    "task.train_size=64",
    "task.test_size=32",
]


@pytest.mark.long
def test_the_example_scene_trains_with_every_variant_that_applies(tmp_path):
    """Through the console script with -cd, from the example's folder: adam, hig (and its tuning
    file from the user's folder), bptt and stable_bptt (the scene is closed loop),
    Levenberg-Marquardt, L-BFGS, Muon, and the user's lion."""
    variants = [
        "adam",
        "bptt",
        "hig",
        "lbfgs",
        "levenberg_marquardt",
        "lion",
        "muon",
        "stable_bptt",
    ]
    result = run_cli(
        "run",
        "-m",
        "-cd",
        "conf",
        "task=pendulum",
        f"optim={','.join(variants)}",
        *SHORT,
        f"hydra.sweep.dir={tmp_path}",
        cwd=EXAMPLE,
    )
    runs = {read_run(p).variant: read_run(p) for p in tmp_path.rglob("results.h5")}
    assert sorted(runs) == variants, result.stderr[-2000:]
    for variant, run in runs.items():
        assert run.attrs["status"] == "completed" and run.attrs["task"] == "pendulum", (
            variant,
            run.attrs,
        )
        assert run.attrs["unroll"] == 40 and run.eval["loss"][-1] < run.eval["loss"][0], variant
        assert "upright" in run.eval
    assert (
        runs["hig"].attrs["batch_size"] == 16
        and "learning_rate: 0.1" in runs["hig"].attrs["config"]
    )
    assert "zeroed_fraction" in runs["stable_bptt"].train and "svd_failures" in runs["hig"].train


# make test-long: composing is checked in tests/integration/test_extending.py
@pytest.mark.long
def test_a_users_optimiser_composes_with_backprop_modes_and_clipping(tmp_path):
    """An optim YAML in a folder of the user's (adamw with an optax schedule, via hydra.searchpath),
    and lion with optim.backprop=C and clipping: the combined gradient's diagnostics are logged."""
    conf = tmp_path / "myconf" / "optim"
    conf.mkdir(parents=True)
    (conf / "adamw_cosine.yaml").write_text(
        "name: adamw_cosine\n_target_: optax.adamw\nweight_decay: 1e-4\nlearning_rate:\n"
        "  _target_: optax.cosine_decay_schedule\n  init_value: 1e-3\n  decay_steps: 60\n"
    )
    searchpath = f"hydra.searchpath=[file://{EXAMPLE / 'conf'},file://{tmp_path / 'myconf'}]"
    run_cli(
        "run",
        "-m",
        "task=pendulum",
        "optim=adamw_cosine,lion",
        "optim.backprop=C",
        "optim.clip=norm",
        *SHORT,
        searchpath,
        f"hydra.sweep.dir={tmp_path / 'out'}",
        cwd=EXAMPLE,
    )
    runs = {read_run(p).attrs["optim"]: read_run(p) for p in (tmp_path / "out").rglob("results.h5")}
    assert sorted(runs) == ["adamw_cosine", "lion"]
    for run in runs.values():
        assert run.attrs["status"] == "completed" and run.variant.endswith(" backprop=C clip=norm")
        assert 0 <= run.train["zeroed_fraction"].min() and run.train["zeroed_fraction"].max() <= 1


# make test-long: the Python API runs in make test through tests/integration/test_compare.py
@pytest.mark.long
def test_python_api_runs_one_configuration_and_reads_its_curves(in_example, tmp_path):
    run = physgrad.run(
        "task=pendulum", "optim=stable_bptt", *SHORT, config_dir="conf", out_dir=tmp_path
    )
    assert run.attrs["status"] == "completed" and run.path == tmp_path / "results.h5"
    assert run.train["loss"].shape == (60,) and run.eval["iteration"].tolist() == [0, 30, 60]
    again = physgrad.read_run(tmp_path / "results.h5")
    np.testing.assert_array_equal(again.eval["loss"], run.eval["loss"])
    seeds = physgrad.run(
        "task=pendulum",
        "optim=adam",
        "seeds=2",
        *SHORT,
        config_dir="conf",
        out_dir=tmp_path / "seeds",
    )
    assert [r.attrs["seed"] for r in seeds] == [0, 1]
    with pytest.raises(UserError, match="optim=bptt needs a closed-loop controller"):
        physgrad.run("task=poisson", "optim=bptt", out_dir=tmp_path / "refused")
    with pytest.raises(UserError, match="add -m"):
        physgrad.run("seed=0,1", out_dir=tmp_path / "sweep")


def test_python_api_writes_where_physgrad_run_would(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = physgrad.run(
        "task=toy", "optim=hig", "trainer.iterations=3", "task.test_size=8", "trainer.batch_size=4"
    )
    relative = run.path.relative_to(tmp_path.resolve())
    assert relative.parts[:2] == ("outputs", "runs") and relative.parent.name.endswith(
        "_toy_hig_s0"
    ), relative
    assert run.attrs["status"] == "completed" and (run.path.parent / "loss.png").exists()


# make test-long: Hydra's own feature, through the console script
@pytest.mark.long
def test_tab_completion_through_hydra(tmp_path):
    env = {**os.environ, "PATH": f"{Path(PHYSGRAD).parent}:{os.environ['PATH']}"}

    def query(line):
        return subprocess.run(
            [PHYSGRAD, "-sc", "query=bash"],
            env={**env, "COMP_LINE": line},
            cwd=EXAMPLE,
            capture_output=True,
            text=True,
            timeout=120,
        ).stdout.split()

    assert "task=poisson" in query("physgrad run task=") and "task=pendulum" not in query(
        "physgrad run task="
    )
    assert "task=pendulum" in query("physgrad run -cd conf task=")
    assert query("physgrad rep") == ["report"]
    script = (
        'eval "$(physgrad run -sc install=bash)"; COMP_LINE="physgrad run optim=h"; '
        "COMP_POINT=${#COMP_LINE}; "
        "COMP_WORDS=(physgrad run optim=h); COMP_CWORD=2; hydra_bash_completion; echo "
        '"${COMPREPLY[@]}"'
    )
    result = subprocess.run(
        ["bash", "-c", script], env=env, capture_output=True, text=True, timeout=120
    )
    assert result.stdout.split() == ["optim=hig"], result.stderr


@pytest.mark.long
def test_the_wheel_installs_and_runs_from_an_unrelated_folder(tmp_path):
    """`pip wheel .`, then the wheel into a fresh virtual environment, and `physgrad run` from a
    folder that has nothing of the repository: the configs come from the installed package. To keep
    the test short the fresh environment reuses this one's dependencies (a .pth line naming its
    site-packages, which does not activate this environment's editable physgrad); physgrad itself is
    only the wheel."""
    import site

    repo = EXAMPLE.parent.parent
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--no-deps",
            "-w",
            str(tmp_path / "dist"),
            str(repo),
        ],
        check=True,
        capture_output=True,
        timeout=600,
    )
    wheel = next((tmp_path / "dist").glob("physgrad-*.whl"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin" / "python"
    subprocess.run(
        [python, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheel)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    packages = next(venv.glob("lib/python*/site-packages"))
    (packages / "dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = subprocess.run(
        [python, "-c", "import physgrad.configs as c; print(c.__file__); print(c.CONF_DIR)"],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert all(Path(p).is_relative_to(packages) for p in where), where
    result = subprocess.run(
        [
            venv / "bin" / "physgrad",
            "run",
            "task=poisson",
            "trainer.iterations=5",
            "hydra.run.dir=out",
        ],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    run = read_run(elsewhere / "out" / "results.h5")
    assert run.attrs["status"] == "completed" and run.train["iteration"].size == 5
    shutil.rmtree(venv)


GIVING_UP_SCENE = r"""
import jax
import jax.numpy as jnp
import numpy as np

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene

CALLS = [0]


def solver(z):  # a library's solver called back on the host, giving up after some steps
    CALLS[0] += 1
    if CALLS[0] > LIMIT:
        # as equinox words it under jax.jit: the cause, then its advice between lines of dashes
        raise RuntimeError("The maximum number of solver steps was reached. Try increasing "
                           "max_steps.\n\n\n--------------------\nAn error occurred during the "
                           "runtime of your JAX program! Please wrap your program with "
                           "`equinox.filter_jit`.\n--------------------\n")
    return np.tanh(np.asarray(z))


def physics(z):
    return jax.pure_callback(solver, jax.ShapeDtypeStruct(z.shape, z.dtype), z,
                             vmap_method="sequential")


def build(key, *, test_size, limit):
    global LIMIT
    LIMIT = limit
    dtype = jnp.zeros(()).dtype

    def draw(k, count, train_set=None):
        x = jax.random.uniform(k, (count, 1), dtype, -1.0, 1.0)
        return {"x": x, "target": jnp.sin(3 * x)}

    return Scene(init_params=lambda k: init_mlp(k, [1, 8, 1], dtype), draw_batch=draw,
                 test_set=draw(key, test_size),
                 sample_output=lambda params, sample: physics(jax.lax.stop_gradient(
                     apply_mlp(params, sample["x"], hidden="tanh"))) + apply_mlp(
                     params, sample["x"], hidden="tanh"),
                 sample_loss=lambda y, sample: 0.5 * jnp.sum((y - sample["target"]) ** 2))
"""


# the fault's second instant (the first evaluation, before any step): make test-long
@pytest.mark.parametrize(
    "limit",
    [300, pytest.param(0, marks=pytest.mark.long)],
    ids=["in a step", "in the first evaluation"],
)
def test_a_solver_that_gives_up_in_a_step_ends_the_run_diverged_with_its_cause(
    tmp_path, monkeypatch, caplog, limit
):
    """An exception the scene's code raises inside the compiled step or the held-out evaluation (a
    host callback, as a diffrax solver's step limit through equinox, its advice banner included)
    is the variant failing on the scene: the run ends diverged, its rows kept, with the innermost
    cause in one line and no traceback logged, and is counted as a divergence."""
    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "giving_up.py").write_text(GIVING_UP_SCENE)
    (tmp_path / "conf" / "task" / "giving_up.yaml").write_text(
        f"_target_: giving_up.build\nbatch_size: 4\ntest_size: 8\nlimit: {limit}\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    run = physgrad.run(
        "task=giving_up",
        "optim=adam",
        "trainer.iterations=200",
        "trainer.eval_every=20",
        config_dir="conf",
        out_dir=tmp_path / "run",
    )
    reason = run.attrs["reason"]
    assert run.attrs["status"] == "diverged" and reason.startswith("solver failed: RuntimeError: ")
    assert reason.endswith("Try increasing max_steps.") and "\n" not in reason, reason
    assert "callback failed" not in caplog.text and "Traceback" not in caplog.text
    done = int(run.attrs["iterations"])
    assert run.train.get("loss", np.empty(0)).shape == (done,)
    assert 0 < done < 200 if limit else done == 0
