"""`physgrad compare --plan`: what a study will cost, estimated before anything trains from each
variant's compile time and step cost, measured here as `physgrad run` builds them (one seed, the
tuning seed)."""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass

# timing.compiled_step looked up when called: a test reads what it was asked to build there
import physgrad.timing as timing
from physgrad.comparison.coverage import coverage_lines, few_steps_lines, planned_points
from physgrad.comparison.jobs import _run_multirun, job_environment, job_yaml, multirun_command
from physgrad.comparison.spec import StudyPlan, Variant
from physgrad.comparison.tuning import seeds_together, trials_together
from physgrad.job_spec import checked
from physgrad.machine import load_average, machine_attributes, machine_label
from physgrad.power import POWER, detectable_ratio, seeds_for_ratio
from physgrad.readout import fmt
from physgrad.trainer_settings import EVALUATIONS_PER_BUDGET

MIN_STEPS = 8  # steps timed per variant, at least ...
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


@dataclass(frozen=True)
class Measured:
    """One variant's costs as `physgrad run` meets them, in seconds: compiling its step, one step,
    its first held-out evaluation (compiling it included), each later one, and building its scene,
    data and rule (each job builds its own)."""

    compile_seconds: float
    step_seconds: float
    first_evaluation_seconds: float
    evaluation_seconds: float
    build_seconds: float = 0.0


def use_job_cache() -> None:
    """JAX's persistent compilation cache of the study's jobs (jobs.job_environment) in this process
    too: a second plan reads what the first compiled, and a job what the plan compiled alike."""
    import jax

    env = job_environment()
    jax.config.update("jax_compilation_cache_dir", env["JAX_COMPILATION_CACHE_DIR"])
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs",
        float(env.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", 0)),
    )


def run_config(variant: Variant) -> object:
    """The variant's config as `physgrad run` gets it (without Hydra's own node)."""
    from omegaconf import open_dict

    cfg = variant.config.copy()
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


def measure(
    variant: Variant, seed: int, members: int = 1, trial_values: dict | None = None
) -> Measured:
    """The variant's costs per run on `members` seeds trained together (vectorised, as the study's
    jobs train them), from seed on, or on the trials trial_values holds (key -> one value per
    trial, all on seed, as a tuning job trains them: a step's cost may depend on the rate it
    trains at); the step's mean along its trajectory after one untimed step (the mean, not the
    median: a study pays every step, and a step's cost may depend on its state, e.g.
    Gauss-Newton's on the exponax Burgers scene took 0.03 s or 0.8 s along one trajectory), and
    its held-out evaluation on the test set, first (with its compile) and again; each divided by
    the runs trained together."""
    import jax

    cfg = run_config(variant)
    if trial_values:
        from omegaconf import open_dict

        with open_dict(cfg):
            cfg.trial_values = trial_values
        members = len(next(iter(trial_values.values())))
    begin = time.perf_counter()
    seeds = [seed] * members if trial_values else [seed + i for i in range(members)]
    _, _, _, stacked, compiled, compile_seconds, one_step = timing.compiled_step(cfg, seeds)
    build_seconds = max(0.0, time.perf_counter() - begin - compile_seconds)
    one_step()
    times, start = [], time.perf_counter()
    while len(times) < MIN_STEPS or (
        time.perf_counter() - start < STEP_SECONDS and len(times) < MAX_STEPS
    ):
        begin = time.perf_counter()
        one_step()
        times.append(time.perf_counter() - begin)
    evaluations = []
    for _ in range(2):
        begin = time.perf_counter()
        jax.block_until_ready(compiled.evaluate(compiled.params, stacked.test_sets))
        evaluations.append((time.perf_counter() - begin) / members)
    step = statistics.fmean(times) / members
    return Measured(compile_seconds, step, *evaluations, build_seconds)


def members(plan: StudyPlan, variant: Variant) -> tuple[int, dict | None]:
    """How a job of the variant trains its runs, as the plan times it: (1, the first tuning
    study's trial points, key by key) where its trials train in one vectorised job, as that job
    takes them; else (a study's seeds, None) where its seeds train in one, else (1, None)."""
    settings = plan.settings
    if settings.tune and trials_together(variant, plan.members_axis):
        points = planned_points(plan)[variant.name]  # the first tuning study's come first
        return 1, {key: points[key][: settings.trials] for key in sorted(points)}
    together = seeds_together(variant, plan.members_axis)
    return (settings.seeds if together else 1), None


def evaluations_per_run(variant: Variant, axis: str, budget: float, step_seconds: float) -> float:
    """The held-out evaluations of one run: at the start, every trainer.eval_every iterations, and
    with a time budget also every trainer.eval_seconds (budget / 20 unless set) of training."""
    settings = checked(run_config(variant)).trainer
    if axis == "iteration":
        return 1 + budget / settings.eval_every
    by_time = budget / (settings.eval_seconds or budget / EVALUATIONS_PER_BUDGET)
    return 1 + budget / max(step_seconds, 1e-9) / settings.eval_every + by_time


