"""The figures of a finished run: loss.png per seed and the scene's own figure of the trained
network, drawn from the results files once they are final."""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad.interrupts import StopRequest
from physgrad.results import ResultsWriter, read_params, read_run
from physgrad.runner import Outcome
from physgrad.tasks import Scene
from physgrad.training import Seeds

log = logging.getLogger("physgrad")

FIGURE_SEEDS = 8  # per-seed figures drawn for a job of many seeds (about half a second each)


def draw_run_figures(
    scene: Scene,
    seeds: Seeds,
    writers: list[ResultsWriter],
    outcomes: list[Outcome],
    stop: StopRequest | None = None,
) -> None:
    """loss.png per seed (the first FIGURE_SEEDS of a job of more: physgrad report draws them all
    together), and the scene's own figure of the trained network where it has one; none for a run
    written aside of a completed results.h5 it did not replace (the figures beside it are that
    run's). A signal (stop) ends the drawing: the results are final already."""
    from physgrad.plots import plot_run  # matplotlib only once training is over

    unravel = ravel_pytree(seeds.network())[1]
    if len(writers) > FIGURE_SEEDS:
        log.info(
            "loss.png drawn for the first %d of %d seeds: physgrad report %s draws them all",
            FIGURE_SEEDS,
            len(writers),
            writers[0].path.parent.parent,
        )
    for index, writer in enumerate(writers[:FIGURE_SEEDS]):
        if stop is not None and stop.signal_name is not None:
            return
        path = writer.path
        if writer.live != path:
            log.warning(
                "%s kept (completed); this run ended %s and is in %s",
                path,
                outcomes[index].status,
                writer.live.name,
            )
            continue
        plot_run(read_run(path), path.with_name("loss.png"))
        # a network was saved; not after an interrupt, whose user wants the process to end now (an
        # abandoned step may still hold the cores)
        if scene.figure is not None and outcomes[index].status not in ("diverged", "interrupted"):
            test_set = jax.tree_util.tree_map(lambda leaf: leaf[index], seeds.test_sets)
            scene.figure(
                unravel(jnp.asarray(read_params(path))), test_set, path.with_name("scene.png")
            )
