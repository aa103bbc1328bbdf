"""Integration layer of the training loop through run_experiment: divergence kept as an outcome, a
stalled step and a failed factorisation named, iteration and time budgets, the same seed giving the
same data and curves, float64, one compilation per run, and trials trained together matching one
job each."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.errors import UserError
from physgrad.experiment import run_experiment
from physgrad.members import set_precision
from physgrad.results import read_run
from physgrad.tasks import build_scene
from tests.helpers import SimulatedClock, load

SMALL = ["task=toy", "task.test_size=8", "trainer.batch_size=4"]


def test_divergence_is_an_outcome_with_the_curve_kept(tmp_path):
    outcome, path = run_experiment(
        load("optim=gd", "optim.learning_rate=1e30", "trainer.iterations=50", *SMALL), tmp_path
    )
    run = read_run(path)
    assert outcome.status == "diverged" == run.attrs["status"]
    match = re.fullmatch(
        r"(output|loss|gradient|update) became (\S+) at iteration (\d+) \((\w+)\)",
        run.attrs["reason"],
    )
    assert match and not np.isfinite(float(match[2])), run.attrs["reason"]
    bad_iteration = int(match[3])
    assert not np.isfinite(run.train[match[4]][-1]) and np.isfinite(run.train[match[4]][:-1]).all()
    assert bad_iteration < 49
    # every row up to and including the bad one
    assert run.train["iteration"].size == bad_iteration + 1
    assert np.isfinite(run.train["loss"][0])


def test_a_run_whose_step_stalls_ends_failed_in_one_line_with_the_way_round(tmp_path, monkeypatch):
    """XLA's CPU pool wedged at the first step (every thread idle, the result never ready): the run
    ends failed, its reason one line that names the XLA option that avoids it, instead of waiting
    for ever (the job ends as on any failure: the traceback in error.txt)."""
    import threading

    import physgrad.runner as runner

    release = threading.Event()
    monkeypatch.setattr(runner, "STALL_SECONDS", 1.0)
    monkeypatch.setattr(runner, "STALL_CPU_SECONDS", 0.05)
    monkeypatch.setattr(runner, "ready", lambda step: lambda *args: release.wait(60))
    from physgrad.interrupts import StepStalled

    try:
        with pytest.raises(StepStalled):  # the job's error.txt keeps its traceback
            run_experiment(load("optim=adam", "trainer.iterations=5", *SMALL), tmp_path)
    finally:
        release.set()
    run = read_run(tmp_path / "results.h5")
    assert run.attrs["status"] == "failed" and "\n" not in run.attrs["reason"]
    assert "XLA_FLAGS=--xla_cpu_enable_concurrency_optimized_scheduler=false" in run.attrs["reason"]


@pytest.mark.long
def test_a_failed_factorisation_is_named_in_the_divergence_reason(tmp_path, monkeypatch):
    from tests.helpers import float32_factorisation_fails

    float32_factorisation_fails(monkeypatch)
    outcome, path = run_experiment(
        load("optim=hig", "optim.retry_float64=false", "trainer.iterations=5", *SMALL), tmp_path
    )
    assert outcome.status == "diverged"
    assert outcome.reason.startswith(
        "update became nan at iteration 0 (update_norm); the SVD/eigh of the Jacobian "
        "did not converge"
    )
    retried, _ = run_experiment(
        load("optim=hig", "trainer.iterations=5", *SMALL), tmp_path / "retry"
    )
    assert (
        retried.status == "completed"
        and read_run(tmp_path / "retry" / "results.h5").train["svd_failures"][-1] == 0
    )


def test_time_budget_stops_training(tmp_path):
    outcome, path = run_experiment(
        load("trainer.iterations=100000000", "trainer.time_budget=0.5", *SMALL), tmp_path
    )
    run = read_run(path)
    assert outcome.status == "completed" and run.attrs["stopped_by"] == "time_budget"
    assert 0.5 <= run.train["wall_time"][-1] == outcome.train_seconds
    assert outcome.iterations < 100000000
    # a final evaluation at the stopping point
    assert run.eval["iteration"][-1] == outcome.iterations


def test_a_time_budget_alone_runs_until_the_budget_and_passes_it_by_less_than_a_step(
    tmp_path, monkeypatch
):
    clock = SimulatedClock(monkeypatch, step=0.01)
    outcome, path = run_experiment(
        load(
            "task=toy",
            "trainer.time_budget=25",
            "trainer.eval_every=1000000",
            "trainer.flush_seconds=1",
        ),
        tmp_path,
    )
    run = read_run(path)
    assert run.attrs["stopped_by"] == "time_budget" == outcome.stopped_by
    # no hidden iteration cap (2000 is the default without a budget)
    assert outcome.iterations > 2000
    assert 25 <= outcome.train_seconds < 25 + clock.step and outcome.iterations == clock.calls
    # evaluations every budget / 20 of training time (trainer.eval_seconds=null), besides start and
    # end
    np.testing.assert_allclose(np.diff(run.eval["wall_time"])[:-1], 25 / 20, atol=clock.step + 1e-4)
    assert run.eval["iteration"][-1] == outcome.iterations


def test_the_first_step_s_one_off_cost_is_start_up_not_training(tmp_path, monkeypatch):
    SimulatedClock(monkeypatch, step=0.01, first_extra=5.0)
    outcome, path = run_experiment(
        load(
            "task=toy",
            "trainer.iterations=50",
            "trainer.eval_every=1",
            "trainer.flush_seconds=0.001",
        ),
        tmp_path,
    )
    run = read_run(path)
    assert run.attrs["first_step_overhead_seconds"] == pytest.approx(5.0, abs=1e-4)
    np.testing.assert_allclose(run.train["wall_time"], 0.01 * np.arange(1, 51), atol=1e-4)
    np.testing.assert_allclose(run.eval["wall_time"], 0.01 * np.arange(0, 51), atol=1e-4)
    assert outcome.train_seconds == pytest.approx(0.5, abs=1e-4)


def test_evaluations_by_training_time_give_a_slow_variant_a_curve(tmp_path, monkeypatch):
    SimulatedClock(monkeypatch, step=2.0)  # a step as slow as HIG's on a large scene
    outcome, path = run_experiment(
        load(
            "task=toy", "trainer.time_budget=20", "trainer.eval_every=100", "trainer.eval_seconds=3"
        ),
        tmp_path,
    )
    run = read_run(path)
    assert outcome.iterations == 10
    # every 3 s of training: after 4, 8, ... s
    assert list(run.eval["iteration"]) == [
        0,
        2,
        4,
        6,
        8,
        10,
    ]


def test_trainer_settings_resolve_iterations_and_evaluation_times():
    from physgrad.trainer_settings import DEFAULT_ITERATIONS, TrainerSettings

    def settings(**trainer):
        return TrainerSettings.from_config(
            {"eval_every": 10, "batch_size": 1, "flush_seconds": 1.0, **trainer}
        )

    assert settings().iterations == DEFAULT_ITERATIONS and settings().eval_seconds is None
    assert (
        settings(time_budget=40.0).iterations is None
        and settings(time_budget=40.0).eval_seconds == 2.0
    )
    assert settings(time_budget=40.0, iterations=5, eval_seconds=7.0).iterations == 5
    with pytest.raises(UserError, match="trainer.log_seconds=0 is not allowed"):
        settings(log_seconds=0)


def test_iterations_stop_training_and_wall_time_is_monotone(tmp_path):
    outcome, path = run_experiment(
        load("trainer.iterations=30", "trainer.eval_every=10", *SMALL), tmp_path
    )
    run = read_run(path)
    assert run.attrs["stopped_by"] == "iterations" and outcome.iterations == 30
    assert list(run.train["iteration"]) == list(range(30))
    assert np.all(np.diff(run.train["wall_time"]) > 0)
    assert list(run.eval["iteration"]) == [0, 10, 20, 30]
    np.testing.assert_array_equal(run.eval["wall_time"][1:], run.train["wall_time"][[9, 19, 29]])
    assert run.attrs["compile_seconds"] > 0
    assert run.eval["loss"][-1] < run.eval["loss"][0]  # Adam makes progress on this scene


def test_same_seed_gives_same_data_and_initial_network_for_every_variant(tmp_path):
    first = {}
    for optim in ("adam", "gd", "hig", "gauss_newton"):
        _, path = run_experiment(
            load(f"optim={optim}", "trainer.iterations=1", *SMALL), tmp_path / optim
        )
        run = read_run(path)
        first[optim] = (run.eval["loss"][0], run.train["loss"][0])
    assert len(set(first.values())) == 1, first
    _, path = run_experiment(load("seed=1", "trainer.iterations=1", *SMALL), tmp_path / "seed1")
    assert read_run(path).eval["loss"][0] != first["adam"][0]


def test_jacobian_step_logs_the_plain_gradient_and_forward_pass(x64):
    """HIG takes y and dL/dtheta = J^T g from its Jacobian pass, not from a separate backward pass:
    its logged
    loss, gradient norm and state must equal plain gradient descent's on the same batch
    (float64)."""
    from physgrad.optim import build_rule
    from physgrad.training import make_step

    cfg = load("task=oscillator", "task.train_size=16", "task.test_size=4", "trainer.batch_size=4")
    scene = build_scene(cfg.task, jax.random.PRNGKey(0))
    params = scene.init_params(jax.random.PRNGKey(1))
    logs = {}
    for optim in ("gd", "hig"):
        rule = build_rule(load(f"optim={optim}").optim)
        step = jax.jit(make_step(scene, rule, 4))
        _, _, logs[optim] = step(
            params, rule.transform.init(params), 0, jax.random.PRNGKey(2), scene.train_set
        )
    for name in ("loss", "grad_norm", "output_max_abs"):
        np.testing.assert_allclose(logs["hig"][name], logs["gd"][name], rtol=1e-10)


def test_flat_parameter_scene_computes_what_the_pytree_scene_does(x64):
    """The runner trains one flat vector per seed (Scene.over_flat_params): outputs, metrics and the
    gradients of every backprop mode must be the pytree scene's, raveled."""
    from jax.flatten_util import ravel_pytree

    from physgrad.unroll import MODES

    scene = build_scene(
        load("task=multicart", "task.poles=2", "task.test_size=4").task, jax.random.PRNGKey(0)
    )
    params = scene.init_params(jax.random.PRNGKey(1))
    flat, unravel = ravel_pytree(params)
    flat_scene = scene.over_flat_params(unravel)
    np.testing.assert_array_equal(flat_scene.init_params(jax.random.PRNGKey(1)), flat)
    for name, value in scene.evaluate(params, scene.test_set).items():
        np.testing.assert_allclose(
            flat_scene.evaluate(flat, scene.test_set)[name], value, rtol=1e-12
        )
    batch = scene.sample_train(jax.random.PRNGKey(2), 4)
    for mode in MODES.values():

        def loss(p, s):
            return s.batch_loss(
                jax.vmap(s.backprop_output(mode), in_axes=(None, 0))(p, batch), batch
            )

        np.testing.assert_allclose(
            jax.grad(loss)(flat, flat_scene),
            ravel_pytree(jax.grad(loss)(params, scene))[0],
            rtol=1e-10,
            atol=1e-14,
        )


