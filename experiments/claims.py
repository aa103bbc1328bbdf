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
import sys
from pathlib import Path

from claim_budget import (
    PageMemo,
    budget_text,
    busy_clock_text,
    failing_text,
    fixed_by_twin,
    main_study,
    measured_briefly,
    of_planned,
    part_study,
    presets_at_paper_budget,
    share,
    share_text,
    untrained_failures_open,
    variants_left_start,
)
from claim_list import CLAIMS, load_claims  # noqa: F401 - experiments/; load_claims: tests
from regime_map import regime_map
from scene_kinds import scene_kinds_block
from studies import GPU, MAP, PROFILES, STUDIES, Study, longer_not_run, where_it_runs
from study_runs import StudyRuns, keep_studies, read_study, study_protocol, uncommitted_note
from tuned_settings import tuned_table

from physgrad.claim import (  # noqa: F401 - Close and Lower: the parts' names, for callers
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
    studies_of,
    tuning_studies,
)
from physgrad.claim_parts import claim_verdict, decide_parts
from physgrad.claim_words import NOT_TESTED, claim_word, combined_causes
from physgrad.errors import UserError
from physgrad.files import clean_text, make_folder, read_own_file, replace_file
from physgrad.verdict import FRACTIONS

# --- reading a study
# --------------------------------------------------------------------------------------


def keep_evidence(root: Path, dest: Path) -> list[str]:
    """Every finished study of the claims under root, and its presets' twin, kept as evidence in
    dest with the columns the claims read of it (study_runs.keep_studies). Returns the studies
    kept."""
    columns: dict[str, set] = {}
    for claim in CLAIMS:
        for part in claim.parts:
            for name in studies_of(claim_of_part(part)):
                columns.setdefault(name, {"loss"}).add(getattr(part, "column", "loss"))
    for study in (s for studies in PROFILES.values() for s in studies if s.joins in columns):
        columns[study.name] = columns[study.joins]
    return keep_studies(root, dest, columns)


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
            cache[name] = runs = _twin_runs(root, name, suffix, specs.get(name))
            for joining in (s for s in specs.values() if s.joins == name and not suffix):
                more = _twin_runs(root, joining.name, suffix, joining)
                if isinstance(more, StudyRuns) and isinstance(runs, StudyRuns):
                    runs.join(more)
        return cache[name]

    rows = decide_parts(claim, study, fraction)
    presets = bool(suffix) or any(not s.tune for s in specs.values())
    if presets:  # presets that fix an axis run only the papers' value of it: say so
        fixed = {n: specs[n].preset for n in specs if isinstance(specs[n].preset, str)}
        rows = [
            (
                part,
                fixed_by_twin(
                    d, [fixed[n] for n in sorted(studies_of(claim_of_part(part))) if n in fixed]
                ),
            )
            for part, d in rows
        ]
    return claim_verdict(rows, twin=presets), rows


decide_claim = PageMemo(decide_claim)


def _twin_runs(root: Path, name: str, suffix: str, spec: Study | None) -> object:
    """The runs of study `name` (suffix "-preset": its presets' twin), or the Decision that says
    why there are none."""
    runs = read_study(root / (name + suffix))
    if runs is None:
        if suffix and spec is not None and spec.preset is False:
            return Decision(NOT_RUN, "-", f"{name} has no presets' twin (cut for time)")
        return Decision(OPEN, "-", f"{root / (name + suffix)} has no finished study")
    if spec is not None:  # evidence is data: a variant the study does not run is not its
        names = {v for study in (runs.tuning or (runs,)) for v in study.paths}
        known = spec.variant_names(preset=bool(suffix))
        if suffix and isinstance(spec.preset, str):  # also by the tuned study's names (below)
            key, _, value = spec.preset.partition("=")
            fixed = f"{key.rsplit('.', 1)[-1]}={value}"
            known += [f"{n} {fixed}" for n in known]
        unknown = sorted(names - set(known))
        if unknown:
            raise UserError(
                f"{root / (name + suffix)}: variant {clean_text(unknown[0], 60)!r} is none of the "
                f"study's ({clean_text(', '.join(known), 200)}): not this study's evidence"
            )
    if (suffix or (spec is not None and not spec.tune)) and isinstance(spec.preset, str):
        # the presets' study fixes one value of an axis (optim.clip=none): its variants are also
        # known by the tuned study's names, which carry that value ("backprop=C" is "backprop=C
        # clip=none")
        key, _, value = spec.preset.partition("=")
        runs.also_known_as(f"{key.rsplit('.', 1)[-1]}={value}")
    return runs


