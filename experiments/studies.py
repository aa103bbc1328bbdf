"""The studies of the claims profiles (experiments/conf/studies.yaml) as `physgrad compare`
commands: each study's variants, seeds, trials and tuning studies, its presets' twin, the networks
it continues from, its expected cost on the 2-core machine, and the parts of at most about 80
minutes `make reproduce-figures PROFILE=... ARGS="--part K"` runs one at a time.

Every study is a `physgrad compare` (docs/protocol.md): each variant tuned with the same trial
points in each of its independent tuning studies, evaluated at its best trial on paired seeds; its
untuned twin (`<study>-preset`, compare.tune=false) evaluates the presets on the first study's
seeds and clock. A study with repeated tuning studies runs one compare per tuning study, in
<study>/study-k, with the tuning seed, trial points and evaluation seeds study k has in one compare
of all of them, so that each part can run on any machine and be kept on its own.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import yaml
from evidence import CLOCK, STUDY_FOLDER, busy_clock  # experiments/

from physgrad.errors import UserError

CONF = Path(__file__).resolve().parent / "conf"
EVIDENCE = Path(__file__).resolve().parent.parent / "docs" / "evidence" / "claims"
PART_SECONDS = 80 * 60  # a part of a profile: it resumes within a 90-minute window
TUNE_SEED = (
    1_000_000  # compare's default tuning seed: a study that continues networks needs one too
)


@dataclass(frozen=True)
class Start:
    """Networks a study continues from (init_from): one `physgrad run` job per seed, evaluation and
    tuning seeds."""

    name: str
    overrides: tuple[str, ...]
    job_seconds: float  # one job on the 2-core machine, start-up and compilation included


@dataclass(frozen=True)
class Study:
    """One `physgrad compare` of the profile, into <profile folder>/<name> (and <name>-preset,
    untuned)."""

    name: str
    # compare's overrides: variant axes (comma lists) and common settings
    overrides: tuple[str, ...]
    trials: int
    seeds: int
    tune_seconds: float  # one tuning job on the 2-core machine (start-up and compilation included)
    eval_seconds: float  # one evaluation job (all seeds of a variant when they train together)
    start: Start | None = None
    preset: bool | str = (
        True  # also evaluate the presets untuned (a key=value: with that override replaced)
    )
    studies: int = 1  # independent tuning studies (compare.studies); CLAIM_STUDIES for the claims
    # tuning study k of the `studies` as a compare of its own in <name>/study-k (slices); 0: all
    # of them in one compare in <name>
    tuning_study: int = 0
    # false: the presets evaluated untuned in <name> (compare.tune=false), the study itself; its
    # preset (a key=value) then names the axis it fixes
    tune: bool = True
    # the name of a study this one adds variants to (run as a compare of its own, on the same
    # budget and seeds, e.g. the clipping modes beside a kept study without clipping): its runs
    # are kept as its own evidence and read as that study's
    joins: str = ""
    # (a scene's kept record, k): where the folder compare.tuned_in names has no trials.csv (the
    # machine that ran it is gone), the trials tuning study k kept in that record stand for it
    tuned_from: tuple[Path, int] | None = None

    @property
    def label(self) -> str:
        return self.name + (
            f" (tuning study {self.tuning_study} of {self.studies})" if self.tuning_study else ""
        )

    @property
    def folder(self) -> str:
        """The study's folder under the profile's: <name>/study-k for tuning study k."""
        k = self.tuning_study
        return f"{self.name}/{STUDY_FOLDER.format(k=k)}" if k else self.name

    @property
    def twin(self) -> bool:
        """Whether the study has a presets' twin (<name>-preset): a tuned study whose presets are
        also evaluated untuned."""
        return self.tune and self.preset is not False

    def kept(self, evidence: Path, preset: bool = False) -> bool:
        """Whether its runs are kept as evidence in `evidence` (docs/evidence/<profile>): the
        presets' twin's table, or this tuning study in the study's record (every planned one for
        a study of all its tuning studies in one compare). A part run again skips what is kept:
        its folder may have gone with its machine; but not a timed study whose kept clock was
        calibrated on a busy machine, which runs again. UserError for a damaged table."""
        from evidence import read_json, read_kept

        path = evidence / f"{self.name}{'-preset' if preset else ''}.csv"
        clock = evidence / CLOCK.format(name=self.name)
        if not path.is_file() or (self.timed and busy_clock(clock)):
            return False  # a busy kept clock bought fewer steps than the budget says: run again
        kept = read_kept(path)
        if preset or not self.tune:
            return bool(kept.studies)
        records = read_json(path.with_suffix(".json")).get("tuning_studies") or {}
        wanted = [self.tuning_study] if self.tuning_study else range(1, self.studies + 1)
        return isinstance(records, dict) and all(str(k) in records for k in wanted)

    def variant_names(self, preset: bool = False) -> list[str]:
        """The names compare gives the study's variants (with preset: its presets' twin's)."""
        import itertools

        from physgrad.comparison.spec import split_overrides, variant_name

        _, axes, _, _ = split_overrides(self.preset_overrides(preset))
        return [variant_name(list(c)) for c in itertools.product(*(v for _, v in axes))]

    def variants(self, preset: bool = False) -> int:
        return math.prod(
            len(_values(o)) for o in self.preset_overrides(preset) if len(_values(o)) > 1
        )

    def preset_overrides(self, preset: bool = True) -> list[str]:
        if not preset or not isinstance(self.preset, str):
            return list(self.overrides)
        key = self.preset.partition("=")[0]
        return [self.preset if o.partition("=")[0] == key else o for o in self.overrides]

    @property
    def timed(self) -> bool:
        return any(o.startswith("trainer.time_budget=") for o in self.overrides)

    def searching(self, preset: bool = False) -> int:
        """How many of the study's variants are of a rule that searches a line (L-BFGS, SSBFGS,
        SSBroyden: capabilities.line_search), whose evaluation seeds train one job each."""
        overrides = self.preset_overrides(preset)
        optims = next((_values(o) for o in overrides if o.startswith("optim=")), ["adam"])
        searching = sum(_searches(name) for name in optims)
        return searching * (self.variants(preset) // len(optims))

    @property
    def measured_clock(self) -> bool:
        return self.timed and "compare.clock=measured" in self.overrides

    def eval_jobs(self, preset: bool = False) -> int:
        """A tuning study's evaluation jobs as compare launches them (tuning.seeds_together): a
        variant's seeds in one job, but one job per seed on the measured clock, for networks
        continued from their own start (init_from) and for a rule that searches a line."""
        if self.measured_clock or self.start is not None:
            return self.variants(preset) * self.seeds
        alone = self.searching(preset)
        return self.variants(preset) - alone + alone * self.seeds

    def eval_job_seconds(self, preset: bool = False) -> float:
        """The evaluation's expected time in one tuning study: eval_seconds a job, plus, for a
        time budget, each further seed's budget in a job whose seeds train together."""
        together = self.eval_jobs(preset) - self.searching(preset) * self.seeds
        if not self.timed or self.measured_clock or self.start is not None:
            together = 0
        return self.eval_jobs(preset) * self.eval_seconds + together * (self.seeds - 1) * (
            self.time_budget
        )

    @property
    def time_budget(self) -> float:
        """The time budget in seconds (0 for a budget in iterations)."""
        given = [o for o in self.overrides if o.startswith("trainer.time_budget=")]
        return float(given[0].partition("=")[2]) if given else 0.0

    def clock(self, root: Path) -> Path | None:
        """The calibration a tuning study after the first and the presets' twin run on: the
        study's kept clock (whatever machine ran its first study), else the first study's own in
        root; None (the study calibrates itself) if there is neither. A calibration measured on a
        busy machine is none: it would charge this study's steps their cost beside other work."""
        for path in (EVIDENCE / CLOCK.format(name=self.name), root / self.name / "study-1"):
            path = path / "calibration.json" if path.suffix != ".json" else path
            if path.is_file() and not busy_clock(path):
                return path
        return None

    def command(self, root: Path, preset: bool = False) -> list[str]:
        overrides = [o.replace("{root}", str(root)) for o in self.preset_overrides(preset)]
        if self.tuned_from is not None:
            overrides = [kept_tuned_in(o, *self.tuned_from) for o in overrides]
        k = self.tuning_study
        folder = f"{self.name}-preset" if preset else self.folder
        settings = [
            f"compare.dir={root / folder}",
            f"compare.seeds={self.seeds}",
            f"compare.trials={self.trials}",
            # repeated tuning studies (docs/protocol.md), each a compare of its own with the
            # tuning seed and evaluation seeds study k has in one compare of all of them; the
            # untuned presets are one study (the first's seeds)
            f"compare.studies={1 if preset or k else self.studies}",
            *(
                (f"compare.seed={(k - 1) * self.seeds}", f"compare.tune_seed={TUNE_SEED + k - 1}")
                if k and not preset
                else ()
            ),
        ]
        if preset or not self.tune:
            settings.append("compare.tune=false")
        clock = self.clock(root) if self.timed and (preset or k > 1) else None
        if clock is not None:  # on the first tuning study's clock
            settings.append(f"compare.calibration={started_clock(root / folder, clock)}")
        return [*overrides, *settings]

    def start_seeds(self, preset: bool = False) -> list[int]:
        """The seeds a study that continues networks needs a start network for: the evaluation
        seeds and tuning seed of each tuning study it runs (study k: (k - 1) * seeds .. k * seeds
        - 1 and compare's tune_seed + k - 1); the presets' twin, the first study's."""
        ks = [self.tuning_study] if self.tuning_study else range(1, self.studies + 1)
        ks = [1] if preset else ks
        return [
            *(s for k in ks for s in range((k - 1) * self.seeds, k * self.seeds)),
            *(TUNE_SEED + k - 1 for k in ks),
        ]

    def seconds(self) -> float:
        """The expected wall time: tuning, evaluation, the presets' evaluation, the start networks,
        calibration."""
        new = 1 if self.tuning_study else self.studies  # the tuning studies this command runs
        trials = self.trials if self.tune else 0
        total = new * (trials * self.variants() * self.tune_seconds + self.eval_job_seconds())
        total += self.eval_job_seconds(preset=True) if self.twin else 0.0
        if self.start:
            seeds = set(self.start_seeds()) | set(self.start_seeds(True) if self.twin else ())
            total += len(seeds) * self.start.job_seconds
        # the first tuning study calibrates the clock; the later ones run on it (kept or in root)
        calibrates = self.timed and self.tuning_study <= 1
        return total + (30.0 * self.variants() if calibrates else 0.0)


@functools.cache  # a plan asks it of every study's rules, often: a file of the package, read once
def _searches(optim: str) -> bool:
    """Whether the rule of conf/optim/<optim>.yaml searches a line (capabilities.line_search)."""
    from physgrad.configs import CONF_DIR
    from physgrad.optim.capabilities import capabilities

    path = CONF_DIR / "optim" / f"{optim}.yaml"
    return path.is_file() and capabilities(rule_config(optim)).line_search


def rule_config(optim: str) -> dict:
    """conf/optim/<optim>.yaml with the rule files its `defaults` name merged under it (Hydra's
    order: each default, then the file itself), so that a rule defined on another's kernel
    (gauss_newton on hig's) has that kernel's _target_ and capabilities."""
    from physgrad.configs import CONF_DIR

    own = yaml.safe_load((CONF_DIR / "optim" / f"{optim}.yaml").read_text()) or {}
    merged: dict = {}
    for default in own.pop("defaults", None) or ["_self_"]:
        merged.update(own if default == "_self_" else rule_config(str(default)))
    return merged


def _values(override: str) -> list[str]:
    """The values of a comma-list override (a variant axis); one value otherwise. Quoted values are
    one value."""
    value = override.partition("=")[2]
    if value.startswith(("'", '"', "[")):
        return [value]
    return value.split(",")


def _start(entry: dict) -> Start:
    return Start(
        str(entry["folder"]), tuple(str(entry["overrides"]).split()), float(entry["job_seconds"])
    )


OWN = ("overrides", "start")  # the keys of a study's entry that are read, not passed on


def load_profiles(path: Path = CONF / "studies.yaml") -> dict[str, tuple[Study, ...]]:
    """The profiles' studies from their YAML file: each study's name and compare overrides (a
    string: variant axes as comma lists, `{root}` for the profile's folder), its per-job costs on
    the 2-core machine, the networks it continues from (a key of `starts`), its presets' twin
    (false: none; a key=value: the twin fixes that axis) and, where it departs from the file's
    protocol, its trials, seeds or tuning studies. A key the file does not define is a UserError."""
    config = yaml.safe_load(path.read_text())
    try:
        protocol = {k: int(v) for k, v in config["protocol"].items()}
        starts = {name: _start(entry) for name, entry in config["starts"].items()}
        return {
            profile: tuple(
                Study(
                    **{**protocol, **{k: v for k, v in entry.items() if k not in OWN}},
                    overrides=tuple(str(entry["overrides"]).split()),
                    start=starts[entry["start"]] if "start" in entry else None,
                )
                for entry in studies
            )
            for profile, studies in config["profiles"].items()
        }
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise UserError(f"{path}: {type(error).__name__}: {error}") from None


PROFILES = load_profiles()
STUDIES = tuple(s for s in PROFILES["claims"] if s.studies > 1)  # the claims' studies
MAP = tuple(s for s in PROFILES["claims"] if s.studies == 1)  # the regime map's cells
LONG, GPU = PROFILES["claims-long"], PROFILES["claims-gpu"]


def starts(studies) -> list[Start]:
    found = []
    for study in studies:
        if study.start is not None and study.start not in found:
            found.append(study.start)
    return found


def slices(study: Study) -> list[Study]:
    """A study with repeated tuning studies as one compare per tuning study, each in a folder of
    its own (<name>/study-k), so that each is kept whatever machine ran the others; the untuned
    presets with the first (on its seeds, its start networks and its clock). A study of one tuning
    study is itself."""
    if study.studies == 1:
        return [study]
    return [
        replace(study, tuning_study=k, preset=study.preset if k == 1 else False)
        for k in range(1, study.studies + 1)
    ]


def chunks(studies, limit_seconds: float = PART_SECONDS) -> list[list[Study]]:
    """The studies in order, each cut into its tuning studies (slices), grouped into parts of at
    most limit_seconds expected; a slice longer than that is a part of its own (it resumes job by
    job)."""
    parts, current, used = [], [], 0.0
    for study in (piece for whole in studies for piece in slices(whole)):
        if current and used + study.seconds() > limit_seconds:
            parts.append(current)
            current, used = [], 0.0
        current.append(study)
        used += study.seconds()
    return parts + ([current] if current else [])


WHERE = (("claims", "decidable on 2 cores"), ("claims-gpu", "needs a GPU"))


def where_it_runs(names: set[str], profiles: tuple = WHERE) -> str:
    """Where a claim whose studies are `names` can be decided, from the profiles' plans: the parts
    of the claims profile (2 cores) that run them and their expected hours, and the claims-gpu
    parts where a GPU's budget is planned (profiles: other (profile, what it needs) pairs, e.g. a
    longer profile's); "no profile runs it yet" otherwise."""
    said = []
    for profile, machine in profiles:
        parts = _parts_and_seconds(profile)
        used = [k for k, part in enumerate(parts, 1) if any(n in names for n, _ in part)]
        if not used or not names <= {n for k in used for n, _ in parts[k - 1]}:
            continue
        seconds = sum(t for k in used for n, t in parts[k - 1] if n in names)
        which = ("part " if len(used) == 1 else "parts ") + ", ".join(map(str, used))
        length = (
            f"about {seconds / 3600:.1f} h" if seconds >= 5400 else f"about {seconds / 60:.0f} min"
        )
        said.append(
            f"{machine}: {profile} {which}, {length}"
            + (" on one GPU" if profile == "claims-gpu" else "")
        )
    return "; ".join(said) or "no profile runs it yet"


def longer_not_run(names: set[str], profile: str) -> str:
    """A longer profile's cell for a claim it has not run: "not run yet" and where it runs."""
    needs = "needs a GPU" if profile == "claims-gpu" else "on 2 cores"
    return f"not run yet: {where_it_runs(names, ((profile, needs),))}"


@functools.lru_cache(maxsize=8)
def _parts_and_seconds(profile: str) -> tuple[tuple[tuple[str, float], ...], ...]:
    """A profile's parts as (study name, expected seconds) pairs, computed once (where_it_runs asks
    for every claim)."""
    return tuple(tuple((s.name, s.seconds()) for s in part) for part in chunks(PROFILES[profile]))


def started_clock(folder: Path, clock: Path) -> Path:
    """The calibration a half-run study in folder was started on where it is the same clock as
    `clock` under another name (the first study's own file, kept into the evidence since): the
    study resumes, where the new name would make compare refuse its folder as another study's;
    `clock` otherwise (no study there, another clock, an unreadable record)."""
    from evidence import read_json

    try:
        record = read_json(folder / "study.json")
        given = [
            o.split("=", 1)[1]
            for o in record["overrides"]
            if isinstance(o, str) and o.startswith("compare.calibration=")
        ]
        earlier = Path(given[0])
        if earlier != clock and earlier.is_file() and read_json(earlier) == read_json(clock):
            return earlier
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError):
        pass
    return clock


