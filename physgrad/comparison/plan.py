"""`physgrad compare --plan`: what a study will cost, estimated before anything trains from each
variant's compile time and step cost, measured here as `physgrad run` builds them (one seed, the
tuning seed)."""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

from physgrad.comparison.coverage import coverage_lines, planned_points
from physgrad.comparison.spec import StudyPlan, Variant
from physgrad.readout import fmt

MIN_STEPS = 5  # steps timed per variant, at least ...
STEP_SECONDS = 1.0  # ... and for about this long, at most MAX_STEPS
MAX_STEPS = 200


@dataclass(frozen=True)
class VariantCost:
    """One variant's measured costs and the study's jobs of it, in seconds."""

    name: str
    compile_seconds: float
    step_seconds: float
    tuning_runs: int
    tuning_seconds: float
    evaluation_jobs: int
    evaluation_seconds: float

    @property
    def seconds(self) -> float:
        return self.tuning_seconds + self.evaluation_seconds


def measure(variant: Variant, seed: int) -> tuple[float, float]:
    """(compile seconds, median step seconds) of the variant's training step on one seed, after
    one untimed step."""
    from omegaconf import open_dict

    from physgrad.timing import compiled_step

    cfg = variant.config.copy()
    with open_dict(cfg):
        del cfg["hydra"]
    compile_seconds, one_step = compiled_step(cfg, [seed])[-2:]
    one_step()
    times, start = [], time.perf_counter()
    while len(times) < MIN_STEPS or (
        time.perf_counter() - start < STEP_SECONDS and len(times) < MAX_STEPS
    ):
        begin = time.perf_counter()
        one_step()
        times.append(time.perf_counter() - begin)
    return compile_seconds, statistics.median(times)


def variant_cost(plan: StudyPlan, variant: Variant, compile_s: float, step_s: float) -> VariantCost:
    """The study's jobs of one variant, costed: each run compiles once and trains to the budget
    (iterations x step cost, or the time budget); the evaluation of an iteration budget trains its
    seeds in one job, counted as seeds x the one-seed step (an upper bound where vmap makes seeds
    cheaper)."""
    settings = plan.settings
    studies, seeds = settings.study_count, settings.seeds
    train = plan.budget * step_s if plan.axis == "iteration" else plan.budget
    tuning_runs = settings.trials * studies if settings.tune else 0
    together = plan.axis == "iteration" and not variant.config.get("init_from")
    jobs = studies if together else studies * seeds
    evaluation = jobs * compile_s + studies * seeds * train
    return VariantCost(
        variant.name,
        compile_s,
        step_s,
        tuning_runs,
        tuning_runs * (compile_s + train),
        jobs,
        evaluation,
    )


def plan_text(plan: StudyPlan) -> str:
    """The estimate as text: a row per variant and the total."""
    from physgrad.machine import machine_attributes, machine_label

    costs = []
    for variant in plan.variants:
        compile_s, step_s = measure(variant, plan.settings.tune_seed)
        costs.append(variant_cost(plan, variant, compile_s, step_s))
    settings = plan.settings
    unit = "iterations" if plan.axis == "iteration" else "s of training"
    calibration = (
        plan.axis == "wall_time" and settings.clock == "calibrated" and not settings.calibration
    )
    extra = sum(c.compile_seconds for c in costs) + 10.0 if calibration else 0.0
    total = sum(c.seconds for c in costs) + extra
    lines = [
        f"# Plan: {plan.variants[0].config.task.get('name')}, "
        f"{', '.join(v.name for v in plan.variants)}",
        "",
        f"Budget {plan.budget:g} {unit} per run; {settings.study_count} tuning "
        f"stud{'ies' if settings.study_count > 1 else 'y'} of "
        f"{settings.trials if settings.tune else 0} trials per variant; {settings.seeds} paired "
        "seeds per study.",
        "",
        "| variant | compile | step | tuning: runs, time | evaluation: jobs, time | total |",
        "|---|---|---|---|---|---|",
    ]
    for c in costs:
        lines.append(
            f"| {c.name} | {fmt(c.compile_seconds)} s | {fmt(c.step_seconds)} s | "
            f"{c.tuning_runs}, {_duration(c.tuning_seconds)} | {c.evaluation_jobs}, "
            f"{_duration(c.evaluation_seconds)} | {_duration(c.seconds)} |"
        )
    lines += power_lines(plan)
    if settings.tune:  # the points are known before anything runs
        lines += coverage_lines(plan.variants, planned_points(plan), settings.trials)
    lines += [
        "",
        f"Total: about {_duration(total)}"
        + (" (with the calibration of the step costs)" if calibration else "")
        + ". Compiling and training only: start-up, the held-out evaluations and writing files add "
        "to it, a study resumed skips what it finished, and JAX's compilation cache (in the user's "
        "physgrad cache) can make later jobs compile faster. Measured on "
        f"{machine_label(machine_attributes())}, one seed, now; nothing was trained or written.",
    ]
    return "\n".join(lines)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


NOISES = (0.1, 0.3, 1.0)  # spreads of the per-seed log loss ratio the plan shows


def power_lines(plan: StudyPlan) -> list[str]:
    """What the design can detect with verdict.POWER, before anything runs: for a few spreads of
    the per-seed log ratio (the run noise, unknown until the study has run), the smallest
    detectable ratio at these settings and the seeds per study that 1.5x and 2x would need."""
    from physgrad.verdict import POWER, detectable_ratio, seeds_for_ratio

    settings = plan.settings
    count = len(plan.variants)
    comparisons = settings.comparisons(count)
    rule = {"margin": settings.margin, "alpha": settings.alpha}
    lines = [
        "",
        f"Power ({100 * POWER:.0f}%, {comparisons} comparison{'s' if comparisons > 1 else ''}, "
        f"{settings.study_count} tuning stud{'ies' if settings.study_count > 1 else 'y'}; "
        'docs/protocol.md, "Power"): the spread of the per-seed log loss ratio is known only '
        "once the study has run (its verdict table says what it could detect), so here for three:",
        "",
        "| spread of log ratio | detectable ratio | seeds per study for 1.5x | for 2x |",
        "|---|---|---|---|",
    ]
    for sd in NOISES:
        ratio = detectable_ratio(sd, settings.seeds, comparisons, settings.study_count, **rule)
        needs = [
            seeds_for_ratio(r, sd, comparisons, settings.study_count, **rule) or "-"
            for r in (1.5, 2.0)
        ]
        lines.append(
            f"| {sd:g} | {fmt(ratio) + 'x' if ratio < float('inf') else 'none'} | "
            f"{needs[0]} | {needs[1]} |"
        )
    return lines
