"""physgrad.run: one configuration from Python, through the same composition, checks and training as
`physgrad run` (without Hydra's launcher, logging or .hydra/ folder)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from physgrad import UserError
from physgrad.configs import check_overrides, compose


def run_one(overrides: list[str], out_dir=None, config_dir=None):
    from omegaconf import OmegaConf, open_dict

    from physgrad.experiment import run_experiment
    from physgrad.results import read_run

    config_dirs = [config_dir] if config_dir else []
    check_overrides(overrides, multirun=False, config_dirs=config_dirs)
    cfg = compose(overrides, config_dirs=config_dirs, return_hydra_config=True)
    folder = (Path(out_dir) if out_dir else Path(OmegaConf.select(cfg, "hydra.run.dir"))).resolve()
    with open_dict(cfg):
        del cfg["hydra"]
    if os.getcwd() not in sys.path:  # a scene or optimiser named by _target_, as for `physgrad run`
        sys.path.append(os.getcwd())
    outcome, path = run_experiment(cfg, folder)
    if outcome.status == "refused":
        raise UserError(outcome.reason)
    if path.is_dir():  # seeds=N: one file per seed
        return [read_run(p) for p in sorted(path.glob("seed=*/results.h5"), key=lambda p: int(p.parent.name[5:]))]
    return read_run(path)