@pytest.fixture
def restore_precision():
    previous = jax.config.jax_enable_x64
    yield
    jax.config.update("jax_enable_x64", previous)


def test_precision_64_runs_in_float64(tmp_path, restore_precision):
    cfg = load("precision=64", *SMALL)
    set_precision(64)
    scene = build_scene(cfg.task, jax.random.PRNGKey(0))
    assert scene.test_set["target"].dtype == jnp.float64
    assert all(
        leaf.dtype == jnp.float64
        for leaf in jax.tree_util.tree_leaves(scene.init_params(jax.random.PRNGKey(1)))
    )
    outcome, path = run_experiment(
        load("precision=64", "optim=hig", "trainer.iterations=3", *SMALL), tmp_path
    )
    assert outcome.status == "completed" and read_run(path).attrs["precision"] == "64"
    set_precision(32)
    assert build_scene(cfg.task, jax.random.PRNGKey(0)).test_set["target"].dtype == jnp.float32


def test_reading_a_foreign_or_corrupt_file_says_so(tmp_path):
    import h5py

    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f["x"] = [1, 2]
    (tmp_path / "corrupt.h5").write_bytes(b"not hdf5 at all")
    for name in ("foreign.h5", "corrupt.h5"):
        with pytest.raises(ValueError, match=name):
            read_run(tmp_path / name)


