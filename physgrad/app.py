"""The Hydra application behind `physgrad run`: one job = one (task, optim, seed, ...) configuration."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
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


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def job(cfg: DictConfig) -> str:
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
        return "failed"
    if outcome.status == "refused":
        if not multirun:
            print(f"physgrad: error: {outcome.reason}", file=sys.stderr)
            sys.exit(2)
        log.warning("%s skipped: %s", name, outcome.reason)
        return outcome.status
    test = outcome.final_eval.get("loss") if outcome.status == "completed" else None
    log.info("%s %s after %d iterations, %.1f s of training%s%s -> %s", name, outcome.status, outcome.iterations,
             outcome.train_seconds, f", test loss {test:.4g}" if test is not None else "",
             f" ({outcome.reason})" if outcome.reason else "", path)
    if outcome.status == "interrupted":
        sys.exit(130)
    return outcome.status
