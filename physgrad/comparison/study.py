"""`physgrad compare`: which variant trains this scene best, tuned with equal budgets, decided on
paired seeds.

    physgrad compare [-cd DIR] [--plan] task=<scene> optim=adam,gauss_newton,hig
    [trainer.time_budget=60] [compare.KEY=V]

--plan estimates the study's cost from each variant's measured compile time and step cost, and what
it can detect, and trains nothing.

Every comma list on the command line is an axis of variants (their product, as in a Hydra multirun);
every other override is common to all jobs. A study runs compare.studies independent tuning studies
in three phases, each a Hydra multirun of `physgrad run` (so `hydra/launcher=...` applies) into the
study folder, and resumes where it stopped when the same command runs again:
1. tuning: in each tuning study compare.trials trials per variant, on the study's tuning seed, at
   the study's budget, over the variant's search space (log-uniform; Halton points shifted by a
   random vector of the study's own, the same for every variant; an Optuna study per variant and
   study in tuning.journal); each trial is scored by its VALIDATION loss at the budget;
2. evaluation: each variant at its best trial's settings on compare.seeds paired seeds of the
   study's own (trained together in one vectorised step when the budget is in iterations or on
   the calibrated clock; one job per seed, variants interleaved, on the measured clock
   (compare.clock=measured), for a rule that searches a line and for networks continued with
   init_from);
3. the verdicts (physgrad.verdict) from the TEST loss, each holding where 3 of 4 studies (more
   than half) reach it with none against: compare.md, trials.csv, runs.csv, comparisons.csv,
   sensitivity.png and the sweep's report (figures of the curves) under report/ (figures=false:
   the tables without the figures).
docs/protocol.md gives the protocol and its reasons.
"""

from __future__ import annotations

import os
import signal
import sys
import time
import warnings
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from physgrad.comparison.calibration import calibrated_clock
from physgrad.comparison.evaluation import evaluation
from physgrad.comparison.figure import plot_sensitivity
from physgrad.comparison.job_names import tuning_study_of, variant_index
from physgrad.comparison.jobs import Launcher
from physgrad.comparison.spec import (
    SETTINGS,
    StudyPlan,
    StudySettings,
    budget_of,
    build_variants,
    check_variants_build,
    parse_arguments,
    split_overrides,
    study_settings,
)
from physgrad.comparison.study_folder import configuration_of, default_folder, record_study
from physgrad.comparison.summary import analyse, trial_rows
from physgrad.comparison.tuned_in import tuned_in
from physgrad.comparison.tuning import tuning
from physgrad.errors import UserError
from physgrad.interrupts import handling_signals, raise_interrupt
from physgrad.verdict import seeds_needed

if TYPE_CHECKING:
    from physgrad.results import Run


@dataclass
class Study:
    """What `physgrad compare` decided, as tables (pandas DataFrames), with the study folder."""

    folder: Path
    trials: object
    runs: object
    comparisons: object
    verdicts: list
    text: str


def run_study(
    overrides: list[str], config_dir: str | None = None, say: Callable[[str], object] = print
) -> Study:
    """The whole study (module docstring); resumes from its folder."""
    from physgrad.errors import FolderOwned
    from physgrad.files import own_folder
    from physgrad.gpus import local_launcher_args, pin_this_process

    gpus = pin_this_process()  # before this process starts jax (building the variants does)
    plan, hydra_args = compose_study(overrides, config_dir)
    hydra_args = local_launcher_args(hydra_args, gpus)
    variants, settings, common, groups, axis, budget = (
        plan.variants,
        plan.settings,
        plan.common,
        plan.groups,
        plan.axis,
        plan.budget,
    )
    first = variants[0].config
    _warn_if_undecidable(settings, len(variants), say)
    configuration = configuration_of([v.config for v in variants])
    folder = (
        Path(settings.dir)
        if settings.dir
        else default_folder(overrides, config_dir, str(first.task.get("name")), configuration)
    )
    try:
        folder.mkdir(parents=True, exist_ok=True)
        record_study(folder, overrides, config_dir, configuration)
    except OSError as error:  # a read-only disk, a full one, a folder of someone else's
        raise UserError(
            f"cannot write the study folder {folder} ({error.strerror or error}): give compare.dir "
            "a folder you can write"
        ) from None
    held = ExitStack()
    try:
        held.enter_context(own_folder(folder, "study"))
    except FolderOwned as error:
        raise UserError(str(error)) from None
    except OSError as error:  # the lock file is a link, a second name, a folder, or unwritable
        raise UserError(
            f"{folder}: the study's lock cannot be taken ({error.strerror or error}): remove "
            f"{folder / '.physgrad-study'} or give another compare.dir"
        ) from None
    with held:
        say(
            f"study {folder}: {len(variants)} variants "
            f"({', '.join(v.name for v in variants)}), budget "
            f"{budget:g} {'iterations' if axis == 'iteration' else 's'}; the same command "
            "resumes it"
        )
        if gpus > 1:
            say(f"{gpus} GPUs: each phase runs {gpus} jobs side by side, one per GPU")
        calibration = None
        if settings.tuned_in and not (Path(settings.tuned_in) / "trials.csv").is_file():
            # before the calibration: minutes that a missing study would waste
            tuned_in(Path(settings.tuned_in), variants, settings.study_count)
        launcher = Launcher(folder, config_dir, hydra_args, say)
        if axis == "wall_time" and settings.clock == "calibrated":
            calibration = calibrated_clock(plan, launcher, settings.calibration)
            axis = "calibrated_time"
        plan = StudyPlan(variants, settings, common, groups, axis, budget)
        best = tuning(plan, launcher)
        rows = trial_rows(folder, variants, settings.study_count)
        # figures=false, as for a run: the tables only (matplotlib's layout is most of a small
        # study's resume)
        figures = bool(first.get("figures", True))
        if rows and figures:
            plot_sensitivity(folder / "sensitivity", variants, rows, best)
        curves, statuses = evaluation(plan, best, launcher)
        runs, comparisons, trials, verdicts, text = analyse(
            folder, variants, best, curves, statuses, settings, axis, budget, rows, calibration
        )
        names = [v.name for v in variants]
        write_curves_report(folder, say, figures, settings.study_count, names)
    return Study(folder, trials, runs, comparisons, verdicts, text)


