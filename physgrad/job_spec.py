"""A job's configuration checked once, at the door (check): the composed Hydra config in, typed
and frozen settings out (JobSpec), or the refusal that says what to change (Refusal). Every check
that reads the config alone runs here: the run's own keys (top level and trainer; NaN and infinity
anywhere), the names that label results, the seeds, the unroll length, the trial values and the
clock's charges for the rule. Below the door nothing reads the config: the run
(physgrad.experiment) takes the JobSpec, whose task and optim sections are plain data handed to the
scene's build function and the rule's factory, which check their own keys when they build.
Refusals that need the built scene (a mode that does not apply, a network without matrices) are
physgrad.refusals'."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from physgrad.errors import UserError
from physgrad.members import (
    comparable_config,
    effective_unroll,
    member_configs,
    run_attributes,
    seed_paths,
)
from physgrad.optim.capabilities import capabilities, scheduled_update
from physgrad.trainer_settings import TrainerSettings
from physgrad.validate import choice, finite_numbers, flag, number, targets_by_name

SEED_LIMIT = 2**32
# seeds trained together in one vectorised step: each has its own data, network and results file, so
# memory and the files grow with it; more seeds than this are a sweep (seed=0,1,... -m), which also
# runs in parallel
SEEDS_LIMIT = 1024


@dataclass(frozen=True)
class Member:
    """One member of a job, a seed or one trial of trial_values: its seed, its results file
    relative to the job folder, the attributes its file records (members.run_attributes: the
    task, variant, seed, precision and the member's resolved config), and that config as plain
    data (what a re-run compares with the file's, physgrad.resume)."""

    seed: int
    path: Path
    attributes: dict
    config: dict


@dataclass(frozen=True)
class JobSpec:
    """A job's settings, checked: the scene's section (task) and the rule's (optim), resolved into
    plain data; the trainer's, typed (TrainerSettings, with the rule's update schedule where the
    clock charges one); the seeds (seed, and one Member per seed or trial); the precision (32 or
    64 bits); the effective number of time steps (None for a scene without time); whether held-out
    validation data are built; the trial values (optim key -> one value per member) or None; the
    results file a network starts from (init_from) or None; overwrite and figures; the experiment
    trackers of logger=... (name -> its settings, plain data, built by physgrad.trackers)."""

    task: dict
    optim: dict
    trainer: TrainerSettings
    seed: int
    precision: int
    unroll: int | None
    validation: bool
    trial_values: dict[str, tuple[float, ...]] | None
    init_from: str | None
    overwrite: bool
    figures: bool
    members: tuple[Member, ...]
    trackers: dict[str, dict] = dataclasses.field(default_factory=dict)

    @property
    def task_name(self) -> str:
        return str(self.task["name"])

    @property
    def rule_name(self) -> str:
        return str(self.optim["name"])

    @property
    def label(self) -> str:
        """The job as a console line names it: task/optim seed s (+ the other members)."""
        more = f" (+{len(self.members) - 1})" if len(self.members) > 1 else ""
        return f"{self.task_name}/{self.rule_name} seed {self.seed}{more}"

    def paths(self, out_dir: str | Path) -> list[tuple[int, Path]]:
        """(seed, results file) of every member, in the job folder out_dir."""
        return [(m.seed, Path(out_dir) / m.path) for m in self.members]

    def scene_key(self, seeds: list[int]) -> str:
        """What the scene and seeds are built from, as text: two jobs with one key build the same
        scene and seeds (the task, precision, unroll, validation data and the seeds)."""
        return json.dumps(
            [self.task, self.precision, self.unroll, self.validation, list(seeds)],
            sort_keys=True,
            default=str,
        )


@dataclass(frozen=True)
class Refusal:
    """A job the door refused: why (one line that says what to change), and the members whose
    results files say so (none where the job is refused before one file per member is named: too
    many seeds, trial values that name no member)."""

    reason: str
    members: tuple[Member, ...]
    trackers: dict[str, dict] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class Calibration:
    """A study's calibration job (calibrate={variant: config}): each variant's whole run config,
    resolved into plain data, and the seed its step costs are measured on."""

    configs: dict[str, dict]
    seed: int


def check(cfg: DictConfig) -> JobSpec | Refusal:
    """The door: the composed config checked into a JobSpec, or the Refusal that says why not."""
    why = too_many_seeds(cfg) or trial_values_refusal(cfg)
    try:
        trackers = tracker_settings(cfg)
    except UserError as error:
        why = why or str(error)
        trackers = {}
    if why is not None:
        return Refusal(why, (), trackers)
    members = _members(cfg)
    why = targets_refusal(cfg)
    if why is not None:
        return Refusal(why, members, trackers)
    try:
        trainer = check_config(cfg)
    except UserError as error:
        return Refusal(str(error), members, trackers)
    values = cfg.get("trial_values")
    return JobSpec(
        task=OmegaConf.to_container(cfg.task, resolve=True),
        optim=OmegaConf.to_container(cfg.optim, resolve=True),
        trainer=trainer,
        seed=int(cfg.seed),
        precision=int(cfg.precision),
        unroll=effective_unroll(cfg),
        validation=bool(cfg.trainer.get("validation", False)),
        trial_values=(
            None
            if values is None
            else {str(k): tuple(float(v) for v in vs) for k, vs in values.items()}
        ),
        init_from=cfg.get("init_from") or None,
        overwrite=bool(cfg.get("overwrite", False)),
        figures=bool(cfg.get("figures", True)),
        members=members,
        trackers=trackers,
    )


def targets_refusal(cfg: DictConfig) -> str | None:
    """Why the task's or the rule's `_target_`s (nested ones included) are refused, by their names
    alone (validate.allowed_target: nothing is imported), or None. The functions they import to
    are looked at again as they are built (validate.call_target); the trackers' as they are built,
    right after the door; Hydra's own sections before Hydra composes (configs.py), since Hydra
    calls them before any job starts."""
    for section in ("task", "optim"):
        node = cfg.get(section)
        if not isinstance(node, DictConfig):
            continue
        try:
            tree = OmegaConf.to_container(node, resolve=True)
        except Exception:  # noqa: BLE001 - an interpolation that does not resolve: check_config says so
            continue
        try:
            targets_by_name(section, tree)
        except UserError as error:
            return str(error)
    return None


def tracker_settings(cfg: DictConfig) -> dict[str, dict]:
    """logger=...: each tracker's settings (name -> its node, resolved; entries that are not a
    mapping, as a tracker switched off with null, are left out); UserError when the section is
    not a mapping."""
    logger = cfg.get("logger")
    if not logger:
        return {}
    if not isinstance(logger, DictConfig):
        raise UserError(
            f"logger={logger!r}: give a mapping of tracker name -> settings (logger=tensorboard; "
            "see docs/configuration.md), or leave it out"
        )
    nodes = OmegaConf.to_container(logger, resolve=True)
    return {str(name): node for name, node in nodes.items() if isinstance(node, dict)}


def calibration_of(cfg: DictConfig) -> Calibration | None:
    """A calibration job's request (calibrate={variant: config}), or None for a training job;
    UserError when calibrate is not such a mapping."""
    configs = cfg.get("calibrate")
    if configs is None:
        return None
    if not isinstance(configs, DictConfig) or not all(
        isinstance(config, DictConfig) for config in configs.values()
    ):
        raise UserError("calibrate: give a mapping of variant -> its whole run config")
    return Calibration(
        {str(name): OmegaConf.to_container(c, resolve=True) for name, c in configs.items()},
        int(cfg.seed),
    )


def checked(cfg: DictConfig) -> JobSpec:
    """check for a caller that builds or times a config outside a job (a study's plan, the
    calibration, the benchmarks): the JobSpec, or UserError with the refusal's reason."""
    spec = check(cfg)
    if isinstance(spec, Refusal):
        raise UserError(spec.reason)
    return spec


def _members(cfg: DictConfig) -> tuple[Member, ...]:
    """Every member of the job, named as its files are (members.seed_paths), each with what its
    file records; read leniently, as a refused job's files record it too."""
    paths = seed_paths(cfg, ".")
    unroll = effective_unroll(cfg) if "task" in cfg else None
    described = {}  # the seeds of a job share one config: described once, not once per seed
    members = []
    for (seed, path), member in zip(paths, member_configs(cfg, len(paths))):
        if id(member) not in described:
            described[id(member)] = (run_attributes(member, unroll), comparable_config(member))
        attributes, config = described[id(member)]
        members.append(Member(seed, Path(*path.parts), {**attributes, "seed": seed}, config))
    return tuple(members)


def check_config(cfg: DictConfig) -> TrainerSettings:
    """The run's own keys (top level and trainer) validated, NaN and infinity refused everywhere,
    and an unroll length refused for a scene without time (its task config has no `unroll`). The
    task and optim settings are checked by the code that reads them (the scene's build function, the
    update rule's factory)."""
    finite_numbers(OmegaConf.to_container(cfg, resolve=True))
    choice("precision", cfg.get("precision"), (32, 64))
    flag("overwrite", cfg.get("overwrite"))
    flag("figures", cfg.get("figures", True))
    flag("trainer.validation", cfg.trainer.get("validation", False))
    if cfg.get("init_from") is not None and (
        not isinstance(cfg.init_from, str) or not cfg.init_from.strip()
    ):
        raise UserError(
            f"init_from={cfg.init_from!r} is not allowed: use the path of a results.h5, or leave "
            "init_from out (null) to start from a fresh network"
        )
    check_seeds(cfg)
    for section in ("task", "optim"):
        if not isinstance(cfg[section].get("name"), str) or not cfg[section].name:
            raise UserError(
                f"the {section} config has no name: add one (e.g. name: mine), it labels results"
            )
    check_unroll(cfg)
    return with_scheduled_update(TrainerSettings.from_config(cfg.trainer), cfg.optim)


def with_scheduled_update(settings: TrainerSettings, optim_cfg: Any) -> TrainerSettings:
    """settings with the rule's update schedule attached where trainer.update_cost charges one; a
    cost given for a rule without one (or trainer.evaluation_cost for a rule that searches no
    line) is refused (its calibration was another rule's). Trials cannot vary the schedule:
    trial_values sets numbers only, and a number fixes the probability, which leaves no
    schedule."""
    if settings.evaluation_cost is not None and not capabilities(optim_cfg).line_search:
        raise UserError(
            f"trainer.evaluation_cost={settings.evaluation_cost:g} charges a line search's "
            f"evaluations, and optim={optim_cfg.get('name')} searches no line: leave "
            "trainer.evaluation_cost and trainer.step_evaluations out (null)"
        )
    if settings.update_cost is None:
        return settings
    schedule = scheduled_update(optim_cfg)
    if schedule is None:
        raise UserError(
            f"trainer.update_cost={settings.update_cost:g} charges a scheduled update, and "
            f"optim={optim_cfg.get('name')} has none (only psgd_kron with "
            "preconditioner_update_probability=null does): leave it out (null)"
        )
    return dataclasses.replace(settings, scheduled_update=schedule)


def check_seeds(cfg: DictConfig) -> None:
    """seed and seeds: integers, seeds at most SEEDS_LIMIT, and every seed below 2^32."""
    # PRNGKey(seed) keeps the low 32 bits of the seed: seeds 2^32 apart would be the same run
    number("seed", cfg.get("seed"), 0, SEED_LIMIT, integer=True)
    number("seeds", cfg.get("seeds"), 1, SEEDS_LIMIT + 1, integer=True)
    if cfg.seed + cfg.seeds > SEED_LIMIT:
        raise UserError(
            f"seed={cfg.seed} with seeds={cfg.seeds} reaches seed {cfg.seed + cfg.seeds - 1}: "
            f"seeds must stay below {SEED_LIMIT} (2^32), so use seed <= {SEED_LIMIT - cfg.seeds}"
        )


def check_unroll(cfg: DictConfig) -> None:
    """The top-level unroll only for a scene with time (its task config has `unroll`), and each a
    positive integer."""
    if cfg.get("unroll") is not None:
        if "unroll" not in cfg.task:
            raise UserError(
                f"task={cfg.task.name} has no time axis: remove unroll={cfg.unroll} "
                "(unroll applies to temporal scenes only)"
            )
        number("unroll", cfg.unroll, 1, integer=True)
    elif "unroll" in cfg.task:
        number("task.unroll", cfg.task.unroll, 1, integer=True)


def too_many_seeds(cfg: DictConfig) -> str | None:
    """Why a job of more than SEEDS_LIMIT seeds is refused before one file per seed is named, or
    None."""
    seeds = cfg.get("seeds", 1)
    if isinstance(seeds, int) and seeds > SEEDS_LIMIT:
        return (
            f"seeds={seeds} is more than {SEEDS_LIMIT} seeds in one process: sweep "
            f"them instead (physgrad run -m seed=0,1,2,...), or use seeds <= {SEEDS_LIMIT}"
        )
    return None


def trial_values_refusal(cfg: DictConfig) -> str | None:
    """Why a job's trial_values (optim key -> one value per member) are refused before one file per
    member is named, or None: each key a number of the optim config, the same number of values
    (1 .. SEEDS_LIMIT) for every key, each a positive finite number, with one seed and no
    init_from."""
    given = cfg.get("trial_values")
    if given is None:
        return None
    if not isinstance(given, DictConfig) or not given:
        return (
            "trial_values must map optim keys to lists of values, e.g. "
            "{learning_rate: [0.001, 0.01]}"
        )
    counts = set()
    for key, values in given.items():
        if not isinstance(cfg.optim.get(key), (int, float)) or isinstance(cfg.optim.get(key), bool):
            return (
                f"trial_values.{key}: optim.{key} is not a number of optim={cfg.optim.get('name')}"
            )
        if not isinstance(values, ListConfig) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < float("inf")
            for v in values
        ):
            return f"trial_values.{key}: give a list of positive numbers"
        counts.add(len(values))
    if len(counts) != 1 or not 0 < next(iter(counts)) <= SEEDS_LIMIT:
        return f"trial_values: give every key the same number of values (1 to {SEEDS_LIMIT})"
    if cfg.get("seeds", 1) != 1 or cfg.get("init_from"):
        return (
            "trial_values trains its members on one seed, each from that seed's network: use "
            "seeds=1 and no init_from"
        )
    return None
