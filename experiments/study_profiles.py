"""The study profiles of `make reproduce-figures`: the claims (claims, claims-long, claims-gpu:
experiments/conf/studies.yaml) and the leaderboard (experiments/leaderboard_scenes.py), each a list
of `physgrad compare` studies run in parts of at most about 80 minutes (`--plan` lists them with
their expected time on the 2-core machine, `--part K` runs one), then their markdown.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

STUDY_PROFILES = ("claims", "claims-long", "claims-gpu", "claims-paper", "leaderboard")


# --- the claims profiles: physgrad compare studies
# ----------------------------------------------------------


def claims_parts(profile: str) -> list:
    from studies import PROFILES, chunks  # experiments/ is this script's folder

    if profile == "leaderboard":
        from leaderboard_scenes import leaderboard_parts

        return leaderboard_parts()
    return chunks(PROFILES[profile])


ON_2_CORES = "on a 2-core machine"
PLAN_MACHINE = {
    "claims-gpu": "on one GPU (Poisson's jobs cost their calibrated budget whatever the step "
    "costs; the Kuramoto-Sivashinsky jobs at one H200's update, 4.7 ms for ten networks)"
}


def print_claims_plan(profile: str, root: Path) -> None:
    """The studies of a claims profile part by part, with their jobs and expected time on the 2-core
    machine."""
    from studies import PART_SECONDS, starts

    total, longest = 0.0, 0.0
    for index, part in enumerate(claims_parts(profile), 1):
        seconds = sum(study.seconds() for study in part)
        total += seconds
        # a part resumes job by job, so a longer one still runs in boxes of a part's length
        longer = (
            f" (longer than a part: run it in boxes, `timeout -s INT {PART_SECONDS // 60:.0f}m` "
            "before the command, until it exits 0)"
        )
        print(
            f"part {index} (--part {index}): about {seconds / 60:.0f} min"
            + (longer if seconds > PART_SECONDS else "")
        )
        for start in starts(part):
            print(
                f"    start networks {start.name}: physgrad run -m {' '.join(start.overrides)} "
                "(one job per seed)"
            )
        for study in part:
            longest = max(longest, study.eval_seconds)
            print(f"    {study.label}: {_study_plan(study)}")
            for _, overrides in study_commands(study, root):
                print(f"        physgrad compare {' '.join(overrides)}")
    print(
        f"expected total: about {total / 3600:.1f} h {PLAN_MACHINE.get(profile, ON_2_CORES)}, in "
        "parts run one after another (each resumes where it stopped; finished jobs are skipped)"
        + (f"; its longest job about {longest / 60:.0f} min" if longest > PART_SECONDS else "")
    )


def study_commands(study, root: Path) -> Iterator[tuple[bool, list[str]]]:
    """The compares a part runs for a study, in order, as (presets' twin?, overrides): the study,
    then its presets' twin where it has one (the plan lists what the part runs). Each command is
    made as it is asked for, so that a twin made after its study ran runs on that study's clock
    (Study.clock) instead of calibrating one of its own."""
    return ((preset, study.command(root, preset)) for preset in (False, True)[: 1 + study.twin])


def _study_plan(study) -> str:
    """A study's jobs and expected time, as the plan lists them."""
    new = 1 if study.tuning_study else study.studies
    evaluation = f"{study.seeds} seeds ({new * study.eval_jobs()} evaluation jobs"
    if not study.tune:
        return (
            f"{study.variants()} variants, the presets untuned, {evaluation}), about "
            f"{study.seconds() / 60:.0f} min"
        )
    if any(o.startswith("compare.tuned_in=") for o in study.overrides):
        return (
            f"{study.variants()} variants, not tuned here (each at the settings another study "
            f"tuned: compare.tuned_in), {evaluation}), about {study.seconds() / 60:.0f} min"
        )
    return (
        f"{study.variants()} variants, {study.trials} trials each in "
        f"{new} tuning stud{'y' if new == 1 else 'ies'} (at most "
        f"{new * study.trials * study.variants()} tuning jobs: the trials of an optax rule train "
        f"together), {evaluation}"
        f"{f', {study.eval_jobs(preset=True)} untuned' if study.twin else ''}), about "
        f"{study.seconds() / 60:.0f} min (an estimate: one job per trial, a vectorised job at its "
        "members' summed budgets, which it can exceed)"
    )


def run_start(start, seeds: list[int], root: Path) -> int:
    """The networks a study continues from: one job per seed, in <root>/<name>/seed=S; those that
    finished before are skipped."""
    command = [
        sys.executable,
        "-m",
        "physgrad.cli",
        "run",
        "-m",
        *start.overrides,
        f"seed={','.join(str(s) for s in seeds)}",
        f"hydra.sweep.dir={root / start.name}",
        "hydra.sweep.subdir='seed=${seed}'",
    ]
    print("reproduce:", " ".join(command[2:]), flush=True)
    return run_child(command)


def run_child(command: list[str], env: dict | None = None) -> int:
    """A child's exit code; 130 after Ctrl-C, once the child (in this process group, so it has the
    signal too) has left its files as a resumable state (subprocess.run would kill it at once)."""
    child = subprocess.Popen(command, env=env)
    try:
        return child.wait()
    except KeyboardInterrupt:
        child.wait()
        return 130


INTERRUPTED = "reproduce: interrupted; the same command resumes where it stopped"


def study_environment(profile: str, study) -> dict | None:
    """The environment of a study's command: the leaderboard's scenes from examples/ import their
    modules from beside their conf/ folder; None (this one) otherwise."""
    if profile != "leaderboard":
        return None
    from leaderboard_scenes import environment

    return environment(study)


def run_claims(profile: str, parts: list[int], root: Path, out: Path, note: str) -> int:
    """The studies of the chosen parts (all: every part), each tuned and untuned; then claims.md
    from every study that has finished."""
    from claims import write
    from studies import EVIDENCE, starts

    failed = []
    all_parts = claims_parts(profile)
    # what is kept as evidence is not run again (the leaderboard keeps its own way)
    evidence = EVIDENCE.parent / profile if profile != "leaderboard" else None
    for index in parts or range(1, len(all_parts) + 1):
        part = all_parts[index - 1]
        # (label, twin?) of what is kept; a damaged table is a UserError (one line, below)
        kept = {
            (study.label, preset)
            for study in part
            for preset, _ in study_commands(study, root)
            if evidence is not None and study.kept(evidence, preset)
        }
        for label, preset in sorted(kept):
            name = f"{label.partition(' ')[0]}-preset" if preset else label
            print(f"reproduce: {name} is kept in {evidence}: skipped", flush=True)
        for start in starts(part):
            # each tuning study's evaluation and tuning seeds, the presets' twin's
            seeds = {
                seed
                for s in part
                if s.start == start
                for preset in (False, True)
                if (s.twin or not preset) and (s.label, preset) not in kept
                for seed in s.start_seeds(preset)
            }
            if not seeds:
                continue
            code = run_start(start, sorted(seeds), root)
            if code == 130:
                print(INTERRUPTED, file=sys.stderr)
                return 130
            if code != 0:
                failed.append(start.name)
        for study in part:
            for preset, overrides in study_commands(study, root):
                if (study.label, preset) in kept:
                    continue
                command = [sys.executable, "-m", "physgrad.cli", "compare", *overrides]
                print("reproduce:", " ".join(command[2:]), flush=True)
                code = run_child(command, env=study_environment(profile, study))
                if code == 130:
                    print(INTERRUPTED, file=sys.stderr)
                    return 130
                if code != 0:
                    failed.append(f"{study.name}{'-preset' if preset else ''} (exit {code})")
    from physgrad.errors import UserError

    try:
        if profile == "leaderboard":
            from leaderboard import write as write_leaderboard

            write_leaderboard(root, out)
        else:
            write(root, out, note, profile)
    except UserError as error:  # a study folder that is not what its tables say: one line
        print(f"reproduce: error: {error}", file=sys.stderr)
        return 2
    print(
        f"reproduce: wrote {out / (profile + '.md')}"
        + (f"; did not finish: {', '.join(failed)}" if failed else "")
    )
    return 1 if failed else 0


def study_profile(profile: str, part: str, plan: bool, out: Path, note: str) -> int:
    """A claims profile or the leaderboard: its plan, or the parts asked for (all: every part)."""
    root = Path("outputs/experiments") / profile
    count = len(claims_parts(profile))
    try:
        parts = [int(k) for k in part.split(",")] if part else []
    except ValueError:
        parts = [0]
    if any(not 1 <= k <= count for k in parts):
        print(
            f"reproduce: error: --part takes numbers from 1 to {count} (--plan lists the parts)",
            file=sys.stderr,
        )
        return 2
    if plan:
        print_claims_plan(profile, root)
        return 0
    from physgrad.errors import UserError

    try:
        return run_claims(profile, parts, root, out, note)
    except UserError as error:  # a damaged evidence table: one line
        print(f"reproduce: error: {error}", file=sys.stderr)
        return 2
