"""Integration layer of the configs: every task and optim has one, each pair of the short set runs
two iterations or is refused with its reason, per-scene settings come from the configs, bad values
are refused with the key, and variant labels keep BPTT modes and clipping apart."""

import numpy as np
import pytest

from physgrad.configs import CONF_DIR
from physgrad.experiment import run_experiment
from physgrad.results import read_run
from tests.helpers import load

TASKS = sorted(p.stem for p in (CONF_DIR / "task").glob("*.yaml"))

OPTIMS = sorted(p.stem for p in (CONF_DIR / "optim").glob("*.yaml"))

# smaller than the reference sizes, so that 2 iterations of every pair stay cheap
SMALL = {
    "poisson": ["task.grid=4", "task.test_size=8", "trainer.batch_size=4"],
    # the reference unroll length: on very short ones (unroll=24) Gauss-Newton's first step blows
    # the physics up the tuned batch sizes (GD at lr 1e-3 with the closed-loop controller is
    # unstable on batches of 16 or 64)
    "oscillator": ["task.train_size=512", "task.test_size=8"],
    "multicart": ["task.poles=2", "task.train_size=16", "task.test_size=8", "unroll=20"],
    # 8 steps: the Jacobian rules' J grows with the steps whose loss counts (quantum control sums
    # every step's), and at 32 steps and a batch of 4 one pair took 24 s (2.8 s at 8 and 2)
    "quantum": ["task.train_size=32", "task.test_size=8", "trainer.batch_size=4", "unroll=8"],
    "quantum_control": [
        "task.train_size=16",
        "task.test_size=8",
        "trainer.batch_size=2",
        "unroll=8",
    ],
    "toy": ["task.test_size=8", "trainer.batch_size=4"],
    "guidance": ["task.train_size=16", "task.test_size=8", "unroll=12", "trainer.batch_size=4"],
    "ks": [
        "task.channels=3",
        "task.blocks=1",
        "task.train_steps=30",
        "task.warmup=20",
        "task.test_count=2",
        "task.test_steps=24",
        "task.horizon=4",
        "task.long_horizon=12",
        "trainer.batch_size=4",
    ],
}

# every scene as configured by default, plus the settings that change which variants apply
SCENES = [(task, []) for task in TASKS] + [
    ("oscillator", ["task.closed_loop=true"]),
    ("quantum", ["task.closed_loop=true"]),
    ("ks", ["task.training=ONE", "task.stepper=predict"]),
]

CLOSED_LOOP = {
    "multicart",
    "quantum_control",
    "guidance",
    "ks",
    "ks task.training=ONE task.stepper=predict",
    "oscillator task.closed_loop=true",
    "quantum task.closed_loop=true",
}


def test_every_task_and_optim_has_a_config():
    assert set(TASKS) >= {
        "poisson",
        "oscillator",
        "quantum",
        "quantum_control",
        "multicart",
    } and set(SMALL) == set(TASKS)
    assert set(OPTIMS) == {
        "adam",
        "gd",
        "gauss_newton",
        "hig",
        "bptt",
        "stable_bptt",
        "levenberg_marquardt",
        "lbfgs",
        "muon",
        "kfac",
        "soap",
        "psgd_kron",
        "ssbfgs",
        "ssbroyden",
    }


# make test's pairs: every scene and every optim at least once, and each kind of refusal, chosen
# where they cost least (the dense and line-search rules on the toy, where a step is cheap; the
# scenes that draw figures of their own once each); make test-long runs every other pair
SHORT = {
    "toy": ("lbfgs", "ssbfgs", "ssbroyden", "psgd_kron", "levenberg_marquardt", "bptt"),
    "poisson": ("hig",),
    "oscillator": ("gd",),
    "quantum": ("kfac",),
    "quantum_control": ("bptt",),
    "multicart": ("gauss_newton", "kfac"),
    "guidance": ("stable_bptt", "ssbfgs"),
    "ks": ("gd",),
    "oscillator task.closed_loop=true": ("muon",),
    "quantum task.closed_loop=true": ("soap",),
    "ks task.training=ONE task.stepper=predict": ("adam",),
}


def pairs():
    """Every scene x optim pair; `make test` runs the SHORT ones, `make test-long` the rest."""
    return [
        pytest.param(
            task,
            settings,
            optim,
            id="-".join([" ".join([task, *settings]), optim]),
            marks=() if optim in SHORT.get(" ".join([task, *settings]), ()) else pytest.mark.long,
        )
        for task, settings in SCENES
        for optim in OPTIMS
    ]