def test_no_recompilation_after_the_first_iteration(tmp_path):
    """The step and the evaluation compile once per run (or come from the persistent compilation
    cache the test session uses), however many iterations follow."""
    compiles = []

    def on_compile(name, duration, **kwargs):
        if name.endswith("backend_compile_duration"):
            compiles.append(name)

    def on_event(name, **kwargs):
        if name == "/jax/compilation_cache/cache_hits":
            compiles.append(name)

    overrides = [
        "task=oscillator",
        "task.closed_loop=true",
        "optim=stable_bptt",
        "task.train_size=64",
        "task.test_size=8",
        "trainer.batch_size=8",
        "unroll=16",
        "trainer.eval_every=4",
    ]
    jax.monitoring.register_event_duration_secs_listener(on_compile)
    jax.monitoring.register_event_listener(on_event)
    try:
        counts = []
        for iterations in (
            1,
            1,
            25,
        ):  # the first run also warms the caches of eager set-up operations
            compiles.clear()
            outcome, _ = run_experiment(
                load(*overrides, f"trainer.iterations={iterations}"), tmp_path / str(len(counts))
            )
            assert outcome.status == "completed"
            counts.append(len(compiles))
    finally:
        jax.monitoring.unregister_event_duration_listener(on_compile)
        jax.monitoring.unregister_event_listener(on_event)
    assert counts[1] >= 2, counts  # at least the step and the evaluation
    assert counts[2] == counts[1], counts


