"""Phase 1 of a study: compare.trials trials per variant on the tuning seed, at the study's budget,
over its search space (log-uniform; scrambled Halton points, as AlgoPerf; an Optuna study per
variant in tuning.journal), each scored by its VALIDATION loss at the budget."""

from __future__ import annotations

import math
from pathlib import Path

from physgrad.comparison.jobs import Launcher, cadence, job_runs, job_yaml
from physgrad.comparison.spec import StudyPlan, StudySettings, Variant
from physgrad.errors import UserError
from physgrad.readout import run_curve


def halton_points(space: dict, count: int, seed: int) -> list[dict]:
    """count scrambled Halton points mapped log-uniformly onto the space (one dimension per key,
    sorted)."""
    from scipy.stats import qmc

    keys = sorted(space)
    unit = qmc.Halton(d=len(keys), scramble=True, seed=seed).random(count)
    return [
        {
            key: float(
                math.exp(
                    math.log(space[key][0])
                    + u * (math.log(space[key][1]) - math.log(space[key][0]))
                )
            )
            for key, u in zip(keys, row)
        }
        for row in unit
    ]


def tuning(plan: StudyPlan, launcher: Launcher) -> dict[str, dict]:
    """Phase 1: trials per variant (equal numbers), scored by validation loss at the budget; returns
    the best settings per variant (its configured ones where every trial diverged or tuning is
    off)."""
    variants, settings, folder = plan.variants, plan.settings, launcher.folder
    common, groups, axis, budget = plan.common, plan.groups, plan.axis, plan.budget
    best = {v.name: {} for v in variants}
    if not settings.tune:
        return best
    studies, pending = _open_studies(folder, variants, settings)
    jobs = {}
    for k in range(settings.trials):  # interleaved: trial k of every variant, then k + 1
        for index, variant in enumerate(variants):
            trial = pending.get((index, k))
            if trial is not None:
                values = {f"optim.{key}": value for key, value in trial.params.items()}
                values.update(
                    {
                        "seed": settings.tune_seed,
                        "seeds": 1,
                        "trainer.validation": True,
                        **variant.job_values,
                    }
                )
                values.update(cadence(variant.config, axis, budget))
                jobs[f"tune_v{index}_t{k:03d}"] = job_yaml(
                    [*common, *variant.overrides], groups, values
                )
    if jobs:
        launcher.run("tune", jobs)
        _score_trials(folder, variants, studies, pending, axis, budget)
    for variant in variants:
        done = [
            t
            for t in studies[variant.name].trials
            if t.value is not None and math.isfinite(t.value)
        ]
        if len(studies[variant.name].trials) and any(
            t.value is None for t in studies[variant.name].trials
        ):
            raise UserError(
                f"tuning of {variant.name} did not finish (see {folder / 'tune.log'}): run the "
                "same command again to resume"
            )
        if done:
            best[variant.name] = dict(min(done, key=lambda t: t.value).params)
    return best


def _open_studies(
    folder: Path, variants: list[Variant], settings: StudySettings
) -> tuple[dict, dict]:
    """Each variant's Optuna study in folder/tuning.journal, with its Halton points enqueued and
    asked for; (studies by variant name, the trials not yet told by (variant index, trial
    number))."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(folder / "tuning.journal"))
    )
    studies, pending = {}, {}
    for index, variant in enumerate(variants):
        study = optuna.create_study(
            study_name=variant.name, storage=storage, direction="minimize", load_if_exists=True
        )
        studies[variant.name] = study
        # the same scrambled points for every variant (one seed): a variant's position or name
        # never changes where it is tried, so two names for one rule are tuned alike
        points = halton_points(variant.space, settings.trials, settings.tune_seed)
        for point in points[len(study.trials) :]:
            study.enqueue_trial(point)
        from optuna.trial import TrialState

        while any(t.state == TrialState.WAITING for t in study.get_trials(deepcopy=False)):
            trial = study.ask()
            for key, (low, high) in sorted(variant.space.items()):
                trial.suggest_float(key, low, high, log=True)
        for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            pending[(index, trial.number)] = trial
    return studies, pending


def _score_trials(
    folder: Path, variants: list[Variant], studies: dict, pending: dict, axis: str, budget: float
) -> None:
    """Each pending trial whose job ran to its end told its validation loss at the budget (a
    diverged one: infinity); one not run to its end stays pending (run again next time)."""
    for index, k in pending:
        runs = job_runs(folder / "tune", f"tune_v{index}_t{k:03d}")
        if not runs or runs[0].attrs.get("status") in ("running", "interrupted", "crashed"):
            continue  # not run to its end: run again next time
        run = runs[0]
        if run.attrs.get("status") == "refused":
            raise UserError(f"variant {variants[index].name} is refused: {run.attrs.get('reason')}")
        value = run_curve(run, axis, "validation_loss").at(budget)
        studies[variants[index].name].tell(k, value if not math.isnan(value) else math.inf)
