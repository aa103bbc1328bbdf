"""Phase 2 of a study: each variant at each tuning study's best settings on compare.seeds paired
seeds, each study on its own block of seeds (StudySettings.study_seeds), so that the studies'
evaluations are independent (trained together in one vectorised step when the budget is in
iterations or on the calibrated clock; one job per seed, variants interleaved, on the measured
clock)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from physgrad.comparison.job_names import study_prefix, variant_index
from physgrad.comparison.jobs import Launcher, cadence, job_runs, job_yaml
from physgrad.comparison.spec import StudyPlan, StudySettings, Variant
from physgrad.comparison.tuning import seeds_together
from physgrad.errors import UserError
from physgrad.readout import run_curve

if TYPE_CHECKING:
    from physgrad.readout import Curve
    from physgrad.results import Run


def evaluation_jobs(
    variants: list[Variant],
    best: list[dict[str, dict]],
    settings: StudySettings,
    common: list[str],
    groups: set[str],
    axis: str,
    budget: float,
) -> dict[str, str]:
    """The evaluation's jobs in launch order, for each tuning study's best settings (best[k]): per
    variant one job of all seeds trained together when the budget is in iterations or on the
    calibrated clock (axis "iteration" or "calibrated_time": tuning.seeds_together; one per seed
    where init_from starts each seed from its own network, e.g.
    init_from='start/seed=${seed}/results.h5', and for a rule that searches a line); on the
    measured clock ("wall_time") one job per seed, variants and studies interleaved (A, B, C of
    each study for the first seed, then the next), so that a drift in the machine's load does not
    line up with a variant or a study."""
    jobs = {}

    def spec(study: int, variant: Variant, seed: int, count: int) -> str:
        values = {f"optim.{k}": v for k, v in best[study][variant.name].items()}
        values.update(
            {
                "seed": seed,
                "seeds": count,
                "figures": False,  # the study's report/ draws every run
                **cadence(variant.config, axis, budget),
                **variant.job_values,
                **variant.priced(best[study][variant.name]),
            }
        )
        return job_yaml([*common, *variant.overrides], groups, values)

    if axis in ("iteration", "calibrated_time"):
        for study in range(len(best)):
            seeds = settings.study_seeds(study)
            for index, variant in enumerate(variants):
                if not seeds_together(variant, axis) and len(seeds) > 1:
                    for seed in seeds:
                        jobs[evaluation_job(study, index, seed)] = spec(study, variant, seed, 1)
                else:
                    jobs[evaluation_job(study, index)] = spec(study, variant, seeds[0], len(seeds))
    else:
        for turn in range(settings.seeds):
            for study in range(len(best)):
                seed = settings.study_seeds(study)[turn]
                for index, variant in enumerate(variants):
                    jobs[evaluation_job(study, index, seed)] = spec(study, variant, seed, 1)
    return jobs


def evaluation_job(study: int, index: int, seed: int | None = None) -> str:
    """The job name of variant index's evaluation in tuning study `study`: all seeds, or one."""
    return f"eval_{study_prefix(study)}v{index}" + ("" if seed is None else f"_s{seed}")


def evaluation(
    plan: StudyPlan, best: list[dict[str, dict]], launcher: Launcher
) -> tuple[list[dict[str, dict[int, Curve]]], list[dict[str, dict[int, Run]]]]:
    """Phase 2: every variant at each tuning study's settings on the paired evaluation seeds;
    (curves, runs) per study, variant and seed. Only runs the jobs asked for count: each seed's
    file must hold that seed and the study's tuned values and have run to its end (completed or
    diverged); a job that was refused, failed, skipped or left another run's file is a UserError
    (one line, the first such job and how many), never a verdict from other runs."""
    variants, folder, axis = plan.variants, launcher.folder, plan.axis
    jobs = evaluation_jobs(
        variants, best, plan.settings, plan.common, plan.groups, plan.members_axis, plan.budget
    )
    launcher.run("eval", jobs, {name: variants[variant_index(name)].config for name in jobs})
    curves, statuses, problems = [], [], []
    for study in range(len(best)):
        curves.append({})
        statuses.append({})
        for index, variant in enumerate(variants):
            curves[study][variant.name], statuses[study][variant.name] = {}, {}
            whole = evaluation_job(study, index)
            for name in jobs:
                if name != whole and not name.startswith(whole + "_s"):
                    continue
                for run in job_runs(folder / "eval", name):
                    if run.attrs.get("status") == "refused":
                        raise UserError(
                            f"variant {variant.name} is refused: {run.attrs.get('reason')}"
                        )
                    why = _not_asked_for(
                        run, best[study][variant.name], plan.settings.study_seeds(study)
                    )
                    if why is not None:
                        problems.append(f"{name}: {why}")
                        continue
                    curves[study][variant.name][run.attrs["seed"]] = run_curve(run, axis)
                    statuses[study][variant.name][run.attrs["seed"]] = run
            missing = set(plan.settings.study_seeds(study)) - set(curves[study][variant.name])
            if missing and not any(p.startswith(whole) for p in problems):
                problems.append(f"{whole}: no results for seed {min(missing)}")
                planted = _planted_link(folder / "eval", jobs, whole, min(missing))
                if planted is not None:  # no run will write there: resuming cannot help
                    raise UserError(
                        f"the evaluation did not run as asked: {planted} is a link, not a "
                        "folder: physgrad writes through no link planted at a name it creates; "
                        "remove it and run the same command again"
                    )
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise UserError(
            f"the evaluation did not run as asked: {problems[0]}{more} (see "
            f"{folder / 'eval.log'}): run the same command again to resume"
        )
    return curves, statuses


def _planted_link(phase: Path, jobs: dict, whole: str, seed: int) -> Path | None:
    """The link planted at a folder an evaluation job of `whole` creates for `seed` (its job folder,
    its seed=S/, its .hydra/), where one is: such a job fails on every resume."""
    for name in (n for n in jobs if n == whole or n.startswith(whole + "_s")):
        job = phase / f"+compare_job={name}"
        for path in (job, job / f"seed={seed}", job / ".hydra"):
            if path.is_symlink():
                return path
    return None


def _not_asked_for(run: Run, tuned: dict, seeds: list[int]) -> str | None:
    """Why an evaluation run is not one its tuning study asked for (one of the study's seeds, its
    tuned values, run to its end with its rows whole), or None."""
    status = run.attrs.get("status")
    if status not in ("completed", "diverged"):
        reason = run.attrs.get("reason")
        return f"{status}" + (f" ({reason})" if reason else "")
    from physgrad.results import cut_short

    short = cut_short(run.attrs, run.final("train", "iteration"))
    if short is not None:
        return short
    seed = run.attrs.get("seed")
    if not isinstance(seed, int) or seed not in seeds:
        return f"seed {seed!r} is not one of the study's evaluation seeds {seeds[0]}..{seeds[-1]}"
    optim = run.config.get("optim", {}) if isinstance(run.config, dict) else {}
    for key, value in tuned.items():
        stored = optim
        for part in key.split("."):
            stored = stored.get(part) if isinstance(stored, dict) else None
        if stored != value:
            return f"its {key} is {stored!r}, not the tuned {value!r} (another run's file)"
    return None
