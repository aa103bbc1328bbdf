"""Integration layer of `physgrad check` and bad input: the small suite names every outcome, large
learning rates, rank-deficient Jacobians, norm drift and BPTT gradient growth are measured, bad
values are refused with their key, and wrong gradients, float64-only and reverse-only scenes are
found and explained."""

import re

import pytest

from physgrad.check import markdown, run_check
from physgrad.experiment import run_experiment
from tests.helpers import REPO, load


def rows_of(rows, case_start):
    found = [row for row in rows if row["case"].startswith(case_start)]
    assert found, case_start
    return found


def every_outcome_is_named(check_rows):
    for row in check_rows:
        assert row["outcome"] in (
            "converged",
            "stalled",
            "grew",
            "diverged",
            "refused",
            "finite",
        ), row


def far_too_large_learning_rates_end_as_outcomes(check_rows):
    rows = [row for row in check_rows if "learning rate 1e6" in row["case"]]
    assert len(rows) == 3
    for row in rows:
        assert row["outcome"] in ("diverged", "stalled", "grew"), row
        if row["outcome"] == "diverged":
            assert re.fullmatch(
                r"(output|loss|gradient|update) became \S+ at iteration \d+ \(\w+\)", row["detail"]
            )


def rank_deficient_jacobians_give_finite_directions(check_rows):
    rows = rows_of(check_rows, "rank-deficient J")
    assert len(rows) == 12 and all(row["outcome"] == "finite" for row in rows)
    for row in rows:
        errors = dict(re.findall(r"(\de[-+]\d+): (\S+?)(?:,|$)", row["detail"].split("tau ", 1)[1]))
        if "all-zero" in row["case"]:
            assert all(float(e) == 0.0 for e in errors.values())  # exactly the zero update
        elif row["precision"] == "64":
            # duplicated samples: rank m/2, the copies' singular values are exactly 0 and must be
            # dropped
            assert all(float(errors[t]) < 1e-6 for t in ("1e-06", "1e-04", "1e-02")), row


def schroedinger_norm_drift_is_round_off(check_rows):
    for row in rows_of(check_rows, "quantum norm"):
        drift = float(row["detail"].rsplit(": ", 1)[1])
        assert drift < (1e-12 if row["precision"] == "64" else 1e-3), row


def bptt_gradient_growth_is_measured(check_rows):
    rows = {row["variant"]: row for row in rows_of(check_rows, "multicart 4 poles: gradient norm")}
    assert set(rows) == {"bptt backprop=R", "bptt backprop=M"} and all(
        row["outcome"] == "finite" for row in rows.values()
    )
    # the modes differ (with the zero output layer of the initial network they would coincide)
    assert rows["bptt backprop=R"]["detail"] != rows["bptt backprop=M"]["detail"]


@pytest.mark.long
def test_the_small_check_names_every_outcome_and_measures_what_it_says(tmp_path):
    """`physgrad check --small` (about half a minute), run once and read by five checks: one test,
    so that pytest-xdist's workers do not each run it."""
    rows = run_check(small=True, out_dir=tmp_path)
    print(markdown(rows))
    every_outcome_is_named(rows)
    far_too_large_learning_rates_end_as_outcomes(rows)
    rank_deficient_jacobians_give_finite_directions(rows)
    schroedinger_norm_drift_is_round_off(rows)
    bptt_gradient_growth_is_measured(rows)


