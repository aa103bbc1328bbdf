"""physgrad from Python (a notebook, a script): the functions the package root hands on.

    import physgrad
    run = physgrad.run("task=oscillator", "optim=hig", "trainer.iterations=200")
    run.eval["loss"], run.train["wall_time"]          # numpy arrays
    same = physgrad.read_run(run.path)                # any results.h5, read back the same way

Each imports what it needs when called: `import physgrad` (and every `physgrad.<module>` import,
which imports the package first) stays free of JAX, Hydra and pandas, so the console script installs
its signal handlers before any of them loads.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where they are used: `import physgrad` stays light
    from physgrad.comparison.study import Study
    from physgrad.results import Run
    from physgrad.tables import Tables


def run(
    *overrides: str,
    out_dir: str | os.PathLike | None = None,
    config_dir: str | os.PathLike | None = None,
    progress: Callable[[str], object] | bool = True,
) -> Run | list[Run]:
    """Train one configuration, given as the overrides `physgrad run` takes (e.g. "task=poisson",
    "optim=hig", "trainer.iterations=100"), and return its results (physgrad.results.Run: attributes
    and the /train and /eval columns as numpy arrays; a list of them, one per seed, with seeds=N >
    1).

    out_dir: the run's folder (default: outputs/runs/<date>/<time>_<task>_<optim>_s<seed>, as
    `physgrad run`); config_dir: a folder of your own configs (like `physgrad run -cd DIR`). A
    configuration that does not apply raises UserError with the reason; a run that diverges or is
    interrupted returns with that status. It goes through the same composition, checks and training
    as `physgrad run`, without Hydra's launcher, logging or .hydra/ folder. progress: what the
    console shows (a bar on a terminal; else a line when it has compiled and every
    trainer.log_seconds: iteration, loss, training time) goes to stderr (True), to a function of
    one line, or nowhere (False); a handler the caller gave the "physgrad" logger gets it
    instead."""
    from omegaconf import OmegaConf, open_dict

    from physgrad.configs import checked_config
    from physgrad.errors import UserError
    from physgrad.experiment import run_experiment
    from physgrad.results import member_order, read_run

    config_dirs = [config_dir] if config_dir else []
    cfg = checked_config(list(overrides), config_dirs)
    folder = (Path(out_dir) if out_dir else Path(OmegaConf.select(cfg, "hydra.run.dir"))).resolve()
    with open_dict(cfg):
        del cfg["hydra"]
    if os.getcwd() not in sys.path:  # a scene or optimiser named by _target_, as for `physgrad run`
        sys.path.append(os.getcwd())
    with _progress_lines(progress):
        outcome, path = run_experiment(cfg, folder)
    if outcome.status == "refused":
        raise UserError(outcome.reason)
    if path.is_dir():  # seeds=N: one file per seed
        return [read_run(p) for p in sorted(path.glob("seed=*/results.h5"), key=member_order)]
    return read_run(path)


@contextmanager
def _progress_lines(progress: Callable[[str], object] | bool) -> Iterator[None]:
    """The "physgrad" logger's lines (a run's progress without a terminal) to stderr or to a
    function while inside, unless the caller gave that logger a handler of its own; nothing is
    added for progress=False."""
    import logging

    logger = logging.getLogger("physgrad")
    if progress is False or logger.handlers:
        yield
        return

    class Lines(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            line = self.format(record)
            if progress is True:
                print(line, file=sys.stderr, flush=True)
            else:
                progress(line)

    handler, level = Lines(), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def compare(
    *overrides: str,
    config_dir: str | os.PathLike | None = None,
    progress: Callable[[str], object] | bool = True,
) -> Study:
    """Which variant trains this scene best, as `physgrad compare` decides it (tuned with equal
    budgets, paired seeds, verdicts with intervals; docs/protocol.md), e.g.
    ``physgrad.compare("task=toy", "optim=adam,hig", "trainer.iterations=300",
    "compare.trials=8")``. Returns physgrad.comparison.Study: .comparisons, .runs and .trials
    (pandas DataFrames), .verdicts, .text (the compare.md table) and .folder. An interrupted study
    resumes when called again with the same overrides. progress: the console's progress lines
    (each phase, its job and loss so far) go to stderr as `physgrad compare` prints them (True),
    to a function of one line, or nowhere (False)."""
    from physgrad.comparison import run_study

    if progress is True:
        say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    elif progress is False:
        say = lambda line: None  # noqa: E731
    else:
        say = progress
    folder = None if config_dir is None else str(config_dir)
    return run_study(list(overrides), config_dir=folder, say=say)


def read_runs(
    paths: Iterable[str | Path] | str | os.PathLike, threshold: float | None = None
) -> Tables:
    """Every run under the given results files or folders (LABEL=PATH sets too; one path alone, or a
    list) as two pandas DataFrames: ``runs, curves =
    physgrad.read_runs("outputs/multirun/...")``. runs: one row per run, every setting in a
    column of its own (optim.learning_rate, task.poles, trainer.iterations, ..., seed, status,
    the machine) and the run's record at its budget (test_loss_at_1, time_to_target, ...:
    readout.run_record); curves: one row per run, split and iteration with the run's id and
    label, variant, seed, ..., so that e.g.
    ``seaborn.lineplot(curves.query("split == 'eval'"), x="wall_time", y="loss", hue="label")``
    needs no merge. See docs/results.md."""
    from physgrad.report import read_runs as read

    return read(paths, threshold)


def read_run(path: str | os.PathLike) -> Run:
    """One results.h5 read back: attributes (run.attrs) and the /train and /eval columns
    (run.train["loss"], run.eval["wall_time"], ...) as numpy arrays."""
    from physgrad.results import read_run as read

    return read(path)
