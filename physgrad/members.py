"""A job's members and what their files say they are: the results file of each seed or trial it
trains (seed_paths), each member's config (member_configs), the attributes its file records
(run_attributes: task, variant label, seed, precision, the config; comparable_config: the config as
a re-run compares it), the time steps it unrolls, the precision it sets and the job's outcome over
its members. The door (physgrad.job_spec) reads the config through these; nothing below it does."""

from __future__ import annotations

from pathlib import Path

import jax
from omegaconf import DictConfig, OmegaConf, open_dict

from physgrad.results import parse_config
from physgrad.runner import Outcome
from physgrad.version import __version__


def effective_unroll(cfg: DictConfig) -> int | None:
    """The number of time steps: the top-level unroll, else the scene's own; None for a scene
    without time."""
    if "unroll" not in cfg.task:
        return None
    return cfg.unroll if cfg.get("unroll") is not None else cfg.task.unroll


def set_precision(bits: int) -> None:
    """Set every time: Hydra's launchers reuse processes, so a previous job's x64 flag would
    leak."""
    jax.config.update("jax_enable_x64", bits == 64)


PRESET_BACKPROP = {"bptt": "R", "stable_bptt": "C"}


def variant_label(optim_cfg: DictConfig) -> str:
    """The optim name, plus the backprop mode and clipping where they differ from what the name
    implies (so that a report keeps `bptt` with mode M apart from plain `bptt`), spelled as
    `physgrad compare` names a variant by its overrides: e.g. `bptt backprop=M`,
    `stable_bptt clip=norm`, `lion backprop=C`."""
    name = str(optim_cfg.get("name", "?"))
    backprop, clip = optim_cfg.get("backprop"), optim_cfg.get("clip", "none")
    marks = [] if backprop == PRESET_BACKPROP.get(name) else [f"backprop={backprop}"]
    marks += [] if clip == "none" else [f"clip={clip}"]
    return " ".join([name, *marks])


def run_attributes(cfg: DictConfig, unroll: int | None = None) -> dict:
    """Root attributes of results.h5; unroll is the effective number of time steps (temporal scenes
    only)."""
    attrs = {
        "task": str(cfg.task.get("name", "?")),
        "optim": str(cfg.optim.get("name", "?")),
        "variant": variant_label(cfg.optim),
        "seed": cfg.seed if isinstance(cfg.seed, int) else str(cfg.seed),
        "precision": str(cfg.precision),
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "physgrad_version": __version__,
        "jax_version": jax.__version__,
    }
    if unroll is not None:
        attrs["unroll"] = unroll
    return attrs


# keys that do not change what a run computes (a run stored without them is the same run)
NOT_RESULT_KEYS = ("overwrite", "figures", "calibrate")


def comparable_config(cfg: DictConfig) -> dict:
    """The resolved config as plain data, as results.h5 stores it, without the keys that do not
    change what a run computes."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    for key in NOT_RESULT_KEYS:
        plain.pop(key, None)
    # the stored text's round trip: YAML's types, cleaned text
    return parse_config(OmegaConf.to_yaml(plain))


def seed_paths(cfg: DictConfig, out_dir: str | Path) -> list[tuple[int, Path]]:
    """(seed, results file) of every member a job trains: out_dir/results.h5 for one seed,
    out_dir/seed=<s>/ results.h5 for seeds > 1 (seed, seed + 1, ...), out_dir/trial=<i>/results.h5
    for the members of trial_values (all on seed)."""
    values = cfg.get("trial_values")
    if values is not None:
        count = len(next(iter(values.values())))
        return [(cfg.seed, Path(out_dir) / f"trial={i}" / "results.h5") for i in range(count)]
    count = cfg.get("seeds", 1)
    count = count if isinstance(count, int) and count > 0 else 1
    if count == 1:
        return [(cfg.seed, Path(out_dir) / "results.h5")]
    return [
        (cfg.seed + i, Path(out_dir) / f"seed={cfg.seed + i}" / "results.h5") for i in range(count)
    ]


def member_configs(cfg: DictConfig, count: int) -> list[DictConfig]:
    """The config of each of a job's count members: the job's for seeds; for trial_values (checked
    by refusals.trial_values_refusal) the job's with each key of the optim config set to the
    member's value and trial_values left out, so that its results file says what it ran, as a job
    of that one trial would."""
    values = cfg.get("trial_values")
    if values is None:
        return [cfg] * count
    members = []
    for i in range(count):
        member = cfg.copy()
        with open_dict(member):
            member.trial_values = None
            for key, per_member in values.items():
                member.optim[key] = per_member[i]
        members.append(member)
    return members


def job_outcome(outcomes: list[Outcome]) -> Outcome:
    """One outcome for a job of several seeds: the first that did not complete, else the first
    seed's."""
    if len(outcomes) == 1:
        return outcomes[0]
    worst = next((o for o in outcomes if o.status != "completed"), outcomes[0])
    reasons = "; ".join(f"seed #{i}: {o.reason}" for i, o in enumerate(outcomes) if o.reason)
    return Outcome(
        worst.status, reasons or None, worst.iterations, worst.train_seconds, outcomes[0].final_eval
    )