def test_same_seed_same_precision_gives_bitwise_identical_curves(tmp_path):
    for optim in ("adam", "hig"):
        curves = []
        for repeat in range(2):
            _, path = run_experiment(
                load(f"optim={optim}", "trainer.iterations=15", "trainer.eval_every=5", *SMALL),
                tmp_path / f"{optim}{repeat}",
            )
            run = read_run(path)
            curves.append((run.train["loss"], run.train["grad_norm"], run.eval["loss"]))
        for first, second in zip(*curves):
            np.testing.assert_array_equal(first, second)


# a Jacobian rule in make test, the others in make test-long
@pytest.mark.parametrize(
    "optim",
    [
        pytest.param("adam", marks=pytest.mark.long),
        "hig",
        pytest.param("gd", marks=pytest.mark.long),
        pytest.param("gauss_newton", marks=pytest.mark.long),
    ],
)
def test_trials_trained_together_are_the_runs_of_one_job_per_trial(tmp_path, optim):
    """trial_values trains one member per learning rate on one seed in one vectorised step: each
    member's curves equal the run of that learning rate alone (float32 round-off), and its file
    records that learning rate and no trial_values, as a job of that one trial would. The Jacobian
    rules too, with their float64 retry on (its default)."""
    rates = [1e-3, 1e-2, 0.1]
    # lambda = 1: at 0.01 HIG's tall 128 x 30 Jacobian amplifies the vmapped SVD's round-off to
    # 1e-2 of the loss in 30 steps, a difference of round-off that is not what this test is about
    common = [
        "task=toy",
        "task.scale=1",
        f"optim={optim}",
        "trainer.iterations=30",
        "trainer.eval_every=10",
    ]
    together = load(*common, f"trial_values={{learning_rate:{rates}}}")
    run_experiment(together, tmp_path / "together")
    for i, rate in enumerate(rates):
        member = read_run(tmp_path / "together" / f"trial={i}" / "results.h5")
        _, path = run_experiment(
            load(*common, f"optim.learning_rate={rate}"), tmp_path / f"alone{i}"
        )
        alone = read_run(path)
        assert member.attrs["status"] == alone.attrs["status"] == "completed"
        np.testing.assert_allclose(member.train["loss"], alone.train["loss"], rtol=1e-5)
        np.testing.assert_allclose(member.eval["loss"], alone.eval["loss"], rtol=1e-5)
        assert member.config["optim"]["learning_rate"] == rate
        assert member.config["trial_values"] is None and member.attrs["seed"] == 0
    losses = [read_run(tmp_path / "together" / f"trial={i}" / "results.h5") for i in range(3)]
    assert len({float(r.eval["loss"][-1]) for r in losses}) == 3  # three learning rates, three runs


@pytest.mark.parametrize(
    "overrides, why",
    [
        (["trial_values={learning_rate:[0.001,-1]}"], "a list of positive numbers"),
        (["trial_values={momentum:[0.1]}"], "optim.momentum is not a number"),
        (["trial_values={learning_rate:[0.1,0.2]}", "seeds=2"], "use seeds=1"),
        (
            ["optim=levenberg_marquardt", "trial_values={learning_rate:[0.1,0.2]}"],
            "cannot train trials together",
        ),
    ],
)
def test_trial_values_a_job_cannot_train_are_refused_in_one_line(tmp_path, overrides, why):
    outcome, _ = run_experiment(load("task=toy", "trainer.iterations=5", *overrides), tmp_path)
    assert outcome.status == "refused" and why in outcome.reason and "\n" not in outcome.reason
