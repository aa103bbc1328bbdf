"""The papers' claims as `physgrad compare` studies: which studies the claims profile runs, how each
claim is read from them, claims.md with tuned and preset verdicts side by side, and the regime map
(payoff.png).

Usage: python experiments/claims.py STUDIES_FOLDER [OUT_FOLDER]
(STUDIES_FOLDER holds the profile's study folders: outputs/experiments/claims, or .../claims-long
or .../claims-gpu for that profile's markdown; or their kept evidence, docs/evidence/claims.)
python experiments/claims.py --keep STUDIES_FOLDER docs/evidence/claims keeps the finished studies'
evidence (experiments/evidence.py).

Every study is a `physgrad compare` (docs/protocol.md): each variant tuned with the same trial
points (8 per variant) in each of 4 independent tuning studies, scored by its validation loss on
the tuning seed, then evaluated at its best trial on 10 paired seeds, the verdicts from the test
loss; its untuned twin (`<study>-preset`, compare.tune=false) evaluates the presets on the same
seeds and clock. Time budgets run on the calibrated clock (iterations x each variant's calibrated
step cost). A claim is read from the studies' evaluation runs with physgrad's own rules
(physgrad.claim: its parts and how each is decided), at X/4, X/2 and X of the budget X (the same
runs, tuned for X, read earlier).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml
from evidence import (  # experiments/
    CLOCK,
    STUDY_FOLDER,
    commit,
    keep_clock,
    kept_row,
    kept_table,
    merged_rows,
    read_kept,
    write_kept,
)
from studies import CONF, GPU, MAP, PROFILES, STUDIES, Study  # experiments/

from physgrad.claim import (
    FAILS,
    HOLDS,
    NOT_RUN,
    OPEN,
    Claim,
    Close,
    Decision,
    Grows,
    Lower,
    Reaches,
    Stalls,
    claim_of_part,
    claim_verdict,
    decide_parts,
    short,
    studies_of,
    tuning_studies,
)
from physgrad.errors import UserError
from physgrad.readout import highest_median
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    EQUIVALENT,
    FRACTIONS,
    claim_word,
    compare_variants,
    left_start,
    ratio_of,
)

# --- the studies
# ------------------------------------------------------------------------------------------


# --- the claims
# -------------------------------------------------------------------------------------------


PART_KINDS = {"lower": Lower, "close": Close, "grows": Grows, "stalls": Stalls, "reaches": Reaches}


def _part(entry: dict) -> object:
    """A claim's part from its entry: its kind as the key of its study (grows: [easy, hard]), then
    its own fields (physgrad.claim)."""
    (kind,) = set(entry) & set(PART_KINDS)
    rest = {k: v for k, v in entry.items() if k != kind}
    if kind == "grows":
        return Grows(*entry[kind], **rest)
    return PART_KINDS[kind](entry[kind], **rest)


def load_claims(path: Path = CONF / "claims.yaml") -> tuple[Claim, ...]:
    """The claims from their YAML file: each claim's name, the paper's statement and where, its
    parts, how the comparison departs, and the paper's budget; anything else is a UserError."""
    try:
        return tuple(
            Claim(**{**entry, "parts": tuple(_part(p) for p in entry["parts"])})
            for entry in yaml.safe_load(path.read_text())["claims"]
        )
    except (KeyError, TypeError, ValueError) as error:
        raise UserError(f"{path}: {type(error).__name__}: {error}") from None


CLAIMS = load_claims()


# --- reading a study
# --------------------------------------------------------------------------------------


@dataclass
class StudyRuns:
    """A study's evaluation runs: variant -> seed -> results file, with the budget and its axis."""

    folder: Path
    axis: str
    budget: float
    paths: dict
    machine: str = ""
    # with repeated tuning studies: every study's runs, the first (this one's paths) included
    tuning: tuple = ()
    # read from kept evidence (experiments/evidence.py): {(variant, column): {seed: KeptCurve}}
    kept: dict | None = None
    protocol: tuple | None = None  # kept evidence: (trials, tuning studies, seeds)
    # the tuning studies the study is to have (0: those it has); a part is decided by a majority
    # of them, so that two of four run cannot decide it alone
    planned: int = 0

    def curves(self, variant: str, column: str = "loss") -> dict:
        from physgrad.readout import run_curve
        from physgrad.results import read_run

        if self.kept is not None:
            return dict(self.kept.get((variant, column), {}))

        found, unreadable = {}, []
        for seed, path in self.paths.get(variant, {}).items():
            try:
                found[seed] = run_curve(read_run(Path(path)), self.axis, column)
            except ValueError as error:
                unreadable.append(str(error))
        if unreadable:
            print(
                f"claims: {variant} in {self.folder}: left out {len(unreadable)} runs, e.g. "
                f"{unreadable[0]}",
                file=sys.stderr,
            )
        return found