def claims_table(root: Path, studies=None, only_run: bool = False, further: tuple = ()) -> str:
    """One row per part of every claim whose studies are all among `studies` (default: every
    claim); with only_run, of the claims one of whose studies has finished; a part the presets'
    twin did not run gives the presets' verdict at the paper's budget where `further` ran it."""
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
        elsewhere = presets_at_paper_budget(claim, further, decide_claim)
        for i, ((part, d), (_, p)) in enumerate(zip(rows, preset_rows)):
            runs = read_study(root / getattr(part, "study", getattr(part, "hard", "")))
            budget = budget_text(runs) if runs else "-"
            head = (
                (
                    f"**{claim.name}**: tuned **{verdict}**, presets **{preset_verdict}**. "
                    f"{claim.paper}" + (f" ({claim.note})" if claim.note else "")
                )
                if i == 0
                else ""
            )
            there = elsewhere.get(part.text()) if p.verdict == NOT_RUN else None
            lines.append(
                f"| {head} | {part.text()} | {part_study(part)}, {budget} | {d.measured} | "
                f"{d.verdict} ({d.why}) | {p.measured} | {p.verdict} ({p.why})"
                f"{'; {1}: {0}{2}'.format(*there) if there else ''} |"
            )
    return "\n".join(lines) + "\n"


def claim_verdicts(
    claim: Claim, root: Path, suffix: str = "", profile: tuple = ()
) -> dict[float, str]:
    """The claim's verdict at each fraction of the budget (FRACTIONS: X/4, X/2, X)."""
    return {f: decide_claim(claim, root, suffix, f, profile)[0] for f in FRACTIONS}


def _verdicts_text(verdicts: dict[float, str]) -> list[str]:
    return [f"**{verdicts[f]}**" if f == 1.0 else verdicts[f] for f in FRACTIONS]


NOT_YET = "not run yet"
# the profiles of longer budgets a claim's headline row reads beside the claims profile's
FURTHER = ("claims-long", "claims-gpu", "claims-paper")


