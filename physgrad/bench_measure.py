"""What one `make bench` subprocess measures (physgrad.bench runs each in a fresh process): the
training step of one configuration timed in turn with its baselines, the step of several seeds
vectorised against one seed's, and the eigendecomposition floors of each library."""

from __future__ import annotations

import resource
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

# runner.compile_training looked up when called: the timing tests slow its steps there
import physgrad.runner as runner
from physgrad.configs import compose
from physgrad.errors import UserError
from physgrad.nets import count_params
from physgrad.optim.spectral import resolve_route
from physgrad.results import ResultsWriter
from physgrad.runner import train
from physgrad.timing import compiled_step, interleaved_times

if TYPE_CHECKING:
    import numpy as np

    from physgrad.nets import Params
    from physgrad.optim import UpdateRule
    from physgrad.tasks import Scene
    from physgrad.trainer_settings import TrainerSettings
    from physgrad.training import Seeds


def _median_times(
    fns: list[Callable[[], object]],
    repeats: int,
    min_seconds: float,
    warmup: bool = True,
    max_seconds: float = 120.0,
) -> list[tuple[float, int]]:
    """Median wall time of each fn() (which must block until its results are ready), timed in turn
    (interleaved_times). Returns (median seconds, calls timed) per fn."""
    return [
        (statistics.median(fn_times), len(fn_times))
        for fn_times in interleaved_times(fns, repeats, min_seconds, warmup, max_seconds)
    ]


def _median_time(
    fn: Callable[[], object],
    repeats: int,
    min_seconds: float,
    warmup: bool = True,
    max_seconds: float = 120.0,
) -> tuple[float, int]:
    return _median_times([fn], repeats, min_seconds, warmup, max_seconds)[0]


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux


def measure_variant(overrides: list[str], repeats: int, min_seconds: float) -> dict:
    """Compile and time the training step of one configuration (the runner's own compiled step) in
    turn with its baselines: the bare loss-and-gradient (adam and the Jacobian variants), the
    runner's overhead (adam), and for a factorised Jacobian variant the same step with the
    per-sample Jacobian."""
    import dataclasses

    import jax
    import numpy as np

    cfg = compose(overrides)
    try:
        settings, scene, rule, seeds, compiled, compile_s, one_step = compiled_step(cfg, [cfg.seed])
    except UserError as error:
        return {"refused": str(error)}
    result = {"compile_s": compile_s}
    one_step()  # the first call reaches the step's peak memory, before any baseline is built
    result["peak_rss_gb"] = _peak_rss_gb()

    # the baselines: the scene's own functions on its own parameter pytree, as a user would write
    # them; timed in turn with the step (one call each per round), so that drift of the machine
    # cancels in the ratios
    timed = {"step_s": one_step}
    params = seeds.network()
    train_key = seeds.train_keys[0]
    if rule.uses_jacobian:
        batch = scene.sample_train(jax.random.fold_in(train_key, 0), settings.batch_size)
        shape = (jax.eval_shape(scene.batch_output, params, batch).size, count_params(params))
        result.update(
            jac_shape=list(shape),
            jacobian=rule.gradient.name,
            # K-FAC takes its step from the layers' factors, not from a route through J
            route=resolve_route(cfg.optim.route, float(cfg.optim.tau), shape)
            if "route" in cfg.optim
            else "factors",
        )
        # the per-sample Jacobian against the layer-factorised one (K-FAC needs the factors)
        if rule.gradient.plan is not None and "route" in cfg.optim:
            per_sample = runner.compile_training(
                scene,
                rule._replace(gradient=dataclasses.replace(rule.gradient, plan=None)),
                seeds,
                settings.batch_size,
            )
            state = [per_sample.params, per_sample.opt_state]

            def per_sample_step() -> None:
                state[0], state[1], _ = per_sample.step(
                    state[0], state[1], np.int32(0), seeds.train_keys, seeds.train_sets
                )
                jax.block_until_ready(state[0])

            per_sample_step()
            result["per_sample_peak_rss_gb"] = _peak_rss_gb()  # the larger of the two
            timed["per_sample_step_s"] = per_sample_step
        timed["eigh_s"] = _eigh_timer(shape[0])
    if cfg.optim.name == "adam" or rule.uses_jacobian:
        # the same function as the step's: draw the minibatch (as every step does), loss, gradient
        def loss_and_grad(p: Params, key: jax.Array) -> tuple[jax.Array, Params]:
            batch = scene.sample_train(key, settings.batch_size)
            return jax.value_and_grad(
                lambda q: scene.batch_loss(scene.batch_output(q, batch), batch)
            )(p)

        bare = jax.jit(loss_and_grad).lower(params, train_key).compile()
        timed["loss_grad_s"] = lambda: jax.block_until_ready(bare(params, train_key))
    medians = _median_times(list(timed.values()), repeats, min_seconds)
    result.update({name: seconds for name, (seconds, _) in zip(timed, medians)})
    result["steps_timed"] = medians[0][1]
    if cfg.optim.name == "adam":
        eval_s, _ = _median_time(
            lambda: jax.block_until_ready(compiled.evaluate(compiled.params, seeds.test_sets)), 3, 0
        )
        result.update(runner_overhead(settings, scene, rule, seeds, result["step_s"], eval_s))
    return result


