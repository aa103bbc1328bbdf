"""The Hydra application behind `physgrad run`: one job = one (task, optim, seed, ...) configuration."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from physgrad.experiment import run_experiment

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
log = logging.getLogger("physgrad")


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def job(cfg: DictConfig) -> str:
    hydra_cfg = HydraConfig.get()
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    outcome, path = run_experiment(cfg, hydra_cfg.runtime.output_dir)
    name = f"{cfg.task.name}/{cfg.optim.name} seed {cfg.seed}"
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
