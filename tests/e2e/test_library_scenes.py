"""Simulators from the libraries people use (examples/library_scenes/, the `sims` extra): a
pendulum controlled through diffrax's diffeqsolve (fixed and adaptive steps, the default
reverse-only adjoint, a physgrad or an equinox network) and an inverse problem through exponax's
Burgers stepper. Each passes `physgrad check` and trains with a rule of each route through it."""

from __future__ import annotations

import pytest

from physgrad.results import read_run
from tests.helpers import REPO
from tests.helpers import console as run_cli

pytest.importorskip("diffrax", reason="the sims extra (diffrax needs Python 3.11 or newer)")

pytest.importorskip("exponax")

EXAMPLE = REPO / "examples" / "library_scenes"

# one rule per way a rule goes through a scene: its gradient (Adam; gd and Muon take the same),
# values and gradients along a line search (L-BFGS), the layer-factorised Jacobian (HIG;
# Gauss-Newton and Levenberg-Marquardt take the same) and K-FAC's layer factors. What each rule
# does with them is tested for every rule in tests/numerics/test_rule_contract.py
VARIANTS = ["adam", "hig", "kfac", "lbfgs"]

SHORT = [
    "trainer.iterations=40",
    "trainer.eval_every=20",
    "task.train_size=64",
    "task.test_size=32",
    "figures=false",  # the curves are read from the results files
]


@pytest.mark.long
@pytest.mark.parametrize(
    "scene, settings, jacobian",
    [
        ("ode_control", [], "layer-factorised"),
        ("ode_control", ["task.adaptive=true"], "layer-factorised"),
        ("ode_control", ["task.network=equinox"], "per-sample: the network is an equinox module"),
        ("burgers_inverse", [], "layer-factorised"),
    ],
    ids=["diffrax-fixed", "diffrax-adaptive", "diffrax-equinox", "exponax"],
)
def test_the_library_scenes_pass_physgrad_check(scene, settings, jacobian):
    """Every check passes in float64; diffrax's default adjoint has no forward mode, so the Jacobian
    check builds its reference in reverse mode and says so; an equinox network keeps the
    per-sample Jacobian with its reason."""
    result = run_cli("check", "-cd", "conf", f"task={scene}", *settings, cwd=EXAMPLE)
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"task={scene}: 6 of 6 checks passed" in result.stdout
    line = next(x for x in result.stdout.splitlines() if x.startswith("ok    jacobian"))
    assert jacobian in line, line
    assert ("J v by reverse mode: the scene has no forward mode" in line) == (
        scene == "ode_control"
    ), line


@pytest.mark.long
@pytest.mark.parametrize("scene", ["ode_control", "burgers_inverse"])
def test_the_library_scenes_train_with_every_variant(tmp_path, scene):
    """Through the console script from the example's folder: a rule of each route through the scene
    (VARIANTS) completes, and lowers the training loss."""
    result = run_cli(
        "run",
        "-m",
        "-cd",
        "conf",
        f"task={scene}",
        f"optim={','.join(VARIANTS)}",
        *SHORT,
        f"hydra.sweep.dir={tmp_path}",
        cwd=EXAMPLE,
    )
    runs = {read_run(p).variant: read_run(p) for p in tmp_path.rglob("results.h5")}
    assert sorted(runs) == VARIANTS, result.stderr[-2000:]
    for variant, run in runs.items():
        assert run.attrs["status"] == "completed" and run.attrs["task"] == scene, (
            variant,
            run.attrs.get("reason"),
        )
        assert run.eval["loss"][-1] < run.eval["loss"][0], (variant, run.eval["loss"])


@pytest.mark.long
def test_an_adaptive_solver_and_an_equinox_network_train(tmp_path):
    """diffrax's PID controller under Gauss-Newton, and HIG on an eqx.nn.MLP (per-sample Jacobian,
    its reason in the results file)."""
    for name, settings in (
        ("adaptive", ["task.adaptive=true", "optim=gauss_newton"]),
        ("equinox", ["task.network=equinox", "optim=hig"]),
    ):
        result = run_cli(
            "run",
            "-cd",
            "conf",
            "task=ode_control",
            *settings,
            *SHORT,
            f"hydra.run.dir={tmp_path / name}",
            cwd=EXAMPLE,
        )
        run = read_run(tmp_path / name / "results.h5")
        assert run.attrs["status"] == "completed", result.stderr[-2000:]
        assert run.eval["loss"][-1] < run.eval["loss"][0], (name, run.eval["loss"])
    jacobian = read_run(tmp_path / "equinox" / "results.h5").attrs["jacobian"]
    assert "equinox module" in jacobian, jacobian