def _random_gram(size: int) -> np.ndarray:
    import numpy as np

    factor = np.random.default_rng(0).standard_normal((size, size))
    return factor @ factor.T


def _eigh_timer(size: int) -> Callable[[], object]:
    """eigh() -> the step's own eigendecomposition (jax, float64) of a random m x m Gram matrix,
    blocking."""
    import jax
    import jax.numpy as jnp

    with jax.enable_x64(True):
        matrix = jnp.asarray(_random_gram(size))
        eigh = jax.jit(jnp.linalg.eigh).lower(matrix).compile()
    return lambda: jax.block_until_ready(eigh(matrix))


def runner_overhead(
    settings: TrainerSettings,
    scene: Scene,
    rule: UpdateRule,
    seeds: Seeds,
    step_s: float,
    eval_s: float,
) -> dict:
    """Run `train` as `physgrad run` does (default eval_every and flush cadence) for ~10 s and split
    its wall time: the timed training steps (train_seconds, which include fetching the logged
    scalars), the evaluations (count x eval_s, their median time), and the rest, which is the
    runner's own work (row buffering, HDF5 flushes, NaN checks, progress bar). Measured within one
    run, so the machine's drift between runs does not enter."""
    import dataclasses

    import h5py

    iterations = max(200, min(20_000, int(10.0 / step_s)))
    settings = dataclasses.replace(
        settings, iterations=iterations, time_budget=None, eval_seconds=None
    )
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "results.h5"
        start = time.perf_counter()
        (outcome,) = train(scene, rule, seeds, [ResultsWriter(path, {})], settings)
        total = time.perf_counter() - start
        with h5py.File(path) as f:
            start_up = float(f.attrs["compile_seconds"]) + float(
                f.attrs.get("first_step_overhead_seconds", 0.0)
            )
            evaluations = f["eval/iteration"].shape[0]
    loop = total - start_up
    rest = loop - outcome.train_seconds - evaluations * eval_s
    return {
        "overhead_iterations": iterations,
        "eval_share": evaluations * eval_s / loop,
        "runner_overhead": rest / loop,
    }


def measure_seeds(overrides: list[str], count: int, repeats: int, min_seconds: float) -> dict:
    """Seconds per iteration of one seed and of `count` seeds in one vectorised step (what
    seeds=<count> runs), timed in turn in one process."""
    cfg = compose(overrides)
    *_, single = compiled_step(cfg, [cfg.seed])
    *_, many = compiled_step(cfg, [cfg.seed + i for i in range(count)])
    (single_s, _), (many_s, _) = _median_times([single, many], repeats, min_seconds)
    return {
        "seeds": count,
        "single_step_s": single_s,
        "step_s": many_s,
        "peak_rss_gb": _peak_rss_gb(),
    }


def measure_floors(size: int, repeats: int) -> dict:
    """The float64 eigendecomposition (eigenvalues and vectors) of a random symmetric positive
    semi-definite size x size matrix, with each library that offers one: numpy (LAPACK syevd), scipy
    (syevr and syevd) and jax (compiled ahead)."""
    import numpy as np
    import scipy.linalg

    matrix = _random_gram(size)
    timed = {
        "eigh_numpy_s": lambda: np.linalg.eigh(matrix),
        "eigh_scipy_evr_s": lambda: scipy.linalg.eigh(matrix, driver="evr"),
        "eigh_scipy_evd_s": lambda: scipy.linalg.eigh(matrix, driver="evd"),
        "eigh_jax_s": _eigh_timer(size),
    }
    medians = _median_times(list(timed.values()), repeats, 0, max_seconds=60)
    return {name: seconds for name, (seconds, _) in zip(timed, medians)}


# where vectorising over seeds is measured: cheap steps, where one seed leaves the cores idle
