"""`physgrad compare`: which variant trains this scene best, tuned with equal budgets, decided on paired seeds.

    physgrad compare [-cd DIR] task=<scene> optim=adam,gauss_newton,hig [trainer.time_budget=60] [compare.KEY=V]

Every comma list on the command line is an axis of variants (their product, as in a Hydra multirun); every
other override is common to all jobs. A study runs in three phases, each a Hydra multirun of `physgrad run`
(so `hydra/launcher=...` applies) into the study folder, and resumes where it stopped when the same command
runs again:
1. tuning: compare.trials trials per variant, on the tuning seed, at the study's budget, over its search space
   (log-uniform; scrambled Halton points, as AlgoPerf; an Optuna study per variant in tuning.journal); each trial
   is scored by its VALIDATION loss at the budget;
2. evaluation: each variant at its best trial's settings on compare.seeds paired seeds (trained together in one
   vectorised step when the budget is in iterations; one job per seed, variants interleaved, for time budgets);
3. the verdicts (physgrad.verdict) from the TEST loss: compare.md, trials.csv, runs.csv, comparisons.csv,
   sensitivity.png and the sweep's report (figures of the curves) under report/.
docs/protocol.md gives the protocol and its reasons.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from physgrad.errors import UserError
from physgrad.interrupts import SignalInterrupt, raise_interrupt, take_lost
from physgrad.verdict import (ALPHA, FRACTIONS, MARGIN, Curve, compare_variants, divergence_test, seeds_needed,
                              target_loss)

JACOBIAN_RULES = ("physgrad.optim.spectral.spectral_rule", "physgrad.optim.spectral.marquardt_rule",
                  "physgrad.optim.kfac.kfac")
# log-uniform learning-rate ranges per rule family (docs/protocol.md): each spans the papers' presets by two
# decades or more on either side
SEARCH_RANGES = {
    "spectral": (1e-3, 1e1),  # Gauss-Newton, HIG, Levenberg-Marquardt, K-FAC (mean-over-samples loss; presets 0.5 to 1)
    "optax.lbfgs": (1e-2, 1e1),  # L-BFGS: scales the direction before its line search (preset 1)
    "optax.sgd": (1e-4, 1e1),  # plain gradient descent
    "adaptive": (1e-5, 1e-1),  # Adam and the other optax rules (presets 1e-4 to 1e-3)
}
SETTINGS = {  # compare.<key>: default, meaning
    "trials": (16, "tuning trials per variant (more on a finished study tunes on from where it stopped)"),
    "seeds": (10, "paired evaluation seeds"),
    "seed": (0, "the first evaluation seed (seed .. seed + seeds - 1)"),
    "tune_seed": (1_000_000, "the seed of every tuning trial (data, network, batches), disjoint from the evaluation seeds"),
    "margin": (MARGIN, "better means a loss ratio beyond this factor; equivalent means within it"),
    "alpha": (ALPHA, "the level of the tests after Holm's correction"),
    "dir": (None, "the study folder (default: outputs/compare/<task>-<hash of the command>)"),
    "search": ({}, "search spaces: compare.search.<optim key>=[low,high] (log-uniform), for every variant with that key"),
    "tune": (True, "false: evaluate the variants at their configured settings without tuning"),
    "clock": ("calibrated", "time budgets: calibrated (iterations x each variant's step cost measured in one "
                            "interleaved calibration, immune to the machine's load) or measured (training seconds)"),
    "calibration": (None, "a calibration.json to use instead of calibrating (e.g. one measured on a quiet machine)"),
}
PHASES = ("tune", "eval")


@dataclass
class Variant:
    name: str
    overrides: list[str]  # the variant's own overrides (key=value)
    config: object = None  # the composed config (common + variant overrides)
    space: dict = field(default_factory=dict)  # optim key -> (low, high), log-uniform
    job_values: dict = field(default_factory=dict)  # settings every job of the variant gets (its step cost)

    @property
    def preset(self) -> dict:
        from omegaconf import OmegaConf

        return {key: OmegaConf.select(self.config.optim, key) for key in self.space}

    @property
    def rate_key(self) -> str:
        return next((key for key in self.space if key.startswith("learning_rate")), "learning_rate")


def learning_rate_key(optim_cfg) -> str | None:
    """The optim key compare tunes: learning_rate, or learning_rate.init_value where the rate is a schedule
    (e.g. _target_: optax.exponential_decay with init_value: the schedule's shape is kept, its scale tuned);
    None if there is neither."""
    rate = optim_cfg.get("learning_rate")
    if rate is None:
        return None
    if hasattr(rate, "keys"):
        return "learning_rate.init_value" if "init_value" in rate else None
    return "learning_rate"


@dataclass
class Study:
    """What `physgrad compare` decided, as tables (pandas DataFrames), with the study folder."""

    folder: Path
    trials: object
    runs: object
    comparisons: object
    verdicts: list
    text: str


# --- parsing the command line -----------------------------------------------------------------------------


def parse_arguments(args: list[str]) -> tuple[list[str], str | None]:
    """Hydra's -cd/--config-dir DIR pulled out of the argument list; the rest are overrides."""
    overrides, config_dir, rest = [], None, list(args)
    while rest:
        arg = rest.pop(0)
        if arg in ("-cd", "--config-dir"):
            if not rest:
                raise UserError(f"{arg} needs a folder")
            config_dir = rest.pop(0)
        elif arg.startswith("--config-dir="):
            config_dir = arg.split("=", 1)[1]
        elif arg.startswith("-"):
            raise UserError(f"physgrad compare does not take {arg}: give overrides (key=value) and -cd DIR")
        else:
            overrides.append(arg)
    return overrides, config_dir


def split_overrides(overrides: list[str]) -> tuple[dict, list, list, list]:
    """(compare settings, variant axes [(key, [values as override strings])], common overrides, hydra overrides)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as error:
        raise UserError(f"cannot read the overrides: {str(error).splitlines()[0]}") from None
    settings, axes, common, hydra_args = {}, [], [], []
    for override in parsed:
        key = override.key_or_group
        if key.startswith("compare."):
            name = key[len("compare."):]
            top = name.split(".")[0]
            if top not in SETTINGS:
                raise UserError(f"unknown setting compare.{name} (choose from {', '.join(SETTINGS)})")
            if top == "search":
                value = override.value()
                if name == "search" or not (isinstance(value, list) and len(value) == 2
                                             and all(isinstance(v, (int, float)) and v > 0 for v in value)
                                             and value[0] < value[1]):
                    raise UserError(f"{override.input_line}: give compare.search.<optim key>=[low,high] with "
                                    "0 < low < high (a log-uniform range)")
                settings.setdefault("search", {})[name[len("search."):]] = (float(value[0]), float(value[1]))
            else:
                settings[top] = override.value()
        elif key.startswith("hydra"):
            hydra_args.append(override.input_line)
        elif key in ("seed", "seeds"):
            raise UserError(f"'{override.input_line}': compare sets the seeds itself: use compare.seeds=N (evaluation "
                            "seeds), compare.seed=S (the first one) or compare.tune_seed=S (tuning)")
        elif override.is_sweep_override():
            if override.is_interval_sweep() or override.is_range_sweep():
                raise UserError(f"'{override.input_line}': list the variants (a,b,c); compare searches each "
                                "variant's learning rate itself (compare.search)")
            prefix = "+" if override.is_add() else ""
            values = list(override.sweep_string_iterator())
            axes.append((key, [f"{prefix}{key}={value}" for value in values]))
        elif override.is_delete():
            raise UserError(f"'{override.input_line}': physgrad compare cannot delete keys")
        else:
            common.append(override.input_line)
    return settings, axes, common, hydra_args


def study_settings(given: dict) -> dict:
    from physgrad.validate import number

    s = {key: default for key, (default, _) in SETTINGS.items()}
    s.update(given)
    number("compare.trials", s["trials"], 1, 10_000, integer=True)
    number("compare.seeds", s["seeds"], 1, 10_000, integer=True)
    number("compare.seed", s["seed"], 0, 2**32, integer=True)
    number("compare.tune_seed", s["tune_seed"], 0, 2**32, integer=True)
    number("compare.margin", s["margin"], 1, open_low=True)
    number("compare.alpha", s["alpha"], 0, 1, open_low=True)
    from physgrad.runner import CLOCKS
    from physgrad.validate import choice

    choice("compare.clock", s["clock"], CLOCKS)
    if not isinstance(s["tune"], bool):
        raise UserError(f"compare.tune={s['tune']!r}: use true or false")
    if s["seed"] <= s["tune_seed"] < s["seed"] + s["seeds"]:
        raise UserError(f"compare.tune_seed={s['tune_seed']} is one of the evaluation seeds {s['seed']}.."
                        f"{s['seed'] + s['seeds'] - 1}: tuning and evaluation seeds must differ")
    return s


def variant_name(overrides: list[str]) -> str:
    """adam; hig; bptt clip=norm: a group's choice by its value, a key by its last part and value."""
    parts = []
    for override in overrides:
        key, _, value = override.lstrip("+").partition("=")
        parts.append(value if "." not in key else f"{key.rsplit('.', 1)[-1]}={value}")
    return " ".join(parts)


def family_range(optim_cfg) -> tuple[float, float]:
    target = str(optim_cfg.get("_target_", ""))
    if target in JACOBIAN_RULES:
        return SEARCH_RANGES["spectral"]
    if target in ("optax.sgd", "optax.lbfgs"):
        return SEARCH_RANGES[target]
    return SEARCH_RANGES["adaptive"]


def build_variants(axes, common, settings, config_dirs) -> list[Variant]:
    from physgrad.configs import check_overrides, compose

    if not axes:
        raise UserError("nothing to compare: list two or more variants, e.g. optim=adam,gauss_newton,hig")
    variants = []
    for combo in itertools.product(*(values for _, values in axes)):
        overrides = list(combo)
        check_overrides([*common, *overrides], multirun=False, config_dirs=config_dirs)
        cfg = compose([*common, *overrides], config_dirs=config_dirs, return_hydra_config=True)
        space = {}
        if settings["tune"]:
            rate = learning_rate_key(cfg.optim)
            if rate is None:
                raise UserError(f"optim={cfg.optim.get('name')} has no learning_rate to tune (a number, or a schedule "
                                "with init_value): add one to its YAML, or compare it untuned (compare.tune=false)")
            space[rate] = family_range(cfg.optim)
            for key, bounds in settings["search"].items():
                if key in cfg.optim:
                    space[rate if key == "learning_rate" else key] = bounds
        variants.append(Variant(variant_name(overrides), overrides, cfg, space))
    if len(variants) < 2:
        raise UserError("nothing to compare: list two or more variants, e.g. optim=adam,gauss_newton,hig")
    names = [v.name for v in variants]
    if len(set(names)) < len(names):
        raise UserError(f"two variants have the same name ({', '.join(names)}): give distinct values")
    return variants


def check_applies(variants: list[Variant], seed: int) -> None:
    """Every variant's run config checked and its scene and rule built as its jobs will (on the tuning seed), so
    that a variant the scene refuses (a backprop mode on a scene without time, a bad setting) stops the study in
    one line before anything trains."""
    from omegaconf import open_dict

    from physgrad.experiment import check_config, prepare

    for variant in variants:
        cfg = variant.config.copy()
        with open_dict(cfg):
            del cfg["hydra"]
        try:
            prepare(cfg, [seed], check_config(cfg))
        except UserError as error:
            raise UserError(f"variant {variant.name}: {error}") from None


# --- jobs as config files ---------------------------------------------------------------------------------


def _nested(values: dict) -> dict:
    tree: dict = {}
    for dotted, value in values.items():
        node = tree
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def job_yaml(overrides: list[str], groups: set, values: dict) -> str:
    """One job as a config file appended to the run config (+compare_job=NAME): the group choices among the
    overrides as `override /group: option`, every other override and `values` as keys (packaged _global_)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    defaults, keys = [], {}
    for override in OverridesParser.create().parse_overrides(overrides):
        key = override.key_or_group
        if key in groups and override.package is None:
            defaults.append(f"override /{key}: {override.get_value_element_as_str()}")
        else:
            keys[key] = override.value()
    keys.update(values)
    text = "# @package _global_\n# written by physgrad compare\n"
    if defaults:
        text += "defaults:\n" + "".join(f"  - {line}\n" for line in defaults)
    return text + OmegaConf.to_yaml(OmegaConf.create(_nested(keys)))


def halton_points(space: dict, count: int, seed: int) -> list[dict]:
    """count scrambled Halton points mapped log-uniformly onto the space (one dimension per key, sorted)."""
    from scipy.stats import qmc

    keys = sorted(space)
    unit = qmc.Halton(d=len(keys), scramble=True, seed=seed).random(count)
    return [{key: float(math.exp(math.log(space[key][0]) + u * (math.log(space[key][1]) - math.log(space[key][0]))))
             for key, u in zip(keys, row)} for row in unit]


# --- running ----------------------------------------------------------------------------------------------


# what does not make a study another: its folder, Hydra's settings, and the number of trials (a finished study
# given more trials tunes on from where it stopped: the Halton points of n trials begin with those of fewer)
NOT_THE_STUDY = ("compare.dir", "compare.trials", "hydra")


def same_study(record: dict | None):
    """The parts of a study.json record that identify the study."""
    if not isinstance(record, dict):
        return None
    overrides = record.get("overrides")
    return ([o for o in overrides if not str(o).startswith(NOT_THE_STUDY)] if isinstance(overrides, list) else None,
            record.get("config_dir"))


def default_folder(overrides: list[str], config_dir: str | None, task: str) -> Path:
    text = json.dumps([sorted(o for o in overrides if not o.startswith(NOT_THE_STUDY)),
                       os.path.abspath(config_dir) if config_dir else None])
    return Path("outputs") / "compare" / f"{task}-{hashlib.sha1(text.encode()).hexdigest()[:8]}"


def launch(folder: Path, phase: str, jobs: dict[str, str], config_dir, hydra_args, say) -> int:
    """Write the jobs' config files and run them as one multirun into folder/phase (a job that completed or
    diverged before with the same config is skipped); its output goes to folder/<phase>.log. Returns the
    multirun's exit status."""
    configs = folder / "configs" / "compare_job"
    configs.mkdir(parents=True, exist_ok=True)
    for name, text in jobs.items():
        path = configs / f"{name}.yaml"
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
    search = [f"file://{(folder / 'configs').resolve()}"]
    extra = []
    for arg in hydra_args:
        if arg.startswith("hydra.searchpath="):
            from physgrad.configs import searchpath_entries

            search = searchpath_entries([arg]) + search
        else:
            extra.append(arg)
    command = [sys.executable, "-m", "physgrad", "run", "-m", *(["-cd", config_dir] if config_dir else []),
               f"hydra.searchpath=[{','.join(search)}]", f"hydra.sweep.dir={folder / phase}", *extra,
               "+compare_job=" + ",".join(jobs)]
    say(f"{phase}: {len(jobs)} jobs -> {folder / phase} (log: {folder / (phase + '.log')})")
    with open(folder / f"{phase}.log", "a") as log:
        log.write(f"\n$ {' '.join(command)}\n")
        log.flush()
        lost = take_lost()  # a signal the interpreter dropped since the last phase (physgrad.interrupts)
        if lost is not None:
            raise SignalInterrupt(lost)
        # its own session: a terminal's Ctrl-C reaches this process only, which passes it (or a SIGTERM) on once,
        # so the sweep stops as a whole and records what it stopped (physgrad.sweeps)
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        received = []

        def forward(signum, frame):
            received.append(signum)
            process.send_signal(signum)

        try:
            previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
        except ValueError:  # not the main thread: leave signals alone
            previous = {}
        try:
            code = process.wait()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if received:
            raise KeyboardInterrupt(signal.Signals(received[0]).name)
        return code