@pytest.mark.parametrize(
    "override, fragment",
    [
        (
            "task.hidden=[0,20]",
            "task.hidden=[0, 20] is not allowed: use a list of positive layer widths",
        ),
        (
            "task.checkpoint=maybe",
            "task.checkpoint='maybe' is not allowed: choose one of False, True",
        ),
        ("task.alpha=strong", "task.alpha='strong' is not allowed: use a number"),
        ("task.dt=-0.1", "task.dt=-0.1 is not allowed: use a number > 0"),
        ("task.oscillators=1.5", "task.oscillators=1.5 is not allowed: use a whole number >= 1"),
        (
            "task.oscillators=100000000",
            "the training set would hold 819,200,000,000 numbers, more than one array can "
            "(2^31 - 1): use a smaller task.oscillators or task.train_size",
        ),
        ("trainer.eval_every=0", "trainer.eval_every=0 is not allowed: use a whole number >= 1"),
        (
            "trainer.time_budget=-5",
            "trainer.time_budget=-5 is not allowed: use a number >= 1e-06 or null",
        ),
        ("precision=16", "precision=16 is not allowed: choose one of 32, 64"),
        ("seed=-1", "seed=-1 is not allowed: use a whole number >= 0"),
        (
            "seed=4294967296",
            "seed=4294967296 is not allowed: use a whole number >= 0 and < 4294967296",
        ),
        (
            "seed=4294967295 seeds=2",
            "seeds must stay below 4294967296 (2^32), so use seed <= 4294967294",
        ),
        ("optim=hig optim.tau=2", "optim.tau=2 is not allowed: use a number >= 0 and < 1"),
        (
            "optim=hig optim.route=qr",
            "optim.route='qr' is not allowed: choose one of auto, svd, gram",
        ),
        (
            "optim=adam optim.learning_rate=0",
            "optim.learning_rate=0 is not allowed: use a number > 0",
        ),
        ("overwrite=sometimes", "overwrite='sometimes' is not allowed: choose one of False, True"),
        ("unroll=0", "unroll=0 is not allowed: use a whole number >= 1"),
        ("seeds=0", "seeds=0 is not allowed: use a whole number >= 1"),
        (
            "init_from=7",
            "init_from=7 is not allowed: use the path of a results.h5, or leave init_from out",
        ),
    ],
)
def test_bad_values_are_refused_with_the_key_and_what_is_allowed(override, fragment, tmp_path):
    outcome, _ = run_experiment(load("task=oscillator", *override.split()), tmp_path)
    assert (
        outcome.status == "refused" and fragment in outcome.reason and "\n" not in outcome.reason
    ), outcome.reason


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("task.grid=1", "task.grid=1 is not allowed: use a whole number >= 2"),
        ("task.smoothness=-1", "task.smoothness=-1 is not allowed: use a number >= 0"),
    ],
)
def test_bad_poisson_values_are_refused(override, fragment, tmp_path):
    outcome, _ = run_experiment(load(override), tmp_path)
    assert outcome.status == "refused" and fragment in outcome.reason


BROKEN_SCENE = """
import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene


@jax.custom_jvp
def squash(z):
    return jnp.tanh(z)


@squash.defjvp
def squash_jvp(primals, tangents):  # the author's derivative is off by a factor of 2
    (z,), (dz,) = primals, tangents
    return jnp.tanh(z), 2.0 * (1.0 - jnp.tanh(z) ** 2) * dz


def build(key, *, test_size, wrong, rtol=None, atol=None):
    dtype = jnp.zeros(()).dtype
    physics = squash if wrong else jnp.tanh

    def draw(k, count, train_set=None):
        x = jax.random.uniform(k, (count, 1), dtype, -1.0, 1.0)
        return {"x": x, "target": jnp.sin(3 * x)}

    return Scene(init_params=lambda k: init_mlp(k, [1, 8, 1], dtype), draw_batch=draw,
                 test_set=draw(key, test_size),
                 sample_output=lambda params, sample: physics(
                     apply_mlp(params, sample["x"], hidden="tanh")),
                 sample_loss=lambda y, sample: 0.5 * jnp.sum((y - sample["target"]) ** 2))
"""