def read_study(folder: Path) -> StudyRuns | None:
    """The study's runs.csv (written by physgrad compare) as StudyRuns of its first tuning study,
    with every tuning study's in `tuning` where it has several (Lower and Close parts are decided
    over them by the package's rule, physgrad.verdict.across_studies; the trend and stall parts
    are decided in each and over them by the same rule, verdict.over_studies; the regime map reads
    the first); None if the study has not finished. The table is data from a folder
    that may come from someone else: each run's file is looked for in the folder's own eval/ (the
    part of its recorded path from "eval" on), never at the path as written (an absolute path or
    "..": anywhere); a row whose seed, budget or path cannot be read so is a UserError (one
    line)."""
    import pandas as pd

    from physgrad.errors import UserError

    table = folder / "runs.csv"
    if not table.is_file():
        kept = kept_table(folder)
        if kept is not None:
            return _kept_runs(read_kept(kept))
        return _tuning_study_runs(folder)
    try:
        table_runs = pd.read_csv(table, dtype=str)
    except ValueError as error:  # pandas' parse errors, an empty file, bytes that are no text
        why = (str(error).splitlines() or [type(error).__name__])[0][:200]
        raise UserError(f"{table}: not a table of runs ({why})") from None
    if "study" not in table_runs:  # written before repeated tuning studies: one study
        return _study_runs(folder, table, table_runs)
    found = [
        _study_runs(folder, table, table_runs[table_runs["study"].astype(str) == str(k)])
        for k in sorted(set(table_runs["study"].astype(str)), key=lambda k: (len(k), k))
    ]
    if not found or any(study is None for study in found):
        return None
    if len(found) == 1:
        return found[0]
    return replace(found[0], tuning=tuple(found))


def _planned(name: str) -> int:
    """The tuning studies a study of the profiles is to have (0: not one of theirs)."""
    return max((s.studies for p in PROFILES.values() for s in p if s.name == name), default=0)


def _tuning_study_runs(folder: Path) -> StudyRuns | None:
    """A study run one compare per tuning study (<folder>/study-k, slices) as StudyRuns: the
    first finished study's, with every finished one in `tuning`, in the order of k; None if none
    has finished. A study folder that is a link is not read (someone else's)."""
    from physgrad.errors import UserError

    subs = list(folder.iterdir()) if folder.is_dir() and not folder.is_symlink() else []
    found = {}
    numbered = (re.fullmatch(STUDY_FOLDER.format(k=r"([1-9][0-9]{0,5})"), p.name) for p in subs)
    for k in sorted(int(m[1]) for m in numbered if m):
        sub = folder / STUDY_FOLDER.format(k=k)
        if sub.is_symlink():
            raise UserError(f"{sub}: a link: refused (a study may come from someone else)")
        runs = read_study(sub) if (sub / "runs.csv").is_file() else None
        if runs is not None:
            if runs.tuning:
                raise UserError(
                    f"{sub}: {len(runs.tuning)} tuning studies, where a study-k folder holds one"
                )
            found[k] = runs
    if not found:
        return None
    studies = [replace(runs, planned=_planned(folder.name)) for runs in found.values()]
    return replace(studies[0], tuning=tuple(studies) if len(studies) > 1 else ())


def _kept_runs(kept) -> StudyRuns | None:
    """Kept evidence (experiments/evidence.py) as StudyRuns: every tuning study's, the first's
    with the others in `tuning`."""
    found = [
        StudyRuns(
            kept.path,
            kept.axis,
            kept.budget,
            {variant: {seed: str(kept.path) for seed in by} for (variant, _), by in curves.items()},
            kept.machine,
            kept=curves,
            protocol=kept.protocol,
            planned=kept.planned,
        )
        for curves in kept.studies
        if curves  # a tuning study not kept (yet)
    ]
    if not found:
        return None
    if len(found) > 1:
        found[0].tuning = tuple(found)
    return found[0]