def headline_table(root: Path, profile: tuple, further: tuple = ()) -> str:
    """One row per claim: what its studies ran (trials per variant in each tuning study, tuning
    studies, paired seeds), the budget and its share of the paper's, the tuned verdict at X/4, X/2
    and X, the presets' at X, and, where a profile of longer budgets ran the claim (further:
    (folder, that profile's studies) pairs: claims-long, claims-gpu, claims-paper), its budget and
    verdicts at its X/4, X/2 and X, with what it ran. A claim that holds at one budget and does not
    at another says so first (apart, where one of the two is the GPU profile's: the machine changed
    too)."""
    header = [
        "| claim | verdict | trials x tuning studies, seeds | budget here | loss fell from the "
        "start | tuned at X/4 | X/2 | X | presets at X | longer budget: X/4, X/2, X |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines, names = list(header), {s.name for s in profile}
    for claim in sorted((c for c in CLAIMS if studies_of(c) <= names), key=lambda c: c.own):
        if claim.own and not any("own questions" in line for line in lines):
            lines += ["", "physgrad's own questions, not claims of the papers:", "", *header]
        main = main_study(claim)
        runs = read_study(root / main)
        longer, seen, elsewhere, at_paper = _longer_budgets(claim, main, further)
        longer_text = "; ".join(longer)
        if runs is None:  # a longer profile's verdicts stand on their own
            tail = f"{' |' * 8} {longer_text} |" if longer_text else f"{' |' * 8} |"
            lines.append(f"| {claim.name} | {NOT_YET}: {where_it_runs(studies_of(claim))}{tail}")
            continue
        trials, studies, seeds = study_protocol(root / main)
        tuned = claim_verdicts(claim, root, profile=profile)
        tuned = untrained_failures_open(claim, runs, tuned)
        preset, _ = decide_claim(claim, root, "-preset", 1.0, profile)
        if preset == OPEN and read_study(root / f"{main}-preset") is None:
            preset = NOT_YET  # the twin's study has not finished
        seen = [*tuned.values(), *seen]
        turned = (
            "**reverses with the budget**: "
            if HOLDS in seen and FAILS in seen
            else "**turns with a GPU's budget**: "
            if {HOLDS, FAILS} <= {*seen, *elsewhere}
            else ""
        )
        head = f"{turned}{claim.name}"
        trained, fell = variants_left_start(claim, runs)
        at_x = decide_claim(claim, root, "", 1.0, profile)[1]
        word, why = claim_word(
            tuned[1.0] == HOLDS,
            tuned[1.0] == FAILS,
            tuned[0.5] == FAILS,
            trained,
            share(claim, runs),
            claim.departs,
            combined_causes([d.cause for _, d in at_x]),
            failing_text(at_x, presets_at_paper_budget(claim, further, decide_claim)),
        )
        why += busy_clock_text(root, main)
        if at_paper:  # measured at the paper's budget too (a longer profile): said beside it
            if word == NOT_TESTED:
                word = f"{NOT_TESTED} with tuning"
            why += "; at the paper's budget: " + "; ".join(at_paper)
        lines.append(
            f"| {head} | **{word}** ({why}) | {trials} x {studies}{of_planned(runs)}, {seeds} | "
            f"{share_text(claim, runs)} | {fell} | "
            + " | ".join(_verdicts_text(tuned))
            + f" | {preset} | {longer_text or 'not in a longer profile'} |"
        )
    return "\n".join(lines) + "\n"


def _longer_budgets(claim: Claim, main: str, further: tuple) -> tuple[list, list, list, list]:
    """Per longer profile that ran the claim (further: (folder, studies) pairs), its budget, what
    it ran and its verdicts at X/4, X/2, X; the verdicts, the GPU profile's apart; and, of those
    at the paper's budget or beyond, their verdict at X with what they ran."""
    longer, seen, elsewhere, at_paper = [], [], [], []
    for folder, studies_there in further:
        if not studies_of(claim) <= {s.name for s in studies_there}:
            continue
        long_runs = read_study(folder / main)
        if long_runs is None:
            longer.append(longer_not_run(studies_of(claim), folder.name))
            continue
        found = claim_verdicts(claim, folder, profile=studies_there)
        (elsewhere if studies_there == GPU else seen).extend(found.values())
        t, k, n = study_protocol(folder / main)
        ran = f"{t} x {k}{of_planned(long_runs)}, {n}" if t else f"presets untuned, {n} seeds"
        parts = "; ".join(  # each part at its X: a claim's word hides which part decided it
            f"{part.text()}: {d.verdict}{measured_briefly(part, d)}"
            for part, d in decide_claim(claim, folder, "", 1.0, studies_there)[1]
        )
        verdicts = ", ".join(_verdicts_text(found))
        if share(claim, long_runs) >= 1.0:  # NaN (no paper budget) is not
            at_paper.append(f"{folder.name}, {budget_text(long_runs)} ({ran}): {found[1.0]}")
        longer.append(
            f"{folder.name}, {budget_text(long_runs)} ({ran}): {verdicts}; at its X: {parts}"
        )
    return longer, seen, elsewhere, at_paper


# --- the regime map
# ---------------------------------------------------------------------------------------


def write(root: Path, out: Path, note: str = "", profile: str = "claims") -> str:
    """<profile>.md (claims.md, claims-long.md) into out from the studies under root, with the
    regime map (payoff.png) where the profile has it; returns the markdown."""
    rule = __doc__.split("\n\n")[2]
    studies = PROFILES[profile]
    # the claims profile's headline also reads the profiles of longer budgets beside its folder
    further = (
        tuple((root.parent / name, PROFILES[name]) for name in FURTHER)
        if profile == "claims"
        else ()
    )
    with decide_claim.page():  # a page decides a claim at one budget once
        tables = headline_table(root, studies, further) + "\n" + claims_table(root, studies)
    make_folder(out)  # once the evidence is read: refused evidence leaves no folder behind
    text = (
        f"# The papers' claims, measured\n\n{note + chr(10) + chr(10) if note else ''}"
        + rule
        + "\n\n"
        f"Studies under {root}; each study's own table (variants, tuned settings, every pair, "
        "timing): `<study>/compare.md`. X is a study's budget; a verdict at X/4 or X/2 reads "
        "the same runs (tuned for X) earlier.\n\n"
        + tables
        + (regime_map(root, out, note) if set(MAP) <= set(studies) else "")
    )
    replace_file(out / f"{profile}.md", text.encode())  # the write door: no link followed
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
    with decide_claim.page():
        studies = PROFILES["claims"]
        # every longer profile, run or not: one not run yet says where it would run
        further = tuple((root.parent / name, PROFILES[name]) for name in FURTHER)
        machines = sorted(  # a study run on several machines records them joined by "; "
            {
                machine
                for s in studies
                for suffix in ("", "-preset")
                if (runs := read_study(root / f"{s.name}{suffix}")) is not None and runs.machine
                for machine in runs.machine.split("; ")
            }
        )
        return (
            f"Decided from the per-seed tables in `{root}` (one per study and per presets' twin, "
            "with the command, commit and machine that produced it beside it); machines: "
            f"{'; '.join(machines) or '-'}{uncommitted_note(root, *(f for f, _ in further))}. A "
            "claim without evidence says "
            '"not run yet" and where it runs. X is a study\'s budget; bold, the verdict at X.\n\n'
            + headline_table(root, studies, further)
            + scene_kinds_block(root)
            + "\nEvery part of the claims run so far (tuned and with the presets):\n\n"
            + claims_table(root, studies, only_run=True, further=further)
            + tuned_table(root)
        )


DOC_LIMIT = 1 << 22  # docs/claims.md is about 50 kB


def write_doc(root: Path, doc: Path) -> str:
    """Replace the generated block of doc (between the GENERATED markers) with evidence_block;
    UserError (one line) for a doc that is missing, not a plain file, too long or not text."""
    try:  # through the reading door: a link or a FIFO at doc is refused, not followed or waited on
        text = read_own_file(doc, DOC_LIMIT).decode()
    except (OSError, ValueError) as error:
        why = error.strerror if isinstance(error, OSError) and error.strerror else error
        raise UserError(f"--doc {doc}: cannot be read ({why}): give docs/claims.md") from None
    start, end = (text.find(marker) for marker in GENERATED)
    if start < 0 or end < start:
        raise UserError(f"{doc}: no generated block (the two markers {GENERATED[0][:40]}...)")
    block = evidence_block(root)
    text = text[: start + len(GENERATED[0])] + "\n\n" + block + "\n" + text[end:]
    replace_file(doc, text.encode())
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
    except OSError as error:  # a link planted at a folder the page goes into, a read-only disk
        print(f"claims: error: {clean_text(str(error), 300)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