def compose_study(overrides: list[str], config_dir: str | None) -> tuple[StudyPlan, list[str]]:
    """The study a command line asks for, every variant composed and built once on the tuning seed
    (a variant the scene refuses is a UserError here, before anything trains); (plan, Hydra's own
    arguments). The plan's axis is the budget's (wall_time before calibration)."""
    settings_given, axes, common, hydra_args = split_overrides(overrides)
    settings = study_settings(settings_given)
    config_dirs = [config_dir] if config_dir else []
    if os.getcwd() not in sys.path:  # a scene or optimiser named by _target_, as for `physgrad run`
        sys.path.append(os.getcwd())
    variants = build_variants(axes, common, settings, config_dirs)
    check_variants_build(variants, settings.tune_seed)
    first = variants[0].config
    groups = set(first.hydra.runtime.choices.keys())
    axis, budget = budget_of(first)
    return StudyPlan(variants, settings, common, groups, axis, budget), hydra_args


def _warn_if_undecidable(settings: StudySettings, count: int, say: Callable[[str], object]) -> None:
    """A warning where the study's seeds are too few for any verdict among count variants."""
    comparisons = settings.comparisons(count)
    needed = seeds_needed(settings.alpha, comparisons)
    if settings.seeds < needed:
        say(
            f"warning: {settings.seeds} seeds cannot decide {comparisons} comparisons at alpha "
            f"{settings.alpha:g}: every verdict will be undecided (compare.seeds={needed} or more)"
        )


def tuning_study(run: Run) -> int:
    """The tuning study (1, 2, ...) whose evaluation job wrote the run, from its job folder's name;
    1 where the path names none."""
    found = (tuning_study_of(part) for part in reversed(Path(run.path).parts))
    return next((k for k in found if k is not None), 1)


def study_variant(run: Run, names: list[str]) -> str:
    """The study's name of the variant whose evaluation job wrote the run (its job folder's
    v<index>), or the file's own where the path names no evaluation job of the study."""
    for part in reversed(Path(run.path).parts):
        if tuning_study_of(part) is not None:
            index = variant_index(part.rpartition("=")[2])
            return names[index] if index < len(names) else run.variant
    return run.variant


def write_curves_report(
    folder: Path,
    say: Callable[[str], object],
    figures: bool = True,
    studies: int = 1,
    names: list[str] | None = None,
) -> None:
    """The sweep's report (its tables and, with figures, the evaluation curves) under
    folder/report, each group labelled with its tuning study where there are several, each run's
    variant named as the study names it (names: the variants in order); a failure is said, not
    raised."""
    try:
        from physgrad.files import make_folder
        from physgrad.report import write_report

        out = make_folder(folder / "report")  # a link planted there is refused, not written into
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            write_report(
                [folder / "eval"],
                out_dir=out,
                figures=figures,
                study_of=tuning_study if studies > 1 else None,
                variant_of=(lambda run: study_variant(run, names)) if names else None,
            )
    except (UserError, OSError, ValueError) as error:
        say(f"report of the curves not written: {error}")


def main(args: list[str]) -> int:
    if any(a in ("-h", "--help") for a in args):
        print(__doc__.strip())
        import textwrap

        print("\nSettings (compare.KEY=VALUE):")
        for key, (default, meaning) in SETTINGS.items():
            # wrapped by words at 100 columns, each setting's text in a column of its own
            print(
                textwrap.fill(
                    meaning if "(default" in meaning else f"{meaning} (default {default})",
                    width=100,
                    initial_indent=f"  compare.{key:<12}",
                    subsequent_indent=" " * 22,
                    break_on_hyphens=False,
                )
            )
        return 0
    overrides, config_dir, plan_only = parse_arguments(args)
    if plan_only:
        from physgrad.comparison.plan import plan_text

        begin = time.perf_counter()  # composing and checking: the study does them again, as here
        plan, hydra_args = compose_study(overrides, config_dir)
        search = [a for a in hydra_args if a.startswith("hydra.searchpath=")]
        print(plan_text(plan, time.perf_counter() - begin, config_dir, search))
        return 0

    # SIGTERM as Ctrl-C: the study's files are left as a resumable state
    try:
        with handling_signals(raise_interrupt, (signal.SIGTERM,)):
            study = run_study(overrides, config_dir)
    except KeyboardInterrupt:
        print(
            "physgrad compare: interrupted; run the same command again to resume", file=sys.stderr
        )
        return 130
    print(study.text)
    drawn = ", sensitivity.png" if (study.folder / "sensitivity.png").is_file() else ""
    # report/ only where this study wrote it (a link planted there is refused, not written into)
    report = study.folder / "report"
    reported = ", report/" if report.is_dir() and not report.is_symlink() else ""
    print(
        f"wrote {study.folder / 'compare.md'}, trials.csv, runs.csv, comparisons.csv{drawn}"
        f"{reported}"
    )
    return 0