def keep_evidence(root: Path, dest: Path) -> list[str]:
    """Every finished study of the claims under root, and its presets' twin, as evidence tables in
    dest (experiments/evidence.py): the columns the claims read of it, at the kept fractions of its
    budget, for every tuning study, variant and seed. A study run one compare per tuning study
    (<name>/study-k) adds each finished one to the kept table, replacing its rows if it was kept
    before and keeping the others' (each is kept whatever machine ran it), and keeps the first's
    calibration as the study's clock; a study run in one compare replaces every study it has.
    Returns the studies kept (<name>, or <name>/study-k)."""
    columns: dict[str, set] = {}
    for claim in CLAIMS:
        for part in claim.parts:
            for name in studies_of(claim_of_part(part)):
                columns.setdefault(name, {"loss"}).add(getattr(part, "column", "loss"))
    kept = []
    for name in sorted(columns):
        for folder in (root / name, root / f"{name}-preset"):
            runs = read_study(folder) if folder.is_dir() and not folder.is_symlink() else None
            if runs is None or runs.kept is not None:
                continue
            split = not (folder / "runs.csv").is_file()  # one compare per tuning study
            finished = {}
            for k, study in enumerate(tuning_studies(runs), 1):
                where = study.folder if split else folder
                k = int(where.name.partition("-")[2]) if split else k
                finished[k] = (
                    [
                        kept_row(k - 1, variant, seed, column, curve, runs.budget)
                        for variant in sorted(study.paths)
                        for column in sorted(columns[name])
                        for seed, curve in sorted(study.curves(variant, column).items())
                    ],
                    _study_record(where, study),
                )
                kept.append(f"{folder.name}/{where.name}" if split else folder.name)
            kept = list(dict.fromkeys(kept))  # a study run in one compare: its name once
            if split:
                rows, by_study = merged_rows(dest, folder.name, finished, runs.budget)
            else:  # one compare: it replaces what was kept
                rows = [row for found, _ in finished.values() for row in found]
                by_study = {str(k): record for k, (_, record) in finished.items()}
            trials, _, seeds = study_protocol(folder)
            about = {
                "study": folder.name,
                "axis": runs.axis,
                "budget": runs.budget,
                "trials": trials,
                "studies": len(by_study),
                "planned": max(_planned(name) if folder.name == name else 1, len(by_study)),
                "seeds": seeds,
                "machine": "; ".join(
                    sorted({str(r.get("machine") or "") for r in by_study.values()} - {""})
                ),
                # of physgrad, as the runs recorded it
                "commits": sorted({c for r in by_study.values() for c in r.get("commits", [])}),
                "kept_by": commit(),
                "overrides": by_study[min(by_study, key=int)].get("overrides", []),
                "tuning_studies": by_study,
            }
            write_kept(dest, folder.name, rows, about)
            if split:
                keep_clock(folder / "study-1" / "calibration.json", dest / CLOCK.format(name=name))
    return kept


def _study_record(folder: Path, runs: StudyRuns) -> dict:
    """What a kept tuning study records of itself: its machine, the physgrad commits its runs
    recorded, the commit that kept it and the compare overrides that ran it."""
    from physgrad.results import read_final

    ran = set()
    for by_seed in runs.paths.values():
        for path in by_seed.values():
            try:
                ran.add(str(read_final(Path(path))[0].get("git_commit", "unknown")))
            except (OSError, ValueError):
                ran.add("unreadable")
    overrides = []
    if (folder / "study.json").is_file():
        overrides = json.loads((folder / "study.json").read_text()).get("overrides", [])
    return {
        "machine": runs.machine,
        "commits": sorted(ran),
        "kept_by": commit(),
        "overrides": overrides,
    }


def _study_runs(folder: Path, table: Path, runs: object) -> StudyRuns | None:
    """One tuning study's rows of runs.csv as StudyRuns (read_study)."""
    from physgrad.errors import UserError

    if not len(runs) or not {"variant", "seed", "axis", "budget", "path"} <= set(runs.columns):
        return None
    if (folder / "eval").is_symlink():  # resolving it would make anywhere "inside"
        raise UserError(f"{folder / 'eval'}: a link: refused (a study may come from someone else)")
    inside = (folder / "eval").resolve()
    paths = {}
    for row in runs.itertuples():
        number = int(row.Index) + 2  # the table's line (a header, then rows from 0)
        parts = Path(str(row.path)).parts
        seed = str(row.seed)
        # a seed as physgrad writes one: ASCII digits below 2^32 ("²" is a digit to str.isdigit)
        if "eval" not in parts or not (seed.isascii() and seed.isdecimal() and len(seed) <= 10):
            raise UserError(f"{table} line {number}: not a run of this study (seed {seed!r})")
        path = folder.joinpath(*parts[len(parts) - 1 - parts[::-1].index("eval") :])
        if ".." in path.relative_to(folder).parts or not path.resolve().is_relative_to(inside):
            raise UserError(f"{table} line {number}: its path leaves {folder / 'eval'}")
        paths.setdefault(str(row.variant), {})[int(seed)] = str(path)
    try:
        budget = float(runs["budget"].iloc[0])
    except ValueError:
        raise UserError(f"{table}: budget {runs['budget'].iloc[0]!r} is not a number") from None
    machines = sorted(set(runs["machine"].astype(str))) if "machine" in runs else []
    return StudyRuns(folder, str(runs["axis"].iloc[0]), budget, paths, "; ".join(machines))


def _budget_text(runs: StudyRuns) -> str:
    return {
        "iteration": f"{runs.budget:g} iterations",
        "wall_time": f"{runs.budget:g} s (measured clock)",
        "calibrated_time": f"{runs.budget:g} s (calibrated clock)",
    }.get(runs.axis, f"{runs.budget:g}")