def job_runs(sweep: Path, name: str) -> list:
    from physgrad.results import read_run

    folder = sweep / f"+compare_job={name}"
    runs = []
    for path in sorted(folder.glob("results.h5")) + sorted(folder.glob("seed=*/results.h5")):
        try:
            runs.append(read_run(path))
        except ValueError:
            continue
    return runs


def run_curve(run, axis: str, column: str = "loss") -> Curve:
    """The run's held-out `column` on the axis (iteration or wall_time), ending where its training ended."""
    x = np.asarray(run.eval.get(axis, np.empty(0)), float)
    end = run.final("train", axis) + (1 if axis == "iteration" else 0)
    status = run.attrs.get("status")
    if status == "completed" and run.attrs.get("stopped_by") in ("iterations", "time_budget"):
        end = math.inf  # ran to its budget: its last evaluation at or before any x counts
    return Curve(x, np.asarray(run.eval.get(column, np.full(x.shape, np.nan)), float),
                 end if math.isfinite(end) or status == "completed" else 0.0, status == "diverged")


def tuning(folder: Path, variants: list[Variant], s: dict, common, groups, axis, budget, config_dir, hydra_args,
           say) -> dict[str, dict]:
    """Phase 1: trials per variant (equal numbers), scored by validation loss at the budget; returns the best
    settings per variant (its configured ones where every trial diverged or tuning is off)."""
    import optuna

    best = {v.name: {} for v in variants}
    if not s["tune"]:
        return best
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(folder / "tuning.journal")))
    studies, pending = {}, {}
    for index, variant in enumerate(variants):
        study = optuna.create_study(study_name=variant.name, storage=storage, direction="minimize",
                                    load_if_exists=True)
        studies[variant.name] = study
        points = halton_points(variant.space, s["trials"], s["tune_seed"] + index)
        for point in points[len(study.trials):]:
            study.enqueue_trial(point)
        from optuna.trial import TrialState

        while any(t.state == TrialState.WAITING for t in study.get_trials(deepcopy=False)):
            trial = study.ask()
            for key, (low, high) in sorted(variant.space.items()):
                trial.suggest_float(key, low, high, log=True)
        for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            pending[(index, trial.number)] = trial
    jobs = {}
    for k in range(s["trials"]):  # interleaved: trial k of every variant, then k + 1
        for index, variant in enumerate(variants):
            trial = pending.get((index, k))
            if trial is not None:
                values = {f"optim.{key}": value for key, value in trial.params.items()}
                values.update({"seed": s["tune_seed"], "seeds": 1, "trainer.validation": True, **variant.job_values})
                values.update(cadence(variant.config, axis, budget))
                jobs[f"tune_v{index}_t{k:03d}"] = job_yaml([*common, *variant.overrides], groups, values)
    if jobs:
        code = launch(folder, "tune", jobs, config_dir, hydra_args, say)
        if code == 130:
            raise KeyboardInterrupt
        for (index, k), trial in pending.items():
            runs = job_runs(folder / "tune", f"tune_v{index}_t{k:03d}")
            if not runs or runs[0].attrs.get("status") in ("running", "interrupted", "crashed"):
                continue  # not run to its end: run again next time
            run = runs[0]
            if run.attrs.get("status") == "refused":
                raise UserError(f"variant {variants[index].name} is refused: {run.attrs.get('reason')}")
            value = run_curve(run, axis, "validation_loss").at(budget)
            studies[variants[index].name].tell(k, value if not math.isnan(value) else math.inf)
    for variant in variants:
        done = [t for t in studies[variant.name].trials if t.value is not None and math.isfinite(t.value)]
        if len(studies[variant.name].trials) and any(t.value is None for t in studies[variant.name].trials):
            raise UserError(f"tuning of {variant.name} did not finish (see {folder / 'tune.log'}): run the same "
                            "command again to resume")
        if done:
            best[variant.name] = dict(min(done, key=lambda t: t.value).params)
    return best