TUNED_IN = "compare.tuned_in="


def kept_tuned_in(override: str, record: Path, k: int) -> str:
    """compare.tuned_in=F itself where F exists (finished or not) or `record` (a scene's kept
    .json) holds no trials of tuning study k; else compare.tuned_in=F.kept, a folder whose
    trials.csv holds those kept trials (each trial's variant, values and validation loss, in the
    order kept; a finite loss COMPLETE, any other FAIL), from which compare picks each variant's
    best by its own rule, so that a study read at a longer budget runs where its tuning study's
    folder has gone (written when the command is made, the plan's included: a small table). Any
    other override unchanged."""
    import csv
    import io

    from evidence import read_json

    from physgrad.files import make_folder, replace_file

    if not override.startswith(TUNED_IN):
        return override
    folder = Path(override.removeprefix(TUNED_IN))
    if os.path.lexists(folder):  # the study is here, finished or not: compare reads it (or says)
        return override
    try:
        trials = read_json(record)["tuning_studies"][str(k)]["trials"]
        assert isinstance(trials, list) and all(isinstance(t, dict) for t in trials)
    except (OSError, ValueError, KeyError, TypeError, AssertionError):
        return override  # nothing kept: compare says in one line that F has no finished study
    keys = sorted({key for t in trials for key in t} - {"variant", "validation_loss"})
    out = io.StringIO()
    table = csv.writer(out, lineterminator="\n")
    table.writerow(["variant", "study", "trial", "state", *keys, "validation_loss"])
    for number, trial in enumerate(trials):
        loss = trial.get("validation_loss")
        done = isinstance(loss, (int, float)) and math.isfinite(loss)
        values = [trial.get(key, "") for key in keys]
        table.writerow(
            [trial.get("variant"), 0, number, "COMPLETE" if done else "FAIL", *values, loss]
        )
    kept = folder.with_name(folder.name + ".kept")
    make_folder(kept, levels=3)
    replace_file(kept / "trials.csv", out.getvalue().encode())
    return TUNED_IN + str(kept)
