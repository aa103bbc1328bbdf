"""What a study compares: its settings (compare.KEY=VALUE), its variants (the comma lists of the
command line, each composed, with the search space of its tuning) and its budget."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

from physgrad.comparison.search_space import search_space
from physgrad.errors import UserError, innermost_cause
from physgrad.readout import budget_of as budget_of_config
from physgrad.verdict import ALPHA, MARGIN

if TYPE_CHECKING:
    from hydra.core.override_parser.types import Override
    from omegaconf import DictConfig

SETTINGS = {  # compare.<key>: default, meaning
    "trials": (
        16,
        "tuning trials per variant (more on a finished study tunes on from where it stopped)",
    ),
    "studies": (
        4,
        "independent tuning studies, each with its own tuning seed (tune_seed + k), trial points "
        "and evaluation seeds; a verdict must hold in more than half of them (3 of 4) with none "
        "against and every study's median ratio on its side (docs/protocol.md)",
    ),
    "seeds": (10, "paired evaluation seeds per tuning study"),
    "seed": (
        0,
        "the first evaluation seed (study k evaluates on seed + k * seeds .. seed + (k + 1) * "
        "seeds - 1)",
    ),
    "tune_seed": (
        1_000_000,
        "the seed of the first study's tuning trials (data, network, batches; study k: "
        "tune_seed + k), disjoint from the evaluation seeds",
    ),
    "margin": (MARGIN, "better means a loss ratio beyond this factor; equivalent means within it"),
    "alpha": (ALPHA, "the level of the tests after Holm's correction"),
    "dir": (None, "the study folder (default: outputs/compare/<task>-<hash of the command>)"),
    "search": (
        {},
        "search spaces: compare.search.<optim key>=[low,high] (log-uniform), for every variant "
        "with that key",
    ),
    "tune": (True, "false: evaluate the variants at their configured settings without tuning"),
    "tuned_in": (
        None,
        "a finished study's folder: evaluate each variant at the settings it tuned (its "
        "trials.csv) instead of tuning here, e.g. the same settings at a longer budget",
    ),
    "knobs": (
        False,
        "true: tune each rule's own settings that its authors tune (Adam's eps, the Jacobian "
        "rules' tau or damping, PSGD Kron's preconditioner step, Muon's Adam step) beside its "
        "learning rate, over their declared ranges (docs/protocol.md)",
    ),
    "clock": (
        "calibrated",
        "time budgets: calibrated (iterations x each variant's step cost measured in one "
        "interleaved calibration: the load during the runs does not move how far a variant gets; "
        "calibrate on a quiet machine) or measured (training seconds)",
    ),
    "calibration": (
        None,
        "a calibration.json to use instead of calibrating (e.g. one measured on a quiet machine)",
    ),
    "baseline": (
        None,
        "a variant's name (e.g. adam): compare every other variant with it alone (k - 1 "
        "comparisons, Holm's correction over those) instead of every pair of the k variants",
    ),
}
PHASES = ("tune", "eval")


@dataclass(frozen=True)
class StudySettings:
    """The compare.* settings of a study (SETTINGS gives each one's meaning and default),
    checked."""

    trials: int
    studies: int
    seeds: int
    seed: int
    tune_seed: int
    margin: float
    alpha: float
    dir: str | None
    search: dict  # optim key -> (low, high), log-uniform
    tune: bool
    clock: str
    calibration: str | None
    baseline: str | None = None
    knobs: bool = False
    tuned_in: str | None = None

    def __getitem__(self, key: str) -> Any:
        """settings["seeds"] as settings.seeds, for callers of the dict these settings were."""
        if key not in {f.name for f in fields(self)}:
            raise KeyError(key)
        return getattr(self, key)

    def study_seeds(self, study: int) -> list[int]:
        """The paired evaluation seeds of tuning study k: a block of its own, so that the studies'
        evaluations are independent draws (three studies of 10 seeds are 30 distinct seeds)."""
        first = self.seed + study * self.seeds
        return list(range(first, first + self.seeds))

    def pairs(self, names: list[str]) -> list[tuple[str, str]] | None:
        """The comparisons (A, B) among the variants named: each other variant against the
        baseline; None (every pair, in order) without one."""
        if self.baseline is None:
            return None
        return [(name, self.baseline) for name in names if name != self.baseline]

    def comparisons(self, count: int) -> int:
        """How many comparisons a study of count variants makes (Holm's correction runs over
        them)."""
        return count - 1 if self.baseline is not None else count * (count - 1) // 2

    @property
    def evaluation_seeds(self) -> list[int]:
        """Every study's evaluation seeds, study 0's first."""
        return list(range(self.seed, self.seed + self.study_count * self.seeds))

    @property
    def study_count(self) -> int:
        """Tuning studies run: compare.studies, or one where nothing is tuned (no tuning variance
        to sample)."""
        return self.studies if self.tune else 1


@dataclass
class Variant:
    name: str
    overrides: list[str]  # the variant's own overrides (key=value)
    config: object = None  # the composed config (common + variant overrides)
    space: dict = field(default_factory=dict)  # optim key -> (low, high), log-uniform
    # settings every job of the variant gets (its step cost)
    job_values: dict = field(default_factory=dict)
    # its tuning trials train together in one vectorised job per study (tuning.trials_together)
    trials_together: bool = False
    # the setting that shapes its step cost, where it is tuned, and the own part of a step
    # calibrated at its range's two ends, its breaks and its preset:
    # (key, shape, ((value, seconds), ...)))
    cost_knob: tuple = ()

    def priced(self, params: dict) -> dict:
        """The job's trainer.step_cost at params (a trial's or the tuned values) where the
        variant's tuned setting shapes it (physgrad.optim.capabilities.knob_step_cost, with the
        preset's line-search evaluations); {} for a variant whose steps cost the same at every
        value."""
        if not self.cost_knob or self.cost_knob[0] not in params:
            return {}
        from physgrad.optim.capabilities import knob_step_cost  # JAX: not for compare --help

        values = self.job_values
        evaluations = values.get("trainer.evaluation_cost", 0.0) * values.get(
            "trainer.step_evaluations", 0.0
        )
        cost = knob_step_cost(self.cost_knob, params[self.cost_knob[0]], evaluations)
        return {"trainer.step_cost": cost}

    @property
    def preset(self) -> dict:
        from omegaconf import OmegaConf

        return {key: OmegaConf.select(self.config.optim, key) for key in self.space}

    @property
    def rate_key(self) -> str:
        return next((key for key in self.space if key.startswith("learning_rate")), "learning_rate")


@dataclass
class StudyPlan:
    """What a study compares and how: its variants, settings, the overrides common to every variant,
    the config groups the command line chose (job files name them), and the budget on its axis
    (iteration, wall_time or calibrated_time)."""

    variants: list[Variant]
    settings: StudySettings
    common: list[str]
    groups: set[str]
    axis: str
    budget: float

    @property
    def members_axis(self) -> str:
        """The axis a job's members (trials, seeds) train and stop on together: the budget's, but
        calibrated_time for a time budget on the calibrated clock, where every member runs the
        iterations its variant's calibrated cost allows, whatever the machine's load."""
        if self.axis == "iteration" or self.settings.clock != "calibrated":
            return self.axis
        return "calibrated_time"


# --- parsing the command line
# -----------------------------------------------------------------------------


def parse_arguments(args: list[str]) -> tuple[list[str], str | None, bool]:
    """Hydra's -cd/--config-dir DIR and --plan pulled out of the argument list; the rest are
    overrides. (overrides, config_dir, plan)."""
    overrides, config_dir, plan, rest = [], None, False, list(args)
    while rest:
        arg = rest.pop(0)
        if arg == "--plan":
            plan = True
        elif arg in ("-cd", "--config-dir"):
            if not rest:
                raise UserError(f"{arg} needs a folder")
            config_dir = rest.pop(0)
        elif arg.startswith("--config-dir="):
            config_dir = arg.split("=", 1)[1]
        elif arg.startswith("-"):
            raise UserError(
                f"physgrad compare does not take {arg}: give overrides (key=value), -cd DIR and "
                "--plan"
            )
        else:
            overrides.append(arg)
    return overrides, config_dir, plan


def split_overrides(overrides: list[str]) -> tuple[dict, list, list, list]:
    """(compare settings, variant axes [(key, [values as override strings])], common overrides,
    hydra overrides)."""
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
            _compare_setting(override, key[len("compare.") :], settings)
        elif key in ("hydra.sweep.dir", "hydra.run.dir", "hydra.sweep.subdir"):
            raise UserError(
                f"'{override.input_line}': compare puts every job into the study folder: give "
                "compare.dir=DIR instead"
            )
        elif key.startswith("hydra"):
            hydra_args.append(override.input_line)
        elif key in ("seed", "seeds"):
            raise UserError(
                f"'{override.input_line}': compare sets the seeds itself: use compare.seeds=N "
                "(evaluation seeds), compare.seed=S (the first one) or compare.tune_seed=S (tuning)"
            )
        elif override.is_sweep_override():
            if override.is_interval_sweep() or override.is_range_sweep():
                raise UserError(
                    f"'{override.input_line}': list the variants (a,b,c); compare searches each "
                    "variant's learning rate itself (compare.search)"
                )
            prefix = "+" if override.is_add() else ""
            values = list(override.sweep_string_iterator())
            axes.append((key, [f"{prefix}{key}={value}" for value in values]))
        elif override.is_delete():
            raise UserError(f"'{override.input_line}': physgrad compare cannot delete keys")
        else:
            common.append(override.input_line)
    return settings, axes, common, hydra_args


def _compare_setting(override: Override, name: str, settings: dict) -> None:
    """compare.<name>=value into settings (a search range under settings["search"])."""
    top = name.split(".")[0]
    if top not in SETTINGS:
        raise UserError(f"unknown setting compare.{name} (choose from {', '.join(SETTINGS)})")
    if override.is_sweep_override():
        raise UserError(
            f"'{override.input_line}': compare.{name} takes one value (a comma in a folder name: "
            f"quote it, compare.{name}='a,b')"
        )
    if top == "search":
        value = override.value()
        if name == "search" or not (
            isinstance(value, list)
            and len(value) == 2
            and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < float("inf")
                for v in value
            )
            and value[0] < value[1]
        ):
            raise UserError(
                f"{override.input_line}: give compare.search.<optim key>=[low,high] with "
                "0 < low < high, both finite (a log-uniform range)"
            )
        settings.setdefault("search", {})[name[len("search.") :]] = (
            float(value[0]),
            float(value[1]),
        )
    else:
        settings[top] = override.value()


def study_settings(given: dict) -> StudySettings:
    from physgrad.validate import number

    values = {key: default for key, (default, _) in SETTINGS.items()}
    values.update(given)
    number("compare.trials", values["trials"], 1, 10_000, integer=True)
    number("compare.studies", values["studies"], 1, 100, integer=True)
    from physgrad.job_spec import SEEDS_LIMIT

    # an evaluation job trains every seed of a variant together, and a job holds at most SEEDS_LIMIT
    number("compare.seeds", values["seeds"], 1, SEEDS_LIMIT + 1, integer=True)
    number("compare.seed", values["seed"], 0, 2**32, integer=True)
    number("compare.tune_seed", values["tune_seed"], 0, 2**32, integer=True)
    number("compare.margin", values["margin"], 1, open_low=True)
    number("compare.alpha", values["alpha"], 0, 1, open_low=True)
    from physgrad.trainer_settings import CLOCKS
    from physgrad.validate import choice

    choice("compare.clock", values["clock"], CLOCKS)
    settings = StudySettings(**values)
    if settings.dir is not None and "${" in str(settings.dir):
        # the folder reaches the phases' jobs as a config value, where OmegaConf would resolve it
        # to another folder: the jobs would write where the study never looks
        raise UserError(
            f"compare.dir={settings.dir}: '${{' would be resolved as an interpolation in the "
            "study's jobs, which would then write into another folder; give the folder itself"
        )
    for flag in ("tune", "knobs"):
        if not isinstance(settings[flag], bool):
            raise UserError(f"compare.{flag}={settings[flag]!r}: use true or false")
    for key in ("tuned_in", "calibration"):
        if settings[key] is not None and not isinstance(settings[key], str):
            raise UserError(f"compare.{key}={settings[key]!r}: give a path")
    if settings.tuned_in is not None and not settings.tune:
        raise UserError("compare.tuned_in tunes nothing here: leave compare.tune=false out")
    last_tuning = settings.tune_seed + settings.studies - 1
    last_evaluation = settings.evaluation_seeds[-1]
    if settings.tune_seed <= last_evaluation and settings.seed <= last_tuning:
        raise UserError(
            f"the tuning seeds {settings.tune_seed}..{last_tuning} (compare.tune_seed, one per "
            f"study) overlap the evaluation seeds {settings.seed}..{last_evaluation} "
            f"(compare.seeds={settings.seeds} per study): tuning and evaluation seeds must differ"
        )
    from physgrad.job_spec import SEED_LIMIT

    if max(last_evaluation, last_tuning) >= SEED_LIMIT:
        raise UserError(
            f"the study's seeds reach {max(last_evaluation, last_tuning)}: seeds must stay below "
            f"{SEED_LIMIT} (2^32); lower compare.seed or compare.tune_seed"
        )
    return settings


# --- the variants
# ------------------------------------------------------------------------------------------


def variant_name(overrides: list[str]) -> str:
    """adam; hig; bptt clip=norm: a group's choice by its value, a key by its last part and
    value."""
    parts = []
    for override in overrides:
        key, _, value = override.lstrip("+").partition("=")
        parts.append(value if "." not in key else f"{key.rsplit('.', 1)[-1]}={value}")
    return " ".join(parts)


def build_variants(
    axes: list[tuple[str, list[str]]],
    common: list[str],
    settings: StudySettings,
    config_dirs: list[str],
) -> list[Variant]:
    from physgrad.configs import checked_config

    if not axes:
        raise UserError(
            "nothing to compare: list two or more variants, e.g. optim=adam,gauss_newton,hig"
        )
    variants, combinations = [], {}  # variants that share their options compose them once
    for combo in itertools.product(*(values for _, values in axes)):
        overrides = list(combo)
        cfg = checked_config([*common, *overrides], config_dirs, combinations)
        space = search_space(cfg, settings.search, settings.knobs) if settings.tune else {}
        variants.append(Variant(variant_name(overrides), overrides, cfg, space))
    if len(variants) < 2:
        raise UserError(
            "nothing to compare: list two or more variants, e.g. optim=adam,gauss_newton,hig"
        )
    unknown = [k for k in settings.search if all(k not in v.config.optim for v in variants)]
    if settings.tune and unknown:
        raise UserError(
            f"compare.search.{unknown[0]} is a setting of none of the variants' rules: name a key "
            "of their optim config (e.g. compare.search.learning_rate=[1e-4,1e-1])"
        )
    names = [v.name for v in variants]
    if len(set(names)) < len(names):
        raise UserError(
            f"two variants have the same name ({', '.join(names)}): give distinct values"
        )
    if settings.baseline is not None and settings.baseline not in names:
        raise UserError(
            f"compare.baseline={settings.baseline} is not one of the variants "
            f"({', '.join(names)}): name one of them"
        )
    return variants


def check_variants_build(variants: list[Variant], seed: int, built: dict | None = None) -> None:
    """Every variant's run config checked and its scene and rule built as its jobs will (on the
    tuning seed), so that a variant the scene refuses (a backprop mode on a scene without time, a
    bad setting) stops the study in one line before anything trains. built: the scenes built so
    far, by physgrad.experiment.scene_key (filled in; a caller checking several studies passes one
    to build each distinct scene once)."""
    from omegaconf import open_dict

    from physgrad.experiment import prepare
    from physgrad.job_spec import checked

    # variants that differ in their rule alone share one scene: built once
    built = {} if built is None else built
    for variant in variants:
        cfg = variant.config.copy()
        with open_dict(cfg):
            del cfg["hydra"]
        try:
            spec = checked(cfg)
            key = spec.scene_key([seed])
            scene, _, seeds = prepare(spec, [seed], built=built.get(key))
            built[key] = (scene, seeds)
        except UserError as error:
            raise UserError(f"variant {variant.name}: {error}") from None
        except Exception as error:  # noqa: BLE001 - the scene's or rule's own code: one line
            raise UserError(
                f"variant {variant.name}: building its scene and rule failed "
                f"({innermost_cause(error)}); `physgrad run` with its overrides shows the traceback"
            ) from None


def budget_of(cfg: DictConfig) -> tuple[str, float]:
    """The study's budget from a variant's config (readout.budget_of, the runner's default
    iterations where trainer.iterations is unset)."""
    from physgrad.trainer_settings import DEFAULT_ITERATIONS

    return budget_of_config(cfg, DEFAULT_ITERATIONS)