def test_the_short_set_has_every_scene_every_optim_and_every_refusal():
    short = [p.values for p in pairs() if not p.marks]
    assert len(short) == sum(len(optims) for optims in SHORT.values())
    assert {(task, tuple(settings)) for task, settings, _ in short} == {
        (task, tuple(settings)) for task, settings in SCENES
    }
    assert {optim for _, _, optim in short} == set(OPTIMS)
    chosen = {(" ".join([task, *settings]), optim) for task, settings, optim in short}
    # bptt without a controller in the loop, K-FAC where the controller runs many times per
    # sample, a dense rule above max_parameters
    assert {("toy", "bptt"), ("multicart", "kfac"), ("guidance", "ssbfgs")} <= chosen


@pytest.mark.parametrize("task, settings, optim", pairs())
def test_pair_runs_two_iterations_or_is_refused(task, settings, optim, tmp_path, request):
    # what runs is checked here, not stability: at these small sizes Gauss-Newton's second guidance
    # step raises the loss 1e5-fold, which the blow-up bound (tested in test_compare) would rightly
    # end as diverged. The figures of a run are drawn where the scene draws one of its own (they
    # cost more than the two iterations) and for poisson, once per scene: in the short set, with
    # the scene's default settings
    short = request.node.get_closest_marker("long") is None
    figures = short and not settings and task in ("guidance", "ks", "poisson")
    cfg = load(
        f"figures={str(figures).lower()}",
        f"task={task}",
        f"optim={optim}",
        "trainer.iterations=2",
        "trainer.eval_every=1",
        *SMALL[task],
        *settings,
        "trainer.divergence_factor=null",
    )
    outcome, path = run_experiment(cfg, tmp_path)
    run = read_run(path)
    assert run.attrs["status"] == outcome.status
    if optim in ("bptt", "stable_bptt") and " ".join([task, *settings]) not in CLOSED_LOOP:
        assert outcome.status == "refused"
        assert f"optim={optim}" in outcome.reason and f"task={task}" in outcome.reason
        assert run.attrs["reason"] == outcome.reason
    elif optim == "kfac" and " ".join([task, *settings]) in CLOSED_LOOP:
        # the closed-loop controller (and ks's convolutional network) is applied many times per
        # sample: no layer factors for K-FAC's Kronecker products
        assert outcome.status == "refused" and "layer factors" in outcome.reason, outcome.reason
        assert f"task={task}" in outcome.reason and "\n" not in outcome.reason
    elif optim in ("ssbfgs", "ssbroyden") and outcome.status == "refused":
        # a dense n x n inverse Hessian: refused above optim.max_parameters (multicart, guidance,
        # quantum control at these sizes), in one line that names the count and the key
        count = int(outcome.reason.split(" parameters")[0].rsplit(" ", 1)[1])
        assert count > 8192 and "optim.max_parameters=8192" in outcome.reason, outcome.reason
        assert "\n" not in outcome.reason
    else:
        assert outcome.status == "completed", outcome.reason
        assert list(run.train["iteration"]) == [0, 1]
        assert list(run.eval["iteration"]) == [0, 1, 2]
        assert (tmp_path / "loss.png").exists() == figures
        # a scene with a per-run figure (Scene.figure) draws it beside loss.png; the others draw
        # none
        assert (tmp_path / "scene.png").exists() == (figures and task in ("guidance", "ks"))
        assert ("unroll" in run.attrs) == (task not in ("poisson", "toy"))
        if optim == "stable_bptt":  # the combined gradient's diagnostics are logged per iteration
            assert (
                0 <= run.train["zeroed_fraction"].min() <= run.train["zeroed_fraction"].max() <= 1
            )
            assert np.all(np.abs(run.train["cos_physics_regular"]) <= 1 + 1e-6)