@dataclass(frozen=True)
class PhaseCosts:
    """What a phase of the study costs besides its jobs' building, compiling, training and held-out
    evaluations, in seconds, measured by running one as the study does: `start` before its first
    job (a fresh interpreter importing physgrad, the scene's modules and Hydra, composing the
    sweep) and the first job's extra time over a later one's (JAX's start in the process), once
    per phase; `job`, each job's own (Hydra's job folder and logging, the results file and its
    reading back)."""

    start: float
    job: float


def phase_costs(
    plan: StudyPlan, config_dir: str | None, measured: Measured, search_path: list[str]
) -> PhaseCosts:
    """Two jobs of the first variant (one and two iterations, the tuning seed, no figures) run as
    a phase of the study runs them: a multirun of `physgrad run` in a fresh process over job files
    as compare writes them, in a temporary folder removed after; the times read from the launch
    lines Hydra logs. `job` is the later job's time less what the plan measured of it (measured:
    building, compiling, two steps, two held-out evaluations); a phase that fails costs what an
    interpreter importing physgrad's runner does, once per job."""
    import re
    import shutil
    import tempfile
    from datetime import datetime
    from pathlib import Path

    first = plan.variants[0]
    values = {"seed": plan.settings.tune_seed, "figures": False, **first.job_values}
    values["trainer.time_budget"] = None
    jobs = {
        f"plan_{n}": job_yaml(
            [*plan.common, *first.overrides], plan.groups, {**values, "trainer.iterations": n}
        )
        for n in (1, 2)
    }
    folder = Path(tempfile.mkdtemp(prefix="physgrad-plan-"))
    try:
        (folder / "files" / "compare_job").mkdir(parents=True)
        for name, text in jobs.items():
            (folder / "files" / "compare_job" / f"{name}.yaml").write_text(text)
        command = multirun_command(folder / "files", folder, "plan", jobs, config_dir, search_path)
        begin = time.time()
        code = _run_multirun(command, folder / "plan.log", job_environment())
        end = time.time()
        log = (folder / "plan.log").read_text(errors="replace")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    launched = [
        datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f").timestamp()
        for stamp in re.findall(r"^\[([^\]]+)\]\[HYDRA\]\s+#\d+ : ", log, re.MULTILINE)
    ]
    if code != 0 or len(launched) != 2:
        return PhaseCosts(0.0, start_up_seconds())
    later = end - launched[1]
    own = (
        measured.build_seconds
        + measured.compile_seconds
        + 2 * measured.step_seconds
        + measured.first_evaluation_seconds
        + measured.evaluation_seconds
    )
    start = launched[0] - begin + max(0.0, launched[1] - launched[0] - later)
    return PhaseCosts(start, max(0.0, later - own))


def start_up_seconds() -> float:
    """What an interpreter importing physgrad's runner (its console script, JAX and Hydra) costs,
    measured once here."""
    import subprocess
    import sys

    begin = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", "import physgrad.experiment, physgrad.app"],
        capture_output=True,
        timeout=300,
    )
    return time.perf_counter() - begin


def phase_count(plan: StudyPlan, calibration: bool) -> int:
    """The multiruns a study launches: its tuning (if it tunes), its evaluation and its calibration
    (where it calibrates)."""
    return int(plan.settings.tune) + 1 + int(calibration)


def variant_cost(
    plan: StudyPlan, variant: Variant, measured: Measured, start_up: float = 0.0
) -> VariantCost:
    """The study's jobs of one variant, costed: each job's own cost (start_up), building its scene
    and data (measured.build_seconds), compiling once (a study's trials trained together: one
    job), training to the budget (iterations x step cost, or the time budget) and evaluating the
    test set as the runner does (evaluations_per_run); the evaluation of a budget in iterations or
    on the calibrated clock trains its seeds in one job (tuning.seeds_together), counted as seeds x
    the step and evaluation per run (measured: per run of a vectorised job where the runs train
    together, members)."""
    settings = plan.settings
    studies, seeds = settings.study_count, settings.seeds
    step_s = measured.step_seconds
    train = plan.budget * step_s if plan.axis == "iteration" else plan.budget
    count = evaluations_per_run(variant, plan.axis, plan.budget, step_s)
    held_out = measured.first_evaluation_seconds + (count - 1) * measured.evaluation_seconds
    per_job = start_up + measured.build_seconds + measured.compile_seconds
    tuning_runs = settings.trials * studies if settings.tune else 0

    # a study's trials of a variant in one vectorised job where the tuning trains them together
    together = tuning_runs and trials_together(variant, plan.members_axis)
    tuning_jobs = studies if together else tuning_runs
    together = seeds_together(variant, plan.members_axis)
    jobs = studies if together else studies * seeds
    evaluation = jobs * per_job + studies * seeds * (train + held_out)
    return VariantCost(
        variant.name,
        measured.compile_seconds,
        step_s,
        tuning_runs,
        tuning_jobs * per_job + tuning_runs * (train + held_out),
        jobs,
        evaluation,
    )


