"""The Hydra application behind `physgrad run`: one job = one (task, optim, seed, ...) configuration."""

from __future__ import annotations

import logging
import sys
from collections import Counter
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig

from physgrad.configs import CONF_DIR
from physgrad.experiment import run_experiment

log = logging.getLogger("physgrad")


def record_failure(cfg: DictConfig, out_dir: Path, error: Exception) -> None:
    """Make sure a failed job leaves a results file per seed that says so (training records its own failures;
    this covers errors before it starts)."""
    from physgrad.experiment import run_attributes, seed_paths
    from physgrad.results import ResultsWriter, read_final

    for seed, path in seed_paths(cfg, out_dir):
        try:
            if read_final(path)[0].get("status") == "failed":
                continue
        except (ValueError, OSError):
            pass
        ResultsWriter(path, {**run_attributes(cfg), "seed": seed}).finish(
            "failed", f"{type(error).__name__}: {error}".splitlines()[0])


OUTCOMES = ("completed", "diverged", "refused")  # what an experiment can find; anything else is a failure
FAILED_JOBS: list[int] = []  # set by SweepSummary at the end of a sweep: `physgrad run -m` exits 1 if non-zero


class SweepSummary(Callback):
    """At the end of a sweep (in the process that launched it, whatever the launcher): the runs it wrote under
    the sweep folder counted by status, the folder, and the report command to run next. A failed run makes
    `physgrad run -m` exit with status 1; refused and diverged runs are outcomes, not failures."""

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        from physgrad.results import find_results

        folder = Path(str(config.hydra.sweep.dir))
        # what was there before: a file counts as this sweep's if it is new or was written since
        self.before = {path: path.stat().st_mtime_ns for path in find_results([folder])} if folder.is_dir() else {}
        FAILED_JOBS.clear()

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        from physgrad.results import find_results, read_final

        folder = Path(str(config.hydra.sweep.dir))
        written, earlier = Counter(), 0
        for path in find_results([folder]) if folder.is_dir() else []:
            try:
                status = read_final(path)[0].get("status", "?")
            except ValueError:
                status = "unreadable"
            if getattr(self, "before", {}).get(path) != path.stat().st_mtime_ns:
                written[status] += 1
            else:
                earlier += 1  # untouched by this sweep: completed before with the same config, or another job's
        # a run left running (its worker was killed), interrupted, failed or unreadable is a failure
        FAILED_JOBS[:] = [sum(n for status, n in written.items() if status not in OUTCOMES)]
        counts = ", ".join(f"{n} {status}" for status, n in sorted(written.items())) or "no runs written"
        skipped = f"; {earlier} untouched (completed before: skipped)" if earlier else ""
        log.info("sweep finished: %s%s in %s; next: physgrad report %s", counts, skipped, folder, folder)


def objective(outcome) -> float:
    """What the job returns to the sweeper, for those that optimise (hydra/sweeper=optuna): the final test loss
    of a completed run (a budgeted run's last evaluation is at its budget); infinity for anything else, so a
    diverged, refused or failed trial ranks last instead of stopping the study."""
    loss = outcome.final_eval.get("loss") if outcome.status == "completed" else None
    return float(loss) if loss is not None else float("inf")


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def job(cfg: DictConfig) -> float:
    hydra_cfg = HydraConfig.get()
    # a scene or optimiser named by _target_ may live in the folder the command was started from, also when a
    # launcher runs this job in another process
    if hydra_cfg.runtime.cwd not in sys.path:
        sys.path.append(hydra_cfg.runtime.cwd)
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    name = f"{cfg.task.get('name')}/{cfg.optim.get('name')} seed {cfg.seed}"
    try:
        outcome, path = run_experiment(cfg, hydra_cfg.runtime.output_dir)
    except Exception as error:  # noqa: BLE001 - one failed job must not end a sweep
        if not multirun:
            raise
        record_failure(cfg, Path(hydra_cfg.runtime.output_dir), error)
        log.error("%s failed: %s: %s", name, type(error).__name__, error)
        return float("inf")
    if outcome.status == "refused":
        if not multirun:
            print(f"physgrad: error: {outcome.reason}", file=sys.stderr)
            sys.exit(2)
        log.warning("%s skipped: %s", name, outcome.reason)
        return objective(outcome)
    test = outcome.final_eval.get("loss") if outcome.status == "completed" else None
    stopped = f" (stopped by {outcome.stopped_by.replace('_', ' ')})" if outcome.stopped_by else ""
    log.info("%s %s after %d iterations%s, %.1f s of training%s%s -> %s", name, outcome.status, outcome.iterations,
             stopped, outcome.train_seconds, f", test loss {test:.4g}" if test is not None else "",
             f" ({outcome.reason})" if outcome.reason else "", path)
    if outcome.status == "interrupted":
        sys.exit(130)
    return objective(outcome)