def test_per_scene_variant_settings_come_from_config():
    osc = {o: load("task=oscillator", f"optim={o}") for o in ("adam", "hig", "gauss_newton")}
    assert (osc["adam"].optim.learning_rate, osc["adam"].trainer.batch_size) == (3e-4, 512)
    assert (
        osc["hig"].optim.learning_rate,
        osc["hig"].optim.tau,
        osc["hig"].trainer.batch_size,
    ) == (1.0, 1e-6, 128)
    assert (osc["gauss_newton"].optim.learning_rate, osc["gauss_newton"].trainer.batch_size) == (
        1.0,
        128,
    )
    quantum = {o: load("task=quantum", f"optim={o}") for o in ("adam", "hig")}
    assert (quantum["adam"].optim.learning_rate, quantum["adam"].trainer.batch_size) == (5e-4, 256)
    assert (
        quantum["hig"].optim.learning_rate,
        quantum["hig"].optim.tau,
        quantum["hig"].trainer.batch_size,
    ) == (0.5, 1e-5, 16)
    for optim in ("adam", "bptt", "stable_bptt"):
        control = load("task=quantum_control", f"optim={optim}")
        assert (control.optim.learning_rate, control.trainer.batch_size, control.task.unroll) == (
            1e-3,
            8,
            128,
        )
    assert load("optim=adam").optim.learning_rate == 3e-4
    hig = load("optim=hig")
    assert (hig.optim.learning_rate, hig.optim.tau, hig.optim.kappa, hig.trainer.batch_size) == (
        0.64,
        1e-5,
        0.5,
        64,
    )
    # the command line wins
    assert load("optim=hig", "optim.learning_rate=0.1").optim.learning_rate == 0.1
    assert load("optim=gauss_newton").optim.kappa == 1.0
    # the batch size has one source, task.batch_size, and trainer.batch_size overrides it
    assert load("task=oscillator", "optim=hig", "task.batch_size=64").trainer.batch_size == 64
    assert load("task=oscillator", "optim=hig", "trainer.batch_size=32").trainer.batch_size == 32


def test_unroll_on_a_scene_without_time_is_refused(tmp_path):
    outcome, path = run_experiment(load("unroll=32"), tmp_path)
    assert outcome.status == "refused"
    assert "no time axis" in outcome.reason and "unroll=32" in outcome.reason
    assert "unroll" not in read_run(path).attrs


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("trainer.iterations=0", "trainer.iterations=0"),
        ("trainer.iterations=abc", "whole number"),
        ("optim.learning_rate=-1", "optim.learning_rate=-1"),
        ("optim.learning_rate=nan", "optim.learning_rate=nan"),
        ("trainer.time_budget=inf", "trainer.time_budget=inf"),
        ("task.smoothness=-inf", "task.smoothness=-inf"),
        ("precision=16", "choose one of 32, 64"),
        ("trainer.time_budget=0", "trainer.time_budget"),
    ],
)
def test_bad_values_are_refused_with_the_key(override, fragment, tmp_path):
    outcome, _ = run_experiment(load(override), tmp_path)
    assert outcome.status == "refused"
    assert fragment in outcome.reason and "\n" not in outcome.reason


def test_hig_tau_out_of_range(tmp_path):
    outcome, _ = run_experiment(load("optim=hig", "optim.tau=1.5"), tmp_path)
    assert outcome.status == "refused" and "optim.tau" in outcome.reason


def test_bad_scene_settings_are_refused(tmp_path):
    for override, fragment in [
        ("task.closed_loop=closed", "task.closed_loop='closed' is not allowed"),
        ("task.dt=0", "task.dt=0"),
        ("unroll=0", "unroll=0"),
        ("trainer.batch_size=10000", "at most 4096"),
    ]:
        outcome, _ = run_experiment(load("task=oscillator", override), tmp_path / override)
        assert outcome.status == "refused" and fragment in outcome.reason, (
            override,
            outcome.reason,
        )


def test_variant_labels_keep_bptt_modes_and_clipping_apart():
    from physgrad.members import variant_label

    def label(*overrides):
        return variant_label(load("task=multicart", *overrides).optim)

    assert label("optim=bptt") == "bptt" and label("optim=stable_bptt") == "stable_bptt"
    assert label("optim=bptt", "optim.backprop=M") == "bptt backprop=M"
    assert label("optim=stable_bptt", "optim.clip=norm") == "stable_bptt clip=norm"
    assert label("optim=bptt", "optim.backprop=C", "optim.clip=value") == (
        "bptt backprop=C clip=value"
    )
    # the spelling of physgrad compare's name for the variant of those overrides
    from physgrad.comparison.spec import variant_name

    overrides = ["optim=bptt", "optim.backprop=C", "optim.clip=value"]
    assert variant_name(overrides) == label(*overrides)
    assert label("optim=hig") == "hig"


def test_bptt_on_an_open_loop_controller_says_how_to_fix_it(tmp_path):
    outcome, _ = run_experiment(load("task=oscillator", "optim=stable_bptt"), tmp_path)
    assert outcome.status == "refused" and "set task.closed_loop=true" in outcome.reason
