"""Phase 2 of a study: each variant at its best trial's settings on compare.seeds paired seeds
(trained together in one vectorised step when the budget is in iterations; one job per seed,
variants interleaved, for time budgets)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from physgrad.comparison.jobs import Launcher, cadence, job_runs, job_yaml
from physgrad.comparison.spec import StudyPlan, StudySettings, Variant
from physgrad.errors import UserError
from physgrad.optim.capabilities import batches_over_seeds
from physgrad.readout import run_curve

if TYPE_CHECKING:
    from physgrad.readout import Curve
    from physgrad.results import Run


def evaluation_jobs(
    variants: list[Variant],
    best: dict[str, dict],
    settings: StudySettings,
    common: list[str],
    groups: set[str],
    axis: str,
    budget: float,
) -> dict[str, str]:
    """The evaluation's jobs in launch order: per variant one job of all seeds trained together when
    the budget is in iterations (one per seed where the rule's float64 retry does not batch or
    init_from starts each seed from its own network, e.g.
    init_from='start/seed=${seed}/results.h5'); for time budgets one job per seed, variants
    interleaved (A, B, C for the first seed, then the next), so that a drift in the machine's load
    does not line up with a variant."""
    seeds = settings.evaluation_seeds
    jobs = {}

    def spec(variant: Variant, seed: int, count: int) -> str:
        values = {f"optim.{k}": v for k, v in best[variant.name].items()}
        values.update(
            {
                "seed": seed,
                "seeds": count,
                **cadence(variant.config, axis, budget),
                **variant.job_values,
            }
        )
        return job_yaml([*common, *variant.overrides], groups, values)

    if axis == "iteration":
        for index, variant in enumerate(variants):
            # a float64 retry does not batch under vmap, and init_from starts one network per job
            if (
                not batches_over_seeds(variant.config.optim) or variant.config.get("init_from")
            ) and len(seeds) > 1:
                jobs.update({f"eval_v{index}_s{seed}": spec(variant, seed, 1) for seed in seeds})
            else:
                jobs[f"eval_v{index}"] = spec(variant, seeds[0], len(seeds))
    else:
        for seed in seeds:
            for index, variant in enumerate(variants):
                jobs[f"eval_v{index}_s{seed}"] = spec(variant, seed, 1)
    return jobs


def evaluation(
    plan: StudyPlan, best: dict[str, dict], launcher: Launcher
) -> tuple[dict[str, dict[int, Curve]], dict[str, dict[int, Run]]]:
    """Phase 2: every variant at its tuned settings on the paired evaluation seeds; (curves, runs)
    per variant and seed."""
    variants, folder, axis = plan.variants, launcher.folder, plan.axis
    jobs = evaluation_jobs(
        variants, best, plan.settings, plan.common, plan.groups, axis, plan.budget
    )
    launcher.run("eval", jobs)
    curves, statuses = {}, {}
    for index, variant in enumerate(variants):
        curves[variant.name], statuses[variant.name] = {}, {}
        for name in jobs:
            if name == f"eval_v{index}" or name.startswith(f"eval_v{index}_s"):
                for run in job_runs(folder / "eval", name):
                    if run.attrs.get("status") == "refused":
                        raise UserError(
                            f"variant {variant.name} is refused: {run.attrs.get('reason')}"
                        )
                    seed = run.attrs.get("seed")
                    if isinstance(seed, int):
                        curves[variant.name][seed] = run_curve(run, axis)
                        statuses[variant.name][seed] = run
    return curves, statuses