@pytest.mark.parametrize("wrong", [pytest.param(False, marks=pytest.mark.long), True])
def test_check_finds_a_scene_s_wrong_gradient(tmp_path, monkeypatch, capsys, wrong):
    from physgrad.check import main

    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "heat.py").write_text(BROKEN_SCENE)
    (tmp_path / "conf" / "task" / "heat.yaml").write_text(
        f"_target_: heat.build\nbatch_size: 4\ntest_size: 8\nwrong: {str(wrong).lower()}\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    code = main(["-cd", "conf", "task=heat"])
    lines = capsys.readouterr().out.splitlines()
    by_name = {
        line.split(":")[0].split()[-1] if line.startswith(("ok", "FAIL")) else "": line
        for line in lines
    }
    assert code == (1 if wrong else 0), lines
    assert (
        by_name["R"].startswith("FAIL" if wrong else "ok") and "finite differences" in by_name["R"]
    )
    # jvp and vjp share the wrong rule: only differences see it
    assert by_name["jacobian"].startswith("ok")
    assert lines[-1].startswith("task=heat: ") and ("failed: gradient R" in lines[-1]) == wrong


# every check of check_scene on the example scene (14 s): make test-long; make test checks the
# checks on the heat scene, right and wrong (above)
@pytest.mark.long
def test_check_of_the_example_scene_passes_and_mistakes_are_one_line(monkeypatch, capsys):
    from physgrad.check import main

    example = REPO / "examples" / "custom_scene"
    monkeypatch.chdir(example)
    monkeypatch.syspath_prepend(str(example))
    assert (
        main(
            [
                "-cd",
                "conf",
                "task=pendulum",
                "task.train_size=8",
                "task.test_size=4",
                "task.unroll=12",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert (
        all(line.startswith("ok") for line in out.splitlines()[:-1])
        and "gradient S" in out
        and "rollout" in out
    )
    # the precision its runs use, float32: built and stepped there too
    assert "ok    precision: float32: built, 3 gradient steps" in out
    assert main(["-cd", "conf", "task.unroll=12"]) == 2
    assert "name the scene to check" in capsys.readouterr().err


FLOAT64_ONLY_SCENE = """
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene


def build(key, *, test_size):
    dtype = jnp.zeros(()).dtype
    # the data's solve to a tolerance of 1e-12, as a stiff solver's: float32 cannot meet it
    x = jnp.asarray(1.0, dtype)
    for _ in range(60):
        x = 0.5 * (x + 2.0 / x)
    if abs(float(x * x - 2.0)) > 1e-12:
        raise ValueError("the data's solve did not reach its tolerance 1e-12")

    def draw(k, count, train_set=None):
        z = jnp.linspace(-1.0, 1.0, count, dtype=dtype)[:, None] * x
        return {"x": z, "target": jnp.sin(z)}

    return Scene(init_params=lambda k: init_mlp(k, [1, 8, 1], dtype), draw_batch=draw,
                 test_set=draw(key, test_size),
                 sample_output=lambda params, sample: apply_mlp(params, sample["x"], hidden="tanh"),
                 sample_loss=lambda y, sample: 0.5 * jnp.sum((y - sample["target"]) ** 2))
"""


def test_a_scene_that_works_in_float64_only_fails_the_precision_check_in_one_line(
    tmp_path, monkeypatch, capsys
):
    """check's other checks run in float64; the scene is also built and stepped in the precision
    its runs use (float32 by default): a scene that cannot work there fails in one line naming
    precision=64, and passes when its runs are asked for in float64."""
    from physgrad.check import main

    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "f64only.py").write_text(FLOAT64_ONLY_SCENE)
    (tmp_path / "conf" / "task" / "f64only.yaml").write_text(
        "_target_: f64only.build\nbatch_size: 4\ntest_size: 8\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["-cd", "conf", "task=f64only"]) == 1
    lines = capsys.readouterr().out.splitlines()
    (precision,) = [line for line in lines if line.split(":")[0].endswith("precision")]
    assert precision.startswith("FAIL") and "float32: ValueError: the data's solve" in precision
    assert "precision=64" in precision
    assert all(
        line.startswith("ok") for line in lines[:-1] if line.split()[0] not in ("FAIL", "skip")
    )
    # what was not checked is said, with why, and not counted
    skipped = [line for line in lines if line.startswith("skip")]
    assert [line.split(":")[0] for line in skipped] == ["skip  rollout", "skip  gradient M and S"]
    assert "nothing is unrolled" in skipped[0] and "closed loops only" in skipped[1]
    assert lines[-1].endswith(
        "5 of 6 checks passed; failed: precision; not checked (see above): rollout, "
        "gradient M and S"
    )
    assert main(["-cd", "conf", "task=f64only", "precision=64"]) == 0
    assert "ok    precision: the runs use float64" in capsys.readouterr().out


LIBRARY_LIKE_SCENE = """
import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene


@jax.custom_vjp
def solve(z):  # a correct derivative in reverse mode only, as diffrax's default adjoint
    return jnp.tanh(z)


def solve_fwd(z):
    return jnp.tanh(z), z


def solve_bwd(z, g):
    return ((1.0 - jnp.tanh(z) ** 2) * g,)


solve.defvjp(solve_fwd, solve_bwd)


def stepped(z):  # an adaptive solver's accepted steps: jumps that autodiff does not see
    return jnp.tanh(z) + 1e-3 * jax.lax.stop_gradient(jnp.floor(z / 3e-3))


def floor(z, rtol):  # an adaptive solver's error floor: its accepted steps move smoothly with z,
    # undifferentiated (diffrax's controllers), leaving an error of the order of its tolerance
    return jnp.tanh(z) + rtol * jax.lax.stop_gradient(jnp.sin(40.0 * z))


def build(key, *, test_size, kind, rtol=1e-5, atol=1e-5):
    dtype = jnp.zeros(()).dtype
    physics = {"reverse_only": solve, "stepped": stepped,
               "floor": lambda z: floor(z, rtol)}[kind]

    def draw(k, count, train_set=None):
        x = jax.random.uniform(k, (count, 1), dtype, -1.0, 1.0)
        return {"x": x, "target": jnp.sin(3 * x)}

    return Scene(init_params=lambda k: init_mlp(k, [1, 8, 1], dtype), draw_batch=draw,
                 test_set=draw(key, test_size),
                 sample_output=lambda params, sample: physics(
                     apply_mlp(params, sample["x"], hidden="tanh")),
                 sample_loss=lambda y, sample: 0.5 * jnp.sum((y - sample["target"]) ** 2))
"""


@pytest.mark.parametrize("kind", ["reverse_only", "stepped", "floor", "wrong", "wrong tolerances"])
def test_check_explains_reverse_only_scenes_and_gradients_that_do_not_settle(
    tmp_path, monkeypatch, capsys, kind
):
    """A scene with no forward mode (a custom_vjp) passes, its Jacobian check built in reverse
    mode and saying so; a loss with jumps autodiff does not see (an adaptive solver) fails with the
    differences at two step sizes and what to do; an error that settles but follows the scene's
    solver tolerances (task.rtol, task.atol) is the solver's error floor, not a wrong derivative;
    a wrong derivative is called off, with tolerances or without."""
    from physgrad.check import main

    (tmp_path / "conf" / "task").mkdir(parents=True)
    module = f"scene_{kind}"  # a module name of its own: the others may be imported already
    module = module.replace(" ", "_")
    if kind.startswith("wrong"):
        (tmp_path / f"{module}.py").write_text(BROKEN_SCENE)
        setting = "wrong: true" + ("\nrtol: 1.0e-5\natol: 1.0e-5" if "tolerances" in kind else "")
    else:
        (tmp_path / f"{module}.py").write_text(LIBRARY_LIKE_SCENE)
        setting = f"kind: {kind}" + ("\nrtol: 1.0e-5\natol: 1.0e-5" if kind == "floor" else "")
    (tmp_path / "conf" / "task" / "heat.yaml").write_text(
        f"_target_: {module}.build\nbatch_size: 4\ntest_size: 8\n{setting}\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    code = main(["-cd", "conf", "task=heat"])
    lines = capsys.readouterr().out.splitlines()
    gradient = next(line for line in lines if "gradient R" in line)
    jacobian = next(line for line in lines if "jacobian" in line.split(":")[0])
    if kind == "reverse_only":
        assert code == 0 and jacobian.startswith("ok") and "J v by reverse mode" in jacobian
        assert "custom_vjp" in jacobian
    elif kind == "stepped":
        assert code == 1 and gradient.startswith("FAIL") and "do not settle" in gradient
        assert "tolerances" in gradient
    elif kind == "floor":
        assert code == 1 and gradient.startswith("FAIL") and "the same at a 10x smaller" in gradient
        assert "100x tighter" in gradient and "error floor" in gradient, gradient
        assert "derivative itself is off" not in gradient
    else:
        assert code == 1 and "the derivative itself is off" in gradient
        assert ("100x tighter" in gradient) == ("tolerances" in kind), gradient