def cadence(cfg, axis: str, budget: float) -> dict:
    """Evaluations fine enough to read the budget's quarters (time budgets: the runner's budget / 20)."""
    if axis == "iteration" and cfg.trainer.get("eval_every", 100) * 20 > budget:
        return {"trainer.eval_every": max(1, int(budget) // 20)}
    return {}


def calibrated_clock(folder: Path, variants: list[Variant], seed: int, given: str | None, say) -> dict:
    """Each variant's step cost (physgrad.calibration), measured once per study and stored in its folder (a
    resumed study reuses it), or taken from a given calibration.json (compare.calibration); every job of a
    variant then runs on the calibrated clock with that cost."""
    from omegaconf import open_dict

    from physgrad.calibration import CALIBRATION_FILE, calibrate, read_calibration, write_calibration

    path = folder / CALIBRATION_FILE
    names = [v.name for v in variants]
    if given is not None:
        calibration = read_calibration(Path(given), names)
        if calibration is None:
            raise UserError(f"compare.calibration={given}: not a calibration.json with a step cost for every "
                            f"variant ({', '.join(names)}); leave it out to calibrate")
        write_calibration(path, calibration)
    calibration = read_calibration(path, names)
    if calibration is None:
        say(f"calibrating the step costs of {len(variants)} variants, interleaved in one process")
        configs = {}
        for variant in variants:
            cfg = variant.config.copy()
            with open_dict(cfg):
                del cfg["hydra"]
            configs[variant.name] = cfg
        calibration = calibrate(configs, seed)
        write_calibration(path, calibration)
    for variant in variants:
        cost = float(calibration["costs"][variant.name]["step_seconds"])
        variant.job_values = {"trainer.step_cost": cost, "trainer.clock": "calibrated"}
    return calibration


def budget_of(cfg) -> tuple[str, float]:
    from physgrad.runner import DEFAULT_ITERATIONS

    if cfg.trainer.get("time_budget") is not None:
        return "wall_time", float(cfg.trainer.time_budget)
    iterations = cfg.trainer.get("iterations")
    return "iteration", float(iterations if iterations is not None else DEFAULT_ITERATIONS)


def evaluation_jobs(variants, best, s, common, groups, axis, budget) -> dict[str, str]:
    """The evaluation's jobs in launch order: per variant one job of all seeds trained together when the budget
    is in iterations (one per seed where the rule's float64 retry does not batch or init_from starts each seed
    from its own network, e.g. init_from='start/seed=${seed}/results.h5'); for time budgets one job per
    seed, variants interleaved (A, B, C for the first seed, then the next), so that a drift in the machine's
    load does not line up with a variant."""
    seeds = list(range(s["seed"], s["seed"] + s["seeds"]))
    jobs = {}

    def spec(variant, seed, count):
        values = {f"optim.{k}": v for k, v in best[variant.name].items()}
        values.update({"seed": seed, "seeds": count, **cadence(variant.config, axis, budget), **variant.job_values})
        return job_yaml([*common, *variant.overrides], groups, values)

    if axis == "iteration":
        for index, variant in enumerate(variants):
            # a float64 retry does not batch under vmap, and init_from starts one network per job
            if (variant.config.optim.get("retry_float64") or variant.config.get("init_from")) and len(seeds) > 1:
                jobs.update({f"eval_v{index}_s{seed}": spec(variant, seed, 1) for seed in seeds})
            else:
                jobs[f"eval_v{index}"] = spec(variant, seeds[0], len(seeds))
    else:
        for seed in seeds:
            for index, variant in enumerate(variants):
                jobs[f"eval_v{index}_s{seed}"] = spec(variant, seed, 1)
    return jobs


def evaluation(folder, variants, best, s, common, groups, axis, budget, config_dir, hydra_args, say):
    """Phase 2: every variant at its tuned settings on the paired evaluation seeds; (curves, runs) per variant
    and seed."""
    jobs = evaluation_jobs(variants, best, s, common, groups, axis, budget)
    code = launch(folder, "eval", jobs, config_dir, hydra_args, say)
    if code == 130:
        raise KeyboardInterrupt
    curves, statuses = {}, {}
    for index, variant in enumerate(variants):
        curves[variant.name], statuses[variant.name] = {}, {}
        for name in jobs:
            if name == f"eval_v{index}" or name.startswith(f"eval_v{index}_s"):
                for run in job_runs(folder / "eval", name):
                    if run.attrs.get("status") == "refused":
                        raise UserError(f"variant {variant.name} is refused: {run.attrs.get('reason')}")
                    seed = run.attrs.get("seed")
                    if isinstance(seed, int):
                        curves[variant.name][seed] = run_curve(run, axis)
                        statuses[variant.name][seed] = run
    return curves, statuses


# --- the analysis and what it writes ----------------------------------------------------------------------


def _g(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def _exp(log_value: float) -> float:
    """A ratio from a log ratio, with LOG_CAP (one side diverged) as 0 or infinity."""
    if math.isnan(log_value):
        return math.nan
    return math.exp(log_value) if abs(log_value) < 700 else (0.0 if log_value < 0 else math.inf)


def _ratio_text(p) -> str:
    return f"{_g(p.ratio)} [{_g(_exp(p.low))}, {_g(_exp(p.high))}]"


def analyse(folder: Path, variants, best, curves, statuses, s, axis, budget, trials_rows, calibration=None):
    import pandas as pd

    from physgrad.machine import machine_label

    unit = "iterations" if axis == "iteration" else "s"
    verdicts = compare_variants(curves, budget, margin=s["margin"], alpha=s["alpha"])
    target_variant, target = target_loss(curves, budget)
    run_rows = []
    for variant in variants:
        for seed, c in sorted(curves[variant.name].items()):
            run = statuses[variant.name][seed]
            row = {"variant": variant.name, "seed": seed, "axis": axis, "budget": budget, "status": run.attrs.get("status"),
                   "stopped_by": run.attrs.get("stopped_by"), "iterations": run.final("train", "iteration") + 1,
                   "train_seconds": run.final("train", "wall_time"),
                   "calibrated_seconds": (run.final("train", "calibrated_time") if "calibrated_time" in run.train
                                          else math.nan),
                   "contended": bool(run.attrs.get("contended", 0)), "contention": run.attrs.get("contention", ""),
                   "step_seconds_p50": run.attrs.get("step_seconds_p50", math.nan),
                   "step_seconds_p90": run.attrs.get("step_seconds_p90", math.nan),
                   "machine": machine_label(run.attrs), "path": str(run.path)}
            for fraction in FRACTIONS:
                row[f"test_loss_at_{fraction:g}"] = c.at(budget * fraction)
            row["diverged_by_budget"] = math.isinf(row["test_loss_at_1"])
            row[f"to_target_{unit}"] = c.reaches(target, budget) if math.isfinite(target) else math.nan
            run_rows.append(row)
    runs = pd.DataFrame(run_rows)
    comparison_rows = []
    for v in verdicts:
        for fraction in FRACTIONS:
            p = v.at[fraction]
            comparison_rows.append({
                "a": v.a, "b": v.b, "fraction": fraction, "budget": budget * fraction, "pairs": p.pairs,
                "a_lower_in": p.wins_a, "missing": p.missing, "median_ratio": p.ratio,
                "ci_low": _exp(p.low), "ci_high": _exp(p.high),
                "p_difference_holm": v.p_difference[fraction], "p_equivalent_holm": v.p_equivalent[fraction],
                "diverged_a": p.diverged_a, "diverged_b": p.diverged_b,
                "p_divergence_fisher": divergence_test(p.diverged_a, p.pairs + p.missing, p.diverged_b,
                                                       p.pairs + p.missing),
                "verdict": v.verdicts[fraction][0], "why": v.verdicts[fraction][1]})
    comparisons = pd.DataFrame(comparison_rows)
    trials = pd.DataFrame(trials_rows)
    trials.to_csv(folder / "trials.csv", index=False)
    runs.to_csv(folder / "runs.csv", index=False)
    comparisons.to_csv(folder / "comparisons.csv", index=False)

    budget_text = {"wall_time": f"{budget:g} s of training (measured clock)",
                   "calibrated_time": f"{budget:g} s of training on the calibrated clock (iterations x the variant's "
                                      "calibrated step cost; the measured seconds are in runs.csv)",
                   }.get(axis, f"{budget:g} iterations")
    contended = {v.name: int(runs[runs.variant == v.name]["contended"].sum()) if len(runs) else 0
                 for v in variants}
    lines = [f"# Which gradient: {variants[0].config.task.get('name')}, {', '.join(v.name for v in variants)}", "",
             f"Budget: {budget_text} per run. Tuning: {s['trials'] if s['tune'] else 0} trials per variant on seed "
             f"{s['tune_seed']}, scored by the validation loss at the budget. Evaluation: seeds {s['seed']}.."
             f"{s['seed'] + s['seeds'] - 1}, paired (same data and initial network), verdicts on the test loss. "
             f"Rule: docs/protocol.md (margin {s['margin']:g}, alpha {s['alpha']:g}, Holm over "
             f"{len(verdicts)} comparisons).", "",
             "## Verdicts", "",
             "| A vs B | verdict at the budget | median A/B [95% interval] | A lower in | verdict at 1/4, 1/2 | "
             "stable | trend 1/2 -> 1 | diverged A, B | contended runs A, B |", "|---|---|---|---|---|---|---|---|---|"]
    for v in verdicts:
        p = v.at[1.0]
        flag = " (timing contended)" if axis == "wall_time" and (contended[v.a] or contended[v.b]) else ""
        lines.append(f"| {v.a} vs {v.b} | **{v.verdict}**{flag} ({v.verdicts[1.0][1]}) | {_ratio_text(p)} | "
                     f"{p.wins_a} of {p.pairs}{f' ({p.missing} missing)' if p.missing else ''} | "
                     f"{v.verdicts[0.25][0]}, {v.verdicts[0.5][0]} | {'yes' if v.stable else 'no'} | {v.trend} | "
                     f"{p.diverged_a}, {p.diverged_b} | {contended[v.a]}, {contended[v.b]} |")
    lines += ["", "## Variants", "",
              f"| variant | tuned | preset | test loss at the budget: median [min, max] | diverged | "
              f"to target ({unit}): median, reached |", "|---|---|---|---|---|---|"]
    for variant in variants:
        sub = runs[runs.variant == variant.name] if len(runs) else runs
        losses = sub["test_loss_at_1"].to_numpy(float) if len(sub) else np.empty(0)
        present = losses[~np.isnan(losses)]
        reach = sub[f"to_target_{unit}"].to_numpy(float) if len(sub) else np.empty(0)
        tuned = ", ".join(f"{k}={_g(val)}" for k, val in best[variant.name].items()) or "as configured"
        preset = ", ".join(f"{k}={_g(float(val)) if isinstance(val, (int, float)) else val}"
                           for k, val in variant.preset.items()) or "-"
        spread = (f"{_g(float(np.median(present)))} [{_g(float(present.min()))}, {_g(float(present.max()))}]"
                  if present.size else "-")
        lines.append(f"| {variant.name} | {tuned} | {preset} | {spread} | {int(np.isinf(present).sum())} of "
                     f"{present.size} | {_g(float(np.median(reach))) if reach.size else '-'}, "
                     f"{int(np.isfinite(reach).sum())} of {reach.size} |")
    lines += ["", f"Target: {_g(target)}, the median test loss of {target_variant or '-'} (the lowest) at the "
              "budget; a run that never reaches it counts as infinite. Losses at 1/4 and 1/2 of the budget and "
              "per seed: runs.csv; every comparison at every fraction with its p-values: comparisons.csv; "
              "trials: trials.csv and sensitivity.png; curves: report/."]
    lines += timing_lines(variants, runs, axis, calibration)
    text = "\n".join(lines) + "\n"
    (folder / "compare.md").write_text(text)
    return runs, comparisons, trials, verdicts, text


def timing_lines(variants, runs, axis, calibration) -> list[str]:
    """compare.md's timing section: the clock, the calibration's step costs, contended runs, the machines."""
    lines = ["", "## Timing", ""]
    if axis == "calibrated_time" and calibration:
        lines += [f"Clock: calibrated. Step costs measured with every variant's compiled step interleaved in one "
                  f"process (the {calibration['quantile']:g} quantile over rounds; load average "
                  f"{calibration['load_start']:.2f} -> {calibration['load_end']:.2f}); a run's time is its "
                  "iterations times its variant's cost, so the machine's load cannot change how far a variant "
                  "gets. The measured clock: compare.clock=measured.", "",
                  "| variant | calibrated step cost | median in the calibration | rounds | measured p50 in the runs "
                  "| contended runs |", "|---|---|---|---|---|---|"]
        for variant in variants:
            cost = calibration["costs"][variant.name]
            sub = runs[runs.variant == variant.name] if len(runs) else runs
            p50 = float(np.nanmedian(sub["step_seconds_p50"])) if len(sub) and sub["step_seconds_p50"].notna().any() \
                else math.nan
            lines.append(f"| {variant.name} | {_g(cost['step_seconds'])} s | {_g(cost['median_seconds'])} s | "
                         f"{cost['rounds']} | {_g(p50)} s | {int(sub['contended'].sum()) if len(sub) else 0} of "
                         f"{len(sub)} |")
        from physgrad.machine import contention

        busy = contention({}, 0, calibration["load_start"], calibration["load_end"],
                          int(calibration["machine"].get("cpu_count", 1)))
        if busy:
            lines += ["", f"**Warning**: the calibration ran on a busy machine ({busy}): the step costs of the "
                          "variants are not slowed alike by other work, so recalibrate on a quiet machine or give "
                          "one with compare.calibration."]
    elif axis == "wall_time":
        lines += ["Clock: measured (training seconds as timed). A run flagged contended (step times spread or the "
                  "machine oversubscribed, docs/decisions.md) was slowed by other work: a verdict that uses one is "
                  "marked. The calibrated clock is the default (compare.clock=calibrated)."]
    else:
        lines += ["Budget in iterations: the clock does not enter the verdicts."]
    machines = sorted(set(runs["machine"])) if len(runs) else []
    if len(machines) > 1:
        lines += ["", f"**Warning**: the runs come from {len(machines)} machines ({'; '.join(machines)}): "
                      "their times are not comparable."]
    elif machines:
        lines += ["", f"Machine: {machines[0]}."]
    flagged = runs[runs.contended] if len(runs) else runs
    if len(flagged):
        lines += ["", f"Contended runs: {len(flagged)} of {len(runs)} "
                      f"(e.g. {flagged.iloc[0]['variant']} seed {flagged.iloc[0]['seed']}: "
                      f"{flagged.iloc[0]['contention']})."]
    return lines


def plot_sensitivity(path: Path, variants, trials_rows, best) -> None:
    """Validation loss at the budget against the learning rate, one panel per variant: every trial, the chosen
    one starred, the preset as a dashed line, diverged trials as crosses at the top."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = min(len(variants), 3)  # at most three panels a row: six variants are two rows, not one strip
    panel_rows = -(-len(variants) // columns)
    fig, grid = plt.subplots(panel_rows, columns, figsize=(3.6 * columns, 3.2 * panel_rows), squeeze=False)
    axes = [list(grid.ravel()[:len(variants)])]
    for ax in grid.ravel()[len(variants):]:
        ax.remove()
    for ax, variant in zip(axes[0], variants):
        rows = [r for r in trials_rows if r["variant"] == variant.name]
        rate = variant.rate_key
        lr = np.array([r.get(rate, np.nan) for r in rows], float)
        loss = np.array([r["validation_loss"] for r in rows], float)
        ok = np.isfinite(loss)
        ax.scatter(lr[ok], loss[ok], s=18, color="C0", label="trial")
        if (~ok).any():
            top = loss[ok].max() * 2 if ok.any() else 1.0
            ax.scatter(lr[~ok], np.full((~ok).sum(), top), marker="x", color="C3", label="diverged")
        if rate in best[variant.name]:
            chosen = [r for r in rows if r.get(rate) == best[variant.name][rate]]
            ax.scatter([best[variant.name][rate]], [chosen[0]["validation_loss"]], marker="*", s=140,
                       color="C1", label="chosen", zorder=3)
        preset = variant.preset.get(rate)
        if isinstance(preset, (int, float)):
            ax.axvline(preset, ls="--", color="0.4", label="preset")
        ax.set_xscale("log")
        if ok.any() and loss[ok].min() > 0:
            ax.set_yscale("log")
        ax.set_title(variant.name)
        ax.set_xlabel("learning rate")
        ax.grid(alpha=0.3)
    for ax in grid[:, 0]:
        ax.set_ylabel("validation loss at the budget")
    legend = {}
    for ax in axes[0]:  # one legend for all panels, below them, off the data
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    fig.legend(legend.values(), legend.keys(), loc="lower center", ncol=len(legend), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.07 / panel_rows, 1, 1))
    for suffix in (".png", ".pdf"):
        fig.savefig(path.with_suffix(suffix), dpi=130)
    plt.close(fig)


def trial_rows(folder: Path, variants) -> list[dict]:
    import optuna

    path = folder / "tuning.journal"
    if not path.exists():
        return []
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(path)))
    rows = []
    for variant in variants:
        study = optuna.load_study(study_name=variant.name, storage=storage)
        for t in study.trials:
            rows.append({"variant": variant.name, "trial": t.number, **t.params,
                         "validation_loss": t.value if t.value is not None else math.nan, "state": t.state.name})
    return rows


def run_study(overrides: list[str], config_dir: str | None = None, say=print) -> Study:
    """The whole study (module docstring); resumes from its folder."""
    from physgrad.errors import FolderOwned
    from physgrad.files import own_folder

    settings_given, axes, common, hydra_args = split_overrides(overrides)
    s = study_settings(settings_given)
    config_dirs = [config_dir] if config_dir else []
    if os.getcwd() not in sys.path:  # a scene or optimiser named by _target_, as for `physgrad run`
        sys.path.append(os.getcwd())
    variants = build_variants(axes, common, s, config_dirs)
    check_applies(variants, s["tune_seed"])
    first = variants[0].config
    comparisons = len(variants) * (len(variants) - 1) // 2
    needed = seeds_needed(s["alpha"], comparisons)
    if s["seeds"] < needed:
        say(f"warning: {s['seeds']} seeds cannot decide {comparisons} comparisons at alpha {s['alpha']:g}: every "
            f"verdict will be undecided (compare.seeds={needed} or more)")
    groups = set(first.hydra.runtime.choices.keys())
    axis, budget = budget_of(first)
    folder = Path(s["dir"]) if s["dir"] else default_folder(overrides, config_dir, str(first.task.get("name")))
    folder.mkdir(parents=True, exist_ok=True)
    record = {"overrides": [o for o in overrides if not o.startswith(("compare.dir", "hydra"))],
              "config_dir": os.path.abspath(config_dir) if config_dir else None}
    stored = folder / "study.json"
    if stored.exists():
        try:
            before = json.loads(stored.read_text())
        except (OSError, ValueError):
            before = None
        if same_study(before) != same_study(record):
            raise UserError(f"{folder} holds another study ({' '.join((before or {}).get('overrides', ['?']))}): "
                            "give another compare.dir")
    if not stored.exists() or before != record:  # new, or the same study given more trials
        stored.write_text(json.dumps(record, indent=1) + "\n")
    try:
        with own_folder(folder, "study"):
            say(f"study {folder}: {len(variants)} variants ({', '.join(v.name for v in variants)}), budget "
                f"{budget:g} {'iterations' if axis == 'iteration' else 's'}; the same command resumes it")
            calibration = None
            if axis == "wall_time" and s["clock"] == "calibrated":
                calibration = calibrated_clock(folder, variants, s["tune_seed"], s["calibration"], say)
                axis = "calibrated_time"
            best = tuning(folder, variants, s, common, groups, axis, budget, config_dir, hydra_args, say)
            rows = trial_rows(folder, variants)
            if rows:
                plot_sensitivity(folder / "sensitivity", variants, rows, best)
            curves, statuses = evaluation(folder, variants, best, s, common, groups, axis, budget, config_dir,
                                          hydra_args, say)
            runs, comparisons, trials, verdicts, text = analyse(folder, variants, best, curves, statuses, s, axis,
                                                                budget, rows, calibration)
            try:
                from physgrad.report import write_report

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    write_report([folder / "eval"], out_dir=folder / "report")
            except (UserError, OSError, ValueError) as error:
                say(f"report of the curves not written: {error}")
    except FolderOwned as error:
        raise UserError(str(error)) from None
    return Study(folder, trials, runs, comparisons, verdicts, text)


def main(args: list[str]) -> int:
    if any(a in ("-h", "--help") for a in args):
        print(__doc__.strip())
        print("\nSettings (compare.KEY=VALUE):")
        for key, (default, meaning) in SETTINGS.items():
            print(f"  compare.{key:<10} {meaning} (default {default})")
        return 0
    overrides, config_dir = parse_arguments(args)

    # SIGTERM as Ctrl-C: the study's files are left as a resumable state
    previous = signal.signal(signal.SIGTERM, raise_interrupt)
    try:
        study = run_study(overrides, config_dir)
    except KeyboardInterrupt:
        print("physgrad compare: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(study.text)
    print(f"wrote {study.folder / 'compare.md'}, trials.csv, runs.csv, comparisons.csv, sensitivity.png, report/")
    return 0