def decide_claim(
    claim: Claim, root: Path, suffix: str = "", fraction: float = 1.0, profile: tuple = ()
) -> tuple[str, list[tuple[object, Decision]]]:
    """The claim's verdict at `fraction` of its budget from the studies under root (suffix
    "-preset": the untuned twins) and its parts' (physgrad.claim). profile: the studies of the
    profile that ran them (default: the claims profile's)."""
    specs = {s.name: s for s in (profile or STUDIES + MAP)}
    cache: dict[str, object] = {}

    def study(name: str) -> object:
        if name not in cache:
            cache[name] = _twin_runs(root, name, suffix, specs.get(name))
        return cache[name]

    rows = decide_parts(claim, study, fraction)
    if suffix:  # a presets' twin that fixes an axis runs only the papers' value of it: say so
        fixed = {n: specs[n].preset for n in specs if isinstance(specs[n].preset, str)}
        rows = [
            (
                part,
                _fixed_by_twin(
                    d, [fixed[n] for n in sorted(studies_of(claim_of_part(part))) if n in fixed]
                ),
            )
            for part, d in rows
        ]
    return claim_verdict(rows, twin=bool(suffix)), rows


def _twin_runs(root: Path, name: str, suffix: str, spec: Study | None) -> object:
    """The runs of study `name` (suffix "-preset": its presets' twin), or the Decision that says
    why there are none."""
    runs = read_study(root / (name + suffix))
    if runs is None:
        if suffix and spec is not None and spec.preset is False:
            return Decision(NOT_RUN, "-", f"{name} has no presets' twin (cut for time)")
        return Decision(OPEN, "-", f"{root / (name + suffix)} has no finished study")
    if suffix and spec is not None and isinstance(spec.preset, str):
        # the presets' study fixes one value of an axis (optim.clip=none): its variants are also
        # known by the tuned study's names, which carry that value ("backprop=C" is "backprop=C
        # clip=none")
        key, _, value = spec.preset.partition("=")
        token = f"{key.rsplit('.', 1)[-1]}={value}"
        runs.paths.update({f"{v} {token}": by for v, by in list(runs.paths.items())})
    return runs


def _fixed_by_twin(decision: Decision, fixed: list[str]) -> Decision:
    """A part the presets' twin does not run because the twin fixes an axis (optim.clip=none, the
    papers' setting) says that, not which variants are missing."""
    if decision.verdict != NOT_RUN or not fixed:
        return decision
    return Decision(NOT_RUN, "-", f"the presets' twin runs {fixed[0]} only (the papers' setting)")


def _part_study(part) -> str:
    return getattr(part, "study", None) or f"{part.easy} -> {part.hard}"


