"""Phase 1 of a study: compare.studies tuning studies, each of compare.trials trials per variant on
its own tuning seed, at the study's budget, over the variant's search space (log-uniform; Halton
points shifted by a random vector of the study's own, the same for every variant of a study, as
AlgoPerf's independent repeated studies; a search (an Optuna study) per variant and tuning study in
tuning.journal), each trial scored by its VALIDATION loss at the budget."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from physgrad.comparison.job_names import study_prefix, variant_index
from physgrad.comparison.jobs import Launcher, cadence, job_runs, job_yaml
from physgrad.comparison.journal import (
    journal_replay,
    journal_storage,
    set_aside_damage,
    set_aside_stale,
)
from physgrad.comparison.points import halton_points, is_whole, point_dimensions
from physgrad.comparison.spec import StudyPlan, StudySettings, Variant
from physgrad.comparison.tuned_in import tuned_in
from physgrad.errors import UserError
from physgrad.files import clean_text
from physgrad.readout import READOUT_VERSION, run_curve

if TYPE_CHECKING:
    pass


def trial_params(trial: object, space: dict) -> dict[str, float | int] | None:
    """A trial's params as data: exactly the variant's search keys, each a finite number inside its
    log-uniform range (a relative 1e-9 of slack for round-off), a whole number where the range is
    of whole numbers (points.is_whole); None for anything else. The journal
    lies in the study folder, which someone else may have written: a param named
    `learning_rate._target_` or a value `${oc.env:...}` would otherwise become a config node of a
    job that physgrad instantiates."""
    params = getattr(trial, "params", None)
    if not isinstance(params, dict) or set(params) != set(space):
        return None
    checked = {}
    for key, (low, high) in space.items():
        value = params[key]
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
            or not low * (1 - 1e-9) <= value <= high * (1 + 1e-9)
            or (is_whole((low, high)) and not float(value).is_integer())
        ):
            return None
        checked[key] = int(value) if is_whole((low, high)) else float(value)
    return checked


def _set_aside_line(variant: Variant, tuning_study: int, trial: object) -> str:
    """The one line that says a trial of the journal was set aside."""
    shown = repr(getattr(trial, "params", None))[:120]
    return (
        f"note: trial {getattr(trial, 'number', '?')} of {variant.name} (tuning study "
        f"{tuning_study}) in tuning.journal is set aside: its params {shown} are not "
        f"{sorted(variant.space)} inside their ranges (a journal changed by hand or by someone "
        "else)"
    )


def tuning(plan: StudyPlan, launcher: Launcher) -> list[dict[str, dict]]:
    """Phase 1: trials per variant (equal numbers) in each of the settings' tuning studies, scored
    by validation loss at the budget; returns per study the best settings per variant (its
    configured ones where every trial diverged or tuning is off)."""
    variants, settings, folder = plan.variants, plan.settings, launcher.folder
    common, groups, axis, budget = plan.common, plan.groups, plan.axis, plan.budget
    count = settings.study_count
    best = [{v.name: {} for v in variants} for _ in range(count)]
    if not settings.tune or settings.tuned_in is not None:  # untuned, or another study's best
        return tuned_in(Path(settings.tuned_in), variants, count) if settings.tune else best
    with journal_replay(folder / "tuning.journal"):
        searches, pending, reread = _open_searches(folder, variants, settings, launcher.say)
    if reread:
        told = _tell_trained(folder, variants, settings, searches, pending, axis, budget)
        launcher.say(f"tune: {told} trials read again from the runs that trained them")
    for variant in variants:
        variant.trials_together = trials_together(variant, axis)

    def job_values(tuning_study: int, variant: Variant) -> dict:
        values = {
            "seed": settings.tune_seed + tuning_study,
            "seeds": 1,
            "figures": False,  # the study's report/ draws every run
            "trainer.validation": True,
            **variant.job_values,
        }
        return {**values, **cadence(variant.config, axis, budget)}

    jobs, batches = {}, {}
    # one vectorised job per study and variant where the rule takes its tuned values as inputs
    for tuning_study in range(count):
        for index, variant in enumerate(variants):
            waiting = sorted(k for s, i, k in pending if (s, i) == (tuning_study, index))
            if variant.trials_together and waiting:
                values = {
                    "trial_values": {
                        key: [pending[tuning_study, index, k].params[key] for k in waiting]
                        for key in sorted(variant.space)
                    },
                    **job_values(tuning_study, variant),
                }
                jobs[batch_job(tuning_study, index, waiting)] = job_yaml(
                    [*common, *variant.overrides], groups, values
                )
                batches[tuning_study, index] = waiting
    # the others one job per trial, interleaved: trial k of every study and variant, then k + 1,
    # so that a study stopped early has tried every variant alike
    for k in range(settings.trials):
        for tuning_study in range(count):
            for index, variant in enumerate(variants):
                trial = pending.get((tuning_study, index, k))
                if trial is None or variant.trials_together:
                    continue
                values = {f"optim.{key}": value for key, value in trial.params.items()}
                values |= job_values(tuning_study, variant) | variant.priced(trial.params)
                jobs[trial_job(tuning_study, index, k)] = job_yaml(
                    [*common, *variant.overrides], groups, values
                )
    if jobs:
        launcher.run("tune", jobs, {name: variants[variant_index(name)].config for name in jobs})
        _score_trials(folder, variants, searches, pending, batches, axis, budget)
    for tuning_study in range(count):
        for variant in variants:
            trials = [
                t
                for t in searches[tuning_study, variant.name].trials
                if trial_params(t, variant.space) is not None
            ]
            if any(t.value is None for t in trials):
                raise UserError(
                    f"tuning of {variant.name} did not finish (see {folder / 'tune.log'}): run the "
                    "same command again to resume"
                )
            done = [
                t for t in trials if isinstance(t.value, (int, float)) and math.isfinite(t.value)
            ]
            if done:
                chosen = min(done, key=lambda t: t.value)
                best[tuning_study][variant.name] = trial_params(chosen, variant.space)
    return best


def trials_together(variant: Variant, axis: str) -> bool:
    """Whether a variant's trials of one study train in one vectorised job (trial_values): the
    budget in iterations or on the calibrated clock (members then stop together), a rule that
    takes its tuned values as inputs of its optax transformation (not Levenberg-Marquardt or
    K-FAC) and searches no line (capabilities.line_search), top-level keys, no whole-number key (a
    count such as SOAP's preconditioning frequency shapes the program) and no key that shapes the
    step's cost (each trial is charged its own: Variant.priced), no init_from."""
    from physgrad.optim import build_rule
    from physgrad.optim.capabilities import capabilities

    optim = variant.config.optim
    if (
        axis not in ("iteration", "calibrated_time")
        or capabilities(optim).line_search
        or not variant.space
        or any("." in key for key in variant.space)
        or any(is_whole(bounds) for bounds in variant.space.values())
        or variant.cost_knob
        or variant.config.get("init_from")
    ):
        return False
    try:
        build_rule(optim, {key: [low] for key, (low, _) in variant.space.items()})
    except UserError:
        return False
    return True


def seeds_together(variant: Variant, axis: str) -> bool:
    """Whether a variant's evaluation seeds train together in one vectorised job: with a budget in
    iterations or on the calibrated clock (axis "iteration" or "calibrated_time": every seed runs
    the same number of steps, whatever the machine's load), not on the measured clock (one job per
    seed, interleaved: load must hit every variant alike); not where init_from starts each from its
    own network, nor for a rule that searches a line (trained together, every seed would wait for
    the slowest one's evaluations at every step: capabilities.line_search)."""
    from physgrad.optim.capabilities import capabilities

    searches = capabilities(variant.config.optim).line_search
    return (
        axis in ("iteration", "calibrated_time")
        and not variant.config.get("init_from")
        and not searches
    )


def batch_job(tuning_study: int, index: int, numbers: list[int]) -> str:
    """The job name of trials `numbers` of variant index in tuning study `tuning_study` trained
    together: tune_v0_t000-015 (one trial: as its own job's name). Trials added to a finished study
    get a job of their own, so the files of those told before stay as they are."""
    last = f"-{numbers[-1]:03d}" if len(numbers) > 1 else ""
    return f"tune_{study_prefix(tuning_study)}v{index}_t{numbers[0]:03d}{last}"


def trial_job(tuning_study: int, index: int, trial: int) -> str:
    """The job name of trial k of variant index in tuning study `tuning_study`."""
    return f"tune_{study_prefix(tuning_study)}v{index}_t{trial:03d}"


def optuna_study_name(variant: Variant, tuning_study: int) -> str:
    """The Optuna study of a variant's tuning study k in tuning.journal (the first keeps the
    variant's name, as a folder written before repeated studies has it)."""
    return variant.name if tuning_study == 0 else f"{variant.name} (study {tuning_study})"


def _open_searches(
    folder: Path, variants: list[Variant], settings: StudySettings, say: Callable[[str], object]
) -> tuple[dict, dict, bool]:
    """Each variant's search per tuning study (an Optuna study in folder/tuning.journal), with its
    Halton points enqueued and asked for; (the searches by (tuning study, variant name), the trials
    not yet told by (tuning study, variant index, trial number), whether the journal was set aside
    to be read again)."""
    import optuna
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    set_aside_damage(folder / "tuning.journal", say)
    reread = set_aside_stale(folder / "tuning.journal", say)
    storage = journal_storage(folder / "tuning.journal")
    searches, pending = {}, {}
    dimensions = point_dimensions([variant.space for variant in variants])
    for tuning_study in range(settings.study_count):
        # the same points for every variant of one study (one seed per study): a variant's
        # position or name never changes where it is tried, so two names for one rule are tuned
        # alike; each study shifts the points anew, so the studies sample the tuning's variance
        for index, variant in enumerate(variants):
            search = optuna.create_study(
                study_name=optuna_study_name(variant, tuning_study),
                storage=storage,
                direction="minimize",
                load_if_exists=True,
            )
            if "readout" not in search.user_attrs:
                search.set_user_attr("readout", READOUT_VERSION)
            searches[tuning_study, variant.name] = search
            _refuse_unasked(folder, search, settings.trials)
            points = halton_points(
                variant.space, settings.trials, settings.tune_seed + tuning_study, dimensions
            )
            for point in points[len(search.trials) :]:
                search.enqueue_trial(point)
            while any(t.state == TrialState.WAITING for t in search.get_trials(deepcopy=False)):
                trial = search.ask()
                try:
                    for key, (low, high) in sorted(variant.space.items()):
                        if is_whole((low, high)):
                            trial.suggest_int(key, low, high, log=True)
                        else:
                            trial.suggest_float(key, low, high, log=True)
                except (ValueError, TypeError, OverflowError):
                    # a point enqueued in the journal by someone else that is no number of the
                    # range: failed in the journal, set aside below
                    search.tell(trial, state=TrialState.FAIL)
            for trial in search.get_trials(deepcopy=False):
                if trial_params(trial, variant.space) is None:
                    say(_set_aside_line(variant, tuning_study, trial))
                elif trial.state == TrialState.RUNNING:
                    pending[tuning_study, index, trial.number] = trial
    return searches, pending, reread


def _refuse_unasked(folder: Path, search: object, trials: int) -> None:
    """physgrad enqueues a search's first `trials` points and nothing more. A few trials beyond them
    still to be run (waiting or running) are asked and set aside like any trial whose params are not
    the study's; more of them than the study's own trials were put in the journal by someone else
    to make work (each is asked and answered: a journal padded with a thousand ran for minutes),
    and are a UserError (one line) before anything is asked."""
    from optuna.trial import TrialState

    unasked = sum(
        t.number >= trials and t.state in (TrialState.WAITING, TrialState.RUNNING)
        for t in search.get_trials(deepcopy=False)
    )
    if unasked > trials:
        raise UserError(
            f"{folder / 'tuning.journal'}: {unasked} trials of {clean_text(search.study_name, 80)} "
            f"to run beyond the {trials} the study asks (compare.trials): not physgrad's; move "
            "the file away to tune again, or give compare.trials as the study was run"
        )


def _tell_trained(
    folder: Path,
    variants: list[Variant],
    settings: StudySettings,
    searches: dict,
    pending: dict,
    axis: str,
    budget: float,
) -> int:
    """After the journal was set aside (set_aside_stale): each pending trial that a finished run of
    this tuning study and variant already trained (a member of any of its jobs in tune/ whose file
    holds the trial's values and tuning seed) is told from that run, without training it again; its
    job's name may differ from the one it would get now, where trials were added in pieces. Job
    folders that are links are not followed. Returns the number told."""
    import re

    tune = folder / "tune"
    if not pending or not tune.is_dir():
        return 0
    told = 0
    names = sorted(
        entry.name.removeprefix("+compare_job=")
        for entry in tune.iterdir()
        if entry.name.startswith("+compare_job=tune_") and not entry.is_symlink() and entry.is_dir()
    )
    for (tuning_study, index), keys in _by_study_variant(pending).items():
        pattern = re.compile(rf"tune_{study_prefix(tuning_study)}v{index}_t\d{{3}}(-\d{{3}})?")
        runs = [run for name in names if pattern.fullmatch(name) for run in job_runs(tune, name)]
        for k in keys:
            params = pending[tuning_study, index, k].params
            for run in runs:
                config = run.config if isinstance(run.config, dict) else {}
                optim = config.get("optim", {})
                if (
                    run.attrs.get("status") in ("completed", "diverged")
                    and config.get("seed") == settings.tune_seed + tuning_study
                    and isinstance(optim, dict)
                    and all(optim.get(key) == value for key, value in params.items())
                ):
                    value = run_curve(run, axis, "validation_loss").at(budget)
                    searches[tuning_study, variants[index].name].tell(
                        k, value if not math.isnan(value) else math.inf
                    )
                    del pending[tuning_study, index, k]
                    told += 1
                    break
    return told


def _by_study_variant(pending: dict) -> dict[tuple[int, int], list[int]]:
    """(tuning study, variant index, trial) keys grouped: (tuning study, variant index) -> trial
    numbers."""
    grouped: dict[tuple[int, int], list[int]] = {}
    for tuning_study, index, k in sorted(pending):
        grouped.setdefault((tuning_study, index), []).append(k)
    return grouped


def _score_trials(
    folder: Path,
    variants: list[Variant],
    searches: dict,
    pending: dict,
    batches: dict,
    axis: str,
    budget: float,
) -> None:
    """Each pending trial whose job ran to its end told its validation loss at the budget (a
    diverged one: infinity); one not run to its end stays pending (run again next time). batches:
    (tuning study, variant index) -> the trial numbers trained together, in the order of their
    members."""
    found = {}
    for (tuning_study, index), numbers in batches.items():
        members = job_runs(folder / "tune", batch_job(tuning_study, index, numbers))
        if len(members) != len(numbers):
            continue
        for k, run in zip(numbers, members):
            # a member's file says which values it ran: one left from other trials is not theirs
            optim = run.config.get("optim", {}) if isinstance(run.config, dict) else {}
            if all(
                optim.get(key) == value
                for key, value in pending[tuning_study, index, k].params.items()
            ):
                found[tuning_study, index, k] = run
    for tuning_study, index, k in pending:
        if (tuning_study, index) in batches:
            run = found.get((tuning_study, index, k))
        else:
            runs = job_runs(folder / "tune", trial_job(tuning_study, index, k))
            run = runs[0] if runs else None
        if run is None or run.attrs.get("status") in ("running", "interrupted", "crashed"):
            continue  # not run to its end: run again next time
        if run.attrs.get("status") == "refused":
            raise UserError(f"variant {variants[index].name} is refused: {run.attrs.get('reason')}")
        value = run_curve(run, axis, "validation_loss").at(budget)
        searches[tuning_study, variants[index].name].tell(
            k, value if not math.isnan(value) else math.inf
        )