def say_progress(line: str) -> None:
    """A progress line on stderr, at once (quiet where PHYSGRAD_QUIET is set)."""
    import sys

    if not os.environ.get("PHYSGRAD_QUIET"):
        print(line, file=sys.stderr, flush=True)


def plan_text(
    plan: StudyPlan,
    composed_seconds: float = 0.0,
    config_dir: str | None = None,
    search_path: list[str] | None = None,
) -> str:
    """The estimate as text: a row per variant and the total, with the time the study spends
    composing and checking its variants before its phases (composed_seconds, as measured where the
    plan composed them) and the phases' own costs (phase_costs, run from config_dir with the
    study's hydra.searchpath, never its launcher: a plan runs here)."""
    use_job_cache()
    load_before = load_average()
    seed = plan.settings.tune_seed
    measured = []
    for index, variant in enumerate(plan.variants, 1):
        # the plan compiles and times each variant as its jobs would: minutes on a busy machine,
        # so it says what it is doing as it goes (stderr: the estimate stays the only stdout)
        say_progress(f"plan: compiling and timing {variant.name} ({index} of {len(plan.variants)})")
        measured.append(measure(variant, seed, *members(plan, variant)))
    say_progress("plan: timing a phase's start-up (two jobs of the first variant)")
    phase = phase_costs(plan, config_dir, measured[0], search_path or [])
    costs = [variant_cost(plan, v, m, phase.job) for v, m in zip(plan.variants, measured)]
    settings = plan.settings
    unit = "iterations" if plan.axis == "iteration" else "s of training"
    calibration = (
        plan.axis == "wall_time" and settings.clock == "calibrated" and not settings.calibration
    )
    extra = sum(c.compile_seconds for c in costs) + 10.0 if calibration else 0.0
    phases = phase_count(plan, calibration)
    load, cpu_count = max(load_before, load_average()), os.cpu_count() or 1
    # this plan's own measuring loads one core; more than that is someone else's work
    busy = (
        "other work was running: the study will take longer where it goes on"
        if load > cpu_count / 2 + 1
        else "quiet enough"
    )
    total = sum(c.seconds for c in costs) + extra + composed_seconds + phases * phase.start
    lines = [
        f"# Plan: {plan.variants[0].config.task.get('name')}, "
        f"{', '.join(v.name for v in plan.variants)}",
        "",
        f"Budget {plan.budget:g} {unit} per run; {settings.study_count} tuning "
        f"stud{'ies' if settings.study_count > 1 else 'y'} of "
        f"{settings.trials if settings.tune else 0} trials per variant; {settings.seeds} paired "
        "seeds per study.",
        "",
        *cost_table(costs),
    ]
    if plan.axis != "iteration":
        lines += few_steps_lines(
            {c.name: plan.budget / c.step_seconds for c in costs if c.step_seconds > 0},
            plan.budget,
        )
    lines += power_lines(plan)
    if settings.tune:  # the points are known before anything runs
        lines += coverage_lines(
            plan.variants, planned_points(plan), settings.trials, settings.study_count
        )
    lines += [
        "",
        f"Total: about {_duration(total)}"
        + (" (with the calibration of the step costs)" if calibration else "")
        + (
            f", composing and checking the variants ({composed_seconds:.0f} s, measured here) "
            "included"
            if composed_seconds
            else ""
        )
        + f". Each of its {phases} phases' start ({phase.start:.1f} s here: a fresh process, its "
        f"imports and its first job's start), each job's own ({phase.job:.1f} s), building its "
        "scene and data, compiling, training and the held-out evaluations, measured by running "
        "two jobs of the first variant as a phase runs them; writing the tables and figures adds "
        "to it, a study resumed skips what it finished, and JAX's compilation cache (in the "
        "user's physgrad cache, which this plan filled) makes later jobs compile faster. "
        f"Measured on {machine_label(machine_attributes())}, now, at a load average of "
        f"{load:.1f} on {cpu_count} cores ({busy}); nothing was kept.",
    ]
    return "\n".join(lines)


def cost_table(costs: list) -> list[str]:
    """The plan's table: a row per variant with its compile, step, phases and total."""
    lines = [
        "| variant | compile | step | tuning: runs, time | evaluation: jobs, time | total |",
        "|---|---|---|---|---|---|",
    ]
    for c in costs:
        lines.append(
            f"| {c.name} | {fmt(c.compile_seconds)} s | {fmt(c.step_seconds)} s | "
            f"{c.tuning_runs}, {_duration(c.tuning_seconds)} | {c.evaluation_jobs}, "
            f"{_duration(c.evaluation_seconds)} | {_duration(c.seconds)} |"
        )
    return lines


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