def claims_table(root: Path, studies=None, only_run: bool = False) -> str:
    """One row per part of every claim whose studies are all among `studies` (default: every
    claim); with only_run, of the claims one of whose studies has finished."""
    names = {s.name for s in studies} if studies is not None else None
    lines = [
        "| claim (paper, where) | part | study, budget | tuned: measured | tuned: verdict | "
        "presets: measured | presets: verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for claim in CLAIMS:
        if names is not None and not studies_of(claim) <= names:
            continue
        if only_run and all(read_study(root / name) is None for name in studies_of(claim)):
            continue
        profile = tuple(studies) if studies is not None else ()
        verdict, rows = decide_claim(claim, root, profile=profile)
        preset_verdict, preset_rows = decide_claim(claim, root, "-preset", profile=profile)
        for i, ((part, d), (_, p)) in enumerate(zip(rows, preset_rows)):
            runs = read_study(root / getattr(part, "study", getattr(part, "hard", "")))
            budget = _budget_text(runs) if runs else "-"
            head = (
                (
                    f"**{claim.name}**: tuned **{verdict}**, presets **{preset_verdict}**. "
                    f"{claim.paper}" + (f" ({claim.note})" if claim.note else "")
                )
                if i == 0
                else ""
            )
            lines.append(
                f"| {head} | {part.text()} | {_part_study(part)}, {budget} | {d.measured} | "
                f"{d.verdict} ({d.why}) | {p.measured} | {p.verdict} ({p.why}) |"
            )
    return "\n".join(lines) + "\n"


def claim_verdicts(
    claim: Claim, root: Path, suffix: str = "", profile: tuple = ()
) -> dict[float, str]:
    """The claim's verdict at each fraction of the budget (FRACTIONS: X/4, X/2, X)."""
    return {f: decide_claim(claim, root, suffix, f, profile)[0] for f in FRACTIONS}


def study_protocol(folder: Path) -> tuple[int, int, int] | None:
    """What a finished study ran: (trials per variant and tuning study, tuning studies, seeds),
    read from its trials.csv and runs.csv (0 trials: untuned); None if it has not finished."""
    import pandas as pd

    runs = read_study(folder)
    if runs is None:
        return None
    if runs.protocol is not None:  # kept evidence says what the study ran
        return runs.protocol
    studies = len(runs.tuning) or 1
    seeds = max((len(by) for by in runs.paths.values()), default=0)
    trials = 0
    # one compare, or one per tuning study (<folder>/study-k)
    for table in [folder / "trials.csv", *(s.folder / "trials.csv" for s in tuning_studies(runs))]:
        if not table.is_file():
            continue
        try:
            rows = pd.read_csv(table)
        except ValueError:  # empty: an untuned study (the presets' twin) tried no trials
            rows = pd.DataFrame()
        if {"variant", "trial"} <= set(rows.columns) and len(rows):
            keys = ["variant", "study"] if "study" in rows.columns else ["variant"]
            trials = max(trials, int(rows.groupby(keys)["trial"].nunique().max()))
    return trials, studies, seeds


def _of_planned(runs: StudyRuns) -> str:
    """ " of N" where fewer of a study's N tuning studies have run (the majority is of N)."""
    ran = len(runs.tuning) or 1
    return f" of {runs.planned}" if runs.planned > ran else ""


def _main_study(claim: Claim) -> str:
    """The study that gives a claim its budget: the first part's (a trend's hard end)."""
    part = claim.parts[0]
    return part.hard if isinstance(part, Grows) else part.study


def _share_text(claim: Claim, runs: StudyRuns) -> str:
    """The budget here against the paper's, e.g. "1500 iterations: 4.7% of the paper's 32,000
    iterations"."""
    here = _budget_text(runs)
    seconds = runs.axis in ("wall_time", "calibrated_time")
    if math.isnan(claim.paper_budget) or seconds != claim.paper_seconds:
        return f"{here}; the paper's: {claim.paper_budget_text}"
    share = 100 * runs.budget / claim.paper_budget
    percent = f"{share:.2g}" if share < 10 else f"{share:.0f}"
    return f"{here}: {percent}% of the paper's {claim.paper_budget_text}"


def _share(claim: Claim, runs: StudyRuns) -> float:
    """The budget here over the paper's (NaN where the paper states none in these units)."""
    seconds = runs.axis in ("wall_time", "calibrated_time")
    if math.isnan(claim.paper_budget) or seconds != claim.paper_seconds:
        return math.nan
    return runs.budget / claim.paper_budget


def _claim_variants(claim: Claim, study: str) -> list[str]:
    names = []
    for part in claim.parts:
        if _part_study(part) == study:
            found = [part.variant] if isinstance(part, (Stalls, Reaches)) else [part.a, part.b]
            names += [n for n in found if n not in names]
    return names


def _left_start(claim: Claim, runs: StudyRuns) -> tuple[bool, str]:
    """Whether every variant of the claim's main study has left its start at X (the median over
    its seeds of loss at X / at its first evaluation, physgrad.verdict.left_start), and each
    variant's factor."""
    said, trained = [], True
    for variant in _claim_variants(claim, _main_study(claim)):
        if variant not in runs.paths:
            continue
        starts, finals = [], []
        for study in tuning_studies(runs):
            for curve in study.curves(variant).values():
                starts.append(float(curve.loss[0]) if len(curve.loss) else math.nan)
                finals.append(curve.at(study.budget))
        trained &= left_start(starts, finals)
        ratios = [f / s for s, f in zip(starts, finals) if s > 0 and not math.isnan(f)]
        factor = 1 / float(np.median(ratios)) if ratios else math.nan
        said.append(f"{variant} {short(factor)}x")
    return trained and bool(said), ", ".join(said)


def _verdicts_text(verdicts: dict[float, str]) -> list[str]:
    return [f"**{verdicts[f]}**" if f == 1.0 else verdicts[f] for f in FRACTIONS]


NOT_YET = "not run yet"


def headline_table(root: Path, profile: tuple, further: tuple = ()) -> str:
    """One row per claim: what its studies ran (trials per variant in each tuning study, tuning
    studies, paired seeds), the budget and its share of the paper's, the tuned verdict at X/4, X/2
    and X, the presets' at X, and, where a profile of longer budgets ran the claim (further:
    (folder, that profile's studies) pairs: claims-long, claims-gpu), its budget and verdicts at
    its X/4, X/2 and X, with what it ran. A claim that holds at one budget and does not at another
    says so first (apart, where one of the two is the GPU profile's: the machine changed too)."""
    lines = [
        "| claim | verdict | trials x tuning studies, seeds | budget here | loss fell from the "
        "start | tuned at X/4 | X/2 | X | presets at X | longer budget: X/4, X/2, X |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    names = {s.name for s in profile}
    for claim in CLAIMS:
        if not studies_of(claim) <= names:
            continue
        main = _main_study(claim)
        runs = read_study(root / main)
        if runs is None:
            lines.append(f"| {claim.name} | {NOT_YET} | | | | | | | | |")
            continue
        trials, studies, seeds = study_protocol(root / main)
        tuned = claim_verdicts(claim, root, profile=profile)
        preset, _ = decide_claim(claim, root, "-preset", 1.0, profile)
        if preset == OPEN and read_study(root / f"{main}-preset") is None:
            preset = NOT_YET  # the twin's study has not finished
        longer, seen, elsewhere = "not in a longer profile", list(tuned.values()), []
        for folder, studies_there in further:
            if not studies_of(claim) <= {s.name for s in studies_there}:
                continue
            long_runs = read_study(folder / main)
            if long_runs is None:
                longer = f"{NOT_YET} ({folder.name})"
                continue
            found = claim_verdicts(claim, folder, profile=studies_there)
            # the GPU's profile changes the machine with the budget: its turns are told apart
            (elsewhere if studies_there == GPU else seen).extend(found.values())
            t, k, n = study_protocol(folder / main)
            ran = f"{t} x {k}{_of_planned(long_runs)}, {n}"
            longer = f"{folder.name}, {_budget_text(long_runs)} ({ran}): " + ", ".join(
                _verdicts_text(found)
            )
        turned = (
            "**reverses with the budget**: "
            if HOLDS in seen and FAILS in seen
            else "**turns with a GPU's budget**: "
            if {HOLDS, FAILS} <= {*seen, *elsewhere}
            else ""
        )
        head = f"{turned}{claim.name}"
        trained, fell = _left_start(claim, runs)
        word, why = claim_word(
            tuned[1.0] == HOLDS,
            tuned[1.0] == FAILS,
            tuned[0.5] == FAILS,
            trained,
            _share(claim, runs),
            claim.departs,
        )
        lines.append(
            f"| {head} | **{word}** ({why}) | {trials} x {studies}{_of_planned(runs)}, {seeds} | "
            f"{_share_text(claim, runs)} | {fell} | "
            + " | ".join(_verdicts_text(tuned))
            + f" | {preset} | {longer} |"
        )
    return "\n".join(lines) + "\n"


# --- the regime map
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Cell:
    study: str
    conditioning: float  # the toy's lambda or the oscillators' coupling
    cost_ratio: float  # HIG's calibrated step cost / Adam's
    ratio: float  # median time-to-target HIG / Adam over the seeds
    low: float
    high: float
    reached: tuple[int, int, int]  # seeds where HIG, Adam reached the target, of n
    verdict: str


def map_cell(root: Path, study: Study) -> Cell | None:
    """One cell: the time each variant's seeds take to reach the cell's target, as per-seed ratios
    HIG / Adam with the verdict rule's median and interval (a seed that never reaches it counts as
    infinite, as a divergence does; a pair where neither does is left out and counted, as a pair
    where both diverged). The target is the higher of
    the two variants' median test loss at the budget (readout.highest_median): what the slower
    variant typically gets to, which the faster one reaches in most seeds. compare's target (the
    lower median) is reached by only about half the better variant's seeds, so with 6 seeds most
    pairs are two misses and no cell can be decided."""
    runs = read_study(root / study.name)
    if runs is None or not {"hig", "adam"} <= set(runs.paths):
        return None
    curves = {v: runs.curves(v) for v in ("hig", "adam")}
    _, target = highest_median(
        {v: [c.at(runs.budget) for c in by.values()] for v, by in curves.items()}
    )
    seeds = sorted(set(curves["hig"]) & set(curves["adam"]))
    times = {
        v: [
            curves[v][s].reaches(target, runs.budget) if math.isfinite(target) else math.inf
            for s in seeds
        ]
        for v in curves
    }
    (result,) = compare_variants(
        {v: {s: _constant(t) for s, t in zip(seeds, times[v])} for v in times},
        1.0,
        fractions=(0.25, 0.5, 1.0),
    )
    p = result.at[1.0]
    cost = math.nan
    calibration = root / study.name / "calibration.json"
    if calibration.is_file():
        try:
            costs = json.loads(calibration.read_text())["costs"]
            cost = float(costs["hig"]["step_seconds"]) / float(costs["adam"]["step_seconds"])
        except (OSError, ValueError, KeyError, TypeError, ZeroDivisionError):
            pass
    conditioning = float(
        re.search(r"task\.(?:scale|alpha)=([0-9.e-]+)", " ".join(study.overrides)).group(1)
    )
    reached = (
        sum(math.isfinite(t) for t in times["hig"]),
        sum(math.isfinite(t) for t in times["adam"]),
        len(seeds),
    )
    if not math.isfinite(target):  # both diverged in most seeds: nothing to reach, not "equivalent"
        return Cell(
            study.name, conditioning, cost, math.nan, math.nan, math.nan, reached, NO_TARGET
        )
    return Cell(
        study.name,
        conditioning,
        cost,
        p.ratio,
        ratio_of(p.low),
        ratio_of(p.high),
        reached,
        result.verdict,
    )


def _constant(value: float):
    """A time to target as a curve whose 'loss' is that time, read at x = 1 (inf: never reached)."""
    from physgrad.readout import Curve

    return Curve(np.array([0.0]), np.array([value]), 1.0, False, None)


NO_TARGET = "no target (both diverged in most seeds)"
MAP_VERDICTS = {A_BETTER: "HIG first", B_BETTER: "Adam first", EQUIVALENT: "within 10%"}


def plot_map(cells: dict[str, list[Cell]], path: Path, machine: str, note: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    panels = [(name, found) for name, found in cells.items() if found]
    fig, axes = plt.subplots(
        1, len(panels), figsize=(6.6 * len(panels), 5.0), squeeze=False, layout="constrained"
    )
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-2.0, vmax=2.0)
    for ax, (name, found) in zip(axes[0], panels):
        xs = sorted({c.conditioning for c in found}, reverse=name == "toy")
        rows = sorted({c.study.rsplit("_b", 1)[-1] if name == "toy" else "" for c in found})
        grid = np.full((len(rows), len(xs)), np.nan)
        for c in found:
            i = rows.index(c.study.rsplit("_b", 1)[-1] if name == "toy" else "")
            j = xs.index(c.conditioning)
            if not math.isnan(c.ratio):  # no target: left blank
                grid[i, j] = math.log10(min(max(c.ratio, 1e-2), 1e2))
            dark = abs(grid[i, j]) > 1.2
            ax.text(
                j,
                i,
                f"{MAP_VERDICTS.get(c.verdict, c.verdict)}\n{short(c.ratio)} [{short(c.low)}, "
                f"{short(c.high)}]\n"
                f"reached: HIG {c.reached[0]}, Adam {c.reached[1]} of {c.reached[2]}",
                ha="center",
                va="center",
                fontsize=7.5,
                color="white" if dark else "black",
            )
        image = ax.imshow(grid, cmap="RdBu_r", norm=norm, aspect="auto", origin="lower")
        costs = {
            r: np.nanmedian(
                [
                    c.cost_ratio
                    for c in found
                    if (c.study.rsplit("_b", 1)[-1] if name == "toy" else "") == r
                ]
                or [np.nan]
            )
            for r in rows
        }
        labels = [
            (f"batch {r}\n" if r else "") + f"HIG step\n= {short(costs[r])} x Adam's" for r in rows
        ]
        ax.set_yticks(range(len(rows)), labels, fontsize=8)
        ax.set_xticks(range(len(xs)), [f"{x:g}" for x in xs])
        ax.set_xlabel(
            "lambda (the second component's scale)\nbadly conditioned to the right"
            if name == "toy"
            else "coupling alpha (the cubic spring)\nstiffer to the right",
            fontsize=9,
        )
        ax.set_title(f"{name}: time to target, HIG / Adam (median [95% interval])", fontsize=9)
    fig.colorbar(image, ax=list(axes[0]), label="log10 HIG / Adam time to target (blue: HIG first)")
    fig.suptitle(
        f"Where HIG pays off: both tuned per cell, equal calibrated training time. {machine}"
        + (f"\n{note}" if note else ""),
        fontsize=8,
    )
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def regime_map(root: Path, out: Path, note: str = "") -> str:
    cells = {
        title: [c for s in MAP if task in s.overrides and (c := map_cell(root, s))]
        for title, task in (("toy", "task=toy"), ("oscillators", "task=oscillator"))
    }
    if not any(cells.values()):
        return ""
    machines = {read_study(root / s.name).machine for s in MAP if read_study(root / s.name)}
    machine = "; ".join(sorted(m for m in machines if m))
    plot_map(cells, out / "payoff.png", machine, note)
    lines = [
        "\n## Where HIG pays off: a regime map\n",
        "![payoff](payoff.png)\n",
        "Each cell is a `physgrad compare` of Adam and HIG, both tuned in that cell, at equal "
        "calibrated "
        "training time: the time each seed takes to reach the cell's target (the higher of the "
        "two variants' "
        "median test loss at the budget: what the slower one typically gets to), as the ratio HIG "
        "/ Adam with "
        "its 95% interval (below 1: HIG gets there first; a seed that never reaches the target "
        "counts as "
        "infinite, a pair where neither does as a tie; 0 or inf: in the middle pair one variant "
        f"got there and the other did not). Machine: {machine or '-'}.\n",
        "| study | conditioning | HIG step / Adam step | time to target HIG / Adam [95%] | "
        "reached HIG, Adam of n | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for found in cells.values():
        for c in found:
            lines.append(
                f"| {c.study} | {c.conditioning:g} | {short(c.cost_ratio)} | {short(c.ratio)} "
                f"[{short(c.low)}, {short(c.high)}] | "
                f"{c.reached[0]}, {c.reached[1]} of {c.reached[2]} | "
                f"{MAP_VERDICTS.get(c.verdict, c.verdict)} |"
            )
    return "\n".join(lines) + "\n"


def write(root: Path, out: Path, note: str = "", profile: str = "claims") -> str:
    """<profile>.md (claims.md, claims-long.md) into out from the studies under root, with the
    regime map (payoff.png) where the profile has it; returns the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    rule = __doc__.split("\n\n")[2]
    studies = PROFILES[profile]
    # the claims profile's headline also reads the profiles of longer budgets beside its folder
    further = (
        tuple((root.parent / name, PROFILES[name]) for name in ("claims-long", "claims-gpu"))
        if profile == "claims"
        else ()
    )
    text = (
        f"# The papers' claims, measured\n\n{note + chr(10) + chr(10) if note else ''}"
        + rule
        + "\n\n"
        f"Studies under {root}; each study's own table (variants, tuned settings, every pair, "
        "timing): `<study>/compare.md`. X is a study's budget; a verdict at X/4 or X/2 reads "
        "the same runs (tuned for X) earlier.\n\n"
        + headline_table(root, studies, further)
        + "\n"
        + claims_table(root, studies)
        + (regime_map(root, out, note) if set(MAP) <= set(studies) else "")
    )
    (out / f"{profile}.md").write_text(text)
    return text


GENERATED = (
    "<!-- generated from docs/evidence/claims by `python experiments/claims.py "
    "docs/evidence/claims --doc docs/claims.md`: edit the evidence, experiments/conf/claims.yaml "
    "or experiments/claims.py, not this block -->",
    "<!-- end of the generated block -->",
)


def evidence_block(root: Path) -> str:
    """The verdicts of every claim of the claims profile from its kept evidence under root: the
    headline table, then every part with its numbers."""
    studies = PROFILES["claims"]
    further = tuple(
        (root.parent / name, PROFILES[name])
        for name in ("claims-long", "claims-gpu")
        if (root.parent / name).is_dir()
    )
    machines = sorted(
        {
            runs.machine
            for s in studies
            for suffix in ("", "-preset")
            if (runs := read_study(root / f"{s.name}{suffix}")) is not None and runs.machine
        }
    )
    return (
        f"Decided from the per-seed tables in `{root}` (one per study and per presets' twin, with "
        "the command, commit and machine that produced it beside it); machines: "
        f"{'; '.join(machines) or '-'}. A claim whose studies have no kept evidence says "
        '"not run yet". X is a study\'s budget; bold, the verdict at X.\n\n'
        + headline_table(root, studies, further)
        + "\nEvery part of the claims run so far (tuned and with the presets):\n\n"
        + claims_table(root, studies, only_run=True)
    )


def write_doc(root: Path, doc: Path) -> str:
    """Replace the generated block of doc (between the GENERATED markers) with evidence_block."""
    from physgrad.errors import UserError

    text = doc.read_text()
    start, end = (text.find(marker) for marker in GENERATED)
    if start < 0 or end < start:
        raise UserError(f"{doc}: no generated block (the two markers {GENERATED[0][:40]}...)")
    block = evidence_block(root)
    text = text[: start + len(GENERATED[0])] + "\n\n" + block + "\n" + text[end:]
    doc.write_text(text)
    return block


def main(argv: list[str] | None = None) -> int:
    """Writes OUT_FOLDER/<profile>.md (claims.md, claims-long.md, claims-gpu.md) from STUDIES."""
    parser = argparse.ArgumentParser(
        prog="claims.py", description=__doc__.split("\n\n")[0].replace("\n", " ")
    )
    parser.add_argument(
        "studies", type=Path, help="the profile's study folders (outputs/experiments/claims)"
    )
    parser.add_argument("out", type=Path, nargs="?", help="where claims.md goes (default: STUDIES)")
    parser.add_argument(
        "--doc",
        type=Path,
        help="write the verdicts into this markdown file's generated block (docs/claims.md)",
    )
    parser.add_argument(
        "--keep",
        action="store_true",
        help="keep the finished studies' evidence tables in OUT (docs/evidence/claims) instead",
    )
    args = parser.parse_args(argv)
    from physgrad.errors import UserError

    if not args.studies.is_dir():  # before anything is written: a typo must not create folders
        print(
            f"claims: error: no study folder {args.studies}: give the profile's folder, "
            "e.g. outputs/experiments/claims",
            file=sys.stderr,
        )
        return 2
    # outputs/experiments/claims-long: that profile's
    profile = args.studies.name if args.studies.name in PROFILES else "claims"
    try:
        if args.keep:
            if args.out is None:
                print("claims: error: --keep needs OUT (docs/evidence/claims)", file=sys.stderr)
                return 2
            kept = keep_evidence(args.studies, args.out)
            print(f"kept {len(kept)} studies in {args.out}: {', '.join(kept) or 'none finished'}")
            return 0
        if args.doc is not None:
            print(write_doc(args.studies, args.doc))
            return 0
        print(write(args.studies, args.out or args.studies, profile=profile))
    except UserError as error:  # a study folder that is not what its tables say: one line
        print(f"claims: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
