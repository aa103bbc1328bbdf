"""Phase 3 of a study: the verdicts (physgrad.verdict) from the TEST loss, and what they are written
to: compare.md, trials.csv, runs.csv and comparisons.csv."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from physgrad.comparison.calibration import cost_spread
from physgrad.comparison.clock_text import busy_calibration, timing_lines
from physgrad.comparison.coverage import (
    coverage_lines,
    edge_lines,
    few_steps_lines,
    same_point_line,
    tried_values,
)
from physgrad.comparison.spec import StudySettings, Variant
from physgrad.files import replaced
from physgrad.power import POWER, detectable_ratio, measured
from physgrad.readout import fmt, run_record, target_loss
from physgrad.replication import across_studies, majority
from physgrad.verdict import (
    FRACTIONS,
    compare_variants,
    divergence_flag,
    divergence_test,
    ratio_of,
    seeds_for_one_against,
)

if TYPE_CHECKING:
    import pandas as pd

    from physgrad.readout import Curve
    from physgrad.results import Run
    from physgrad.verdict import Paired, PairVerdict


def _ratio_text(p: Paired) -> str:
    return f"{fmt(p.ratio)} [{fmt(ratio_of(p.low))}, {fmt(ratio_of(p.high))}]"


def analyse(
    folder: Path,
    variants: list[Variant],
    best: list[dict[str, dict]],
    curves: list[dict[str, dict[int, Curve]]],
    statuses: list[dict[str, dict[int, Run]]],
    settings: StudySettings,
    axis: str,
    budget: float,
    trials_rows: list[dict],
    calibration: dict | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame, list[PairVerdict], str]:
    """The verdicts and tables of the evaluation runs of every tuning study (best, curves and
    statuses: one entry per study), written to folder (trials.csv, runs.csv, comparisons.csv,
    compare.md); returns (runs, comparisons, trials, verdicts over the studies, compare.md's
    text)."""
    import pandas as pd

    spread = (
        cost_spread(calibration, [v.name for v in variants])
        if axis == "calibrated_time" and calibration
        else None
    )
    per_study = [
        compare_variants(
            by_variant,
            budget,
            pairs=settings.pairs([v.name for v in variants]),
            margin=settings.margin,
            alpha=settings.alpha,
            cost_spread=spread,
        )
        for by_variant in curves
    ]
    verdicts = across_studies(per_study)
    # the target: the lowest median over every study's runs of a variant
    pooled = {
        v.name: {(k, seed): c for k, runs in enumerate(curves) for seed, c in runs[v.name].items()}
        for v in variants
    }
    target_variant, target = target_loss(pooled, budget)
    runs = pd.DataFrame(
        [
            row
            for k in range(len(curves))
            for row in run_rows(variants, curves[k], statuses[k], axis, budget, target, k)
        ]
    )
    comparisons = pd.DataFrame(comparison_rows(verdicts, budget, per_study, settings))
    trials = pd.DataFrame(trials_rows)
    # written beside and renamed: a link planted at a table's name is replaced, not written through
    for name, table in (("trials", trials), ("runs", runs), ("comparisons", comparisons)):
        with replaced(folder / f"{name}.csv", text=True) as f:
            table.to_csv(f, index=False)

    lines = verdict_lines(variants, runs, verdicts, settings, axis, budget, calibration)
    if axis != "iteration" and len(runs):  # a verdict from a handful of a rule's steps
        lines += few_steps_lines(runs.groupby("variant")["iterations"].median().to_dict(), budget)
    searched = (
        coverage_lines(variants, tried_values(trials_rows), settings.trials, settings.study_count)
        + same_point_line(variants, best)
        if settings.tune
        else []
    )
    lines += variant_lines(variants, runs, best, target_variant, target, searched, trials_rows)
    lines += timing_lines(variants, runs, axis, calibration)
    text = "\n".join(lines) + "\n"
    with replaced(folder / "compare.md", text=True) as f:
        f.write(text)
    return runs, comparisons, trials, verdicts, text


def run_rows(
    variants: list[Variant],
    curves: dict[str, dict[int, Curve]],
    statuses: dict[str, dict[int, Run]],
    axis: str,
    budget: float,
    target: float,
    study: int = 0,
) -> list[dict]:
    """runs.csv: one row per evaluation run (of tuning study `study`): the study's variant and the
    run's record at the study's budget (readout.run_record)."""
    return [
        {
            **run_record(statuses[variant.name][seed], target, axis, budget),
            "variant": variant.name,
            "study": study,
        }
        for variant in variants
        for seed in sorted(curves[variant.name])
    ]


def comparison_rows(
    verdicts: list[PairVerdict],
    budget: float,
    per_study: list[list[PairVerdict]] | None = None,
    settings: StudySettings | None = None,
) -> list[dict]:
    """comparisons.csv: every pair at every fraction of the budget; with repeated tuning studies the
    verdicts over all studies (study "all") and then each study's own; with the settings, the
    ratio the design could detect (over all studies: detectable)."""
    per_study = per_study or [verdicts]
    labelled = [(0, verdicts)] if len(per_study) == 1 else [("all", verdicts)]
    if len(per_study) > 1:
        labelled += list(enumerate(per_study))
    rows = []
    for study, v in ((study, v) for study, vs in labelled for v in vs):
        # the ratio the whole design could detect: on the rows over all studies
        overall = settings is not None and (study == "all" or len(per_study) == 1)
        for fraction in FRACTIONS:
            p = v.at[fraction]
            rows.append(
                {
                    "study": study,
                    "a": v.a,
                    "b": v.b,
                    "fraction": fraction,
                    "budget": budget * fraction,
                    "pairs": p.pairs,
                    "a_lower_in": p.wins_a,
                    "missing": p.missing,
                    "both_diverged": p.both_diverged,
                    "median_ratio": p.ratio,
                    "ci_low": ratio_of(p.low),
                    "ci_high": ratio_of(p.high),
                    "p_difference_holm": v.p_difference[fraction],
                    "p_equivalent_holm": v.p_equivalent[fraction],
                    "diverged_a": p.diverged_a,
                    "diverged_b": p.diverged_b,
                    "p_divergence_fisher": divergence_test(
                        p.diverged_a, p.seeds, p.diverged_b, p.seeds
                    ),
                    "detectable_ratio": detectable(v, settings, len(verdicts), fraction)
                    if overall
                    else math.nan,
                    "verdict": v.verdicts[fraction][0],
                    "why": v.verdicts[fraction][1],
                }
            )
    return rows


def verdict_lines(
    variants: list[Variant],
    runs: pd.DataFrame,
    verdicts: list[PairVerdict],
    settings: StudySettings,
    axis: str,
    budget: float,
    calibration: dict | None = None,
) -> list[str]:
    """compare.md's title, the study's budget and rule, and its verdicts table; a verdict that reads
    a clock the machine's load may have moved (a contended run on the measured clock, a calibration
    on a busy machine) says so in its cell."""
    scheduled = (
        ", a scheduled update at its expected cost"
        if calibration and any("update_seconds" in calibration["costs"][v.name] for v in variants)
        else ""
    )
    budget_text = {
        "wall_time": f"{budget:g} s of training (measured clock)",
        "calibrated_time": f"{budget:g} s of training on the calibrated clock (iterations x the "
        f"variant's calibrated step cost{scheduled}; the measured seconds are in runs.csv)",
    }.get(axis, f"{budget:g} iterations")
    contended = {
        v.name: int(runs[runs.variant == v.name]["contended"].sum()) if len(runs) else 0
        for v in variants
    }
    lines = [
        f"# Which gradient: {variants[0].config.task.get('name')}, "
        f"{', '.join(v.name for v in variants)}",
        "",
        f"Budget: {budget_text} per run. {_tuning_text(settings)}{_batching_text(variants)} "
        f"Evaluation: {_seeds_text(settings)}, paired (same data and initial network), "
        f"verdicts on the test loss. Rule: docs/protocol.md (margin {settings.margin:g}, alpha "
        f"{settings.alpha:g}, Holm over {len(verdicts)} "
        f"comparison{'s' if len(verdicts) > 1 else ''}"
        f"{_studies_rule(settings)}).",
        "",
        "## Verdicts",
        "",
        f"| A vs B | verdict at the budget | median A/B [95% interval]"
        f"{', per tuning study' if settings.study_count > 1 else ''} | A lower in | detectable "
        "| verdict at 1/4, 1/2 | stable | trend 1/2 -> 1 | diverged A, B | contended runs A, B |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    busy = busy_calibration(calibration) if axis == "calibrated_time" and calibration else ""
    for v in verdicts:
        p = v.at[1.0]
        flag = (
            " (timing contended)"
            if axis == "wall_time" and (contended[v.a] or contended[v.b])
            else ""
        )
        if busy:
            flag += f" (clock calibrated on a busy machine: {busy})"
        diverging = divergence_flag(p, v.a, v.b, settings.alpha)
        if diverging:
            flag += f" ({diverging})"
        if v.reversed:
            flag += f" (reversed: {v.verdicts[0.25][0]}, {v.verdicts[0.5][0]} at 1/4, 1/2)"
        lines.append(
            f"| {v.a} vs {v.b} | **{v.verdict}**{flag} ({v.verdicts[1.0][1]}) | "
            f"{'; '.join(_ratio_text(s.at[1.0]) for s in v.studies) or _ratio_text(p)} | "
            f"{p.wins_a} of {p.pairs}{f' ({p.missing} missing)' if p.missing else ''}"
            f"{f' ({p.both_diverged} both diverged)' if p.both_diverged else ''} | "
            f"{_detectable_text(detectable(v, settings, len(verdicts)), settings.margin)} | "
            f"{v.verdicts[0.25][0]}, {v.verdicts[0.5][0]} | {'yes' if v.stable else 'no'} | "
            f"{v.trend} | {p.diverged_a}, {p.diverged_b} | {contended[v.a]}, {contended[v.b]} |"
        )
    lines += [
        "",
        f"Detectable: the smallest loss ratio this design finds with {100 * POWER:.0f}% power, "
        "from what its studies measured: the spread of the seeds' log ratios, the spread between "
        'the tuning studies and the divergence rate (docs/protocol.md, "Power"): an undecided '
        "verdict with a detectable ratio of 3 says little; one of 1.2 says any difference is "
        "small.",
    ]
    return lines + unanimity_lines(settings.seeds, settings.alpha, len(verdicts))


def detectable(
    verdict: PairVerdict, settings: StudySettings, comparisons: int, fraction: float = 1.0
) -> float:
    """The smallest ratio a pair's study could detect with POWER (physgrad.power.detectable_ratio),
    from what its tuning studies measured at the budget (or the fraction of it): the seeds' spread,
    the spread between the studies and the divergence rate (physgrad.power.measured)."""
    sd, between, divergence, other = measured(verdict, fraction)
    if math.isnan(sd):
        return math.nan
    return detectable_ratio(
        sd,
        settings.seeds,
        comparisons,
        settings.study_count,
        margin=settings.margin,
        alpha=settings.alpha,
        divergence=divergence,
        between=between,
        divergence_other=other,
    )


def _detectable_text(ratio: float, margin: float = 1.1) -> str:
    if math.isnan(ratio):
        return "-"
    if math.isinf(ratio):
        return "none (too few seeds, or too many divergences)"
    if ratio <= margin:
        return f"any above {fmt(margin)}x (no spread)"
    return f"{fmt(ratio)}x"


def _seeds_text(settings: StudySettings) -> str:
    """The evaluation seeds: one block, or each tuning study's own."""
    blocks = [settings.study_seeds(k) for k in range(settings.study_count)]
    if len(blocks) == 1:
        return f"seeds {blocks[0][0]}..{blocks[0][-1]}"
    return (
        "each tuning study on its own seeds (" + ", ".join(f"{b[0]}..{b[-1]}" for b in blocks) + ")"
    )


def _tuning_text(settings: StudySettings) -> str:
    if not settings.tune:
        return "Not tuned: every variant at its configured settings."
    if settings.study_count == 1:
        return (
            f"Tuning: {settings.trials} trials per variant on seed {settings.tune_seed}, the same "
            "points for every variant, scored by the validation loss at the budget."
        )
    last = settings.tune_seed + settings.study_count - 1
    return (
        f"Tuning: {settings.study_count} independent tuning studies of {settings.trials} trials "
        f"per variant (seeds {settings.tune_seed}..{last}, each study its own trial points, "
        "interleaved with the others' and the same for every variant), scored by the validation "
        "loss at the budget; each study's best is evaluated on the study's own seeds."
    )


def _batching_text(variants: list[Variant]) -> str:
    """Which variants trained their trials together in one vectorised job per study, and which one
    job per trial (a rule whose tuned values cannot be inputs, a float64 retry, a measured
    clock)."""
    together = [v.name for v in variants if v.trials_together]
    alone = [v.name for v in variants if not v.trials_together]
    if not any(v.space for v in variants):
        return ""
    if not together:
        return " Trials: one job each."
    text = f" Trials trained together, one vectorised job per study: {', '.join(together)}"
    return text + (f"; one job per trial: {', '.join(alone)}." if alone else ".")


def _studies_rule(settings: StudySettings) -> str:
    if settings.study_count == 1:
        return ""
    return (
        f"; a verdict must hold in {majority(settings.study_count)} of the "
        f"{settings.study_count} tuning studies with none against it, and a better with every "
        "study's median ratio on its side and the studies, taken as one draw each, excluding a "
        "ratio of 1; the table gives each study's median ratio and interval in turn"
    )


def unanimity_lines(seeds: int, alpha: float, comparisons: int) -> list[str]:
    """Where the seeds are too few for a verdict of "better" with any seed on the other side, a
    sentence that says so and which seed count would allow one."""
    enough = seeds_for_one_against(alpha, comparisons)
    if seeds >= enough or comparisons < 1:
        return []
    return [
        "",
        f"With {seeds} seeds and {comparisons} comparison{'s' if comparisons > 1 else ''} at alpha "
        f'{alpha:g}, "better" needs every seed on one side: one seed against leaves p above '
        f"alpha after Holm's correction. compare.seeds={enough} would allow one against.",
    ]


def variant_lines(
    variants: list[Variant],
    runs: pd.DataFrame,
    best: list[dict[str, dict]],
    target_variant: str,
    target: float,
    searched: Sequence[str] = (),
    trials: Sequence[Mapping] = (),
) -> list[str]:
    """compare.md's variants table (tuned settings, one value per tuning study, and the preset;
    test loss at the budget over every study's runs; time to target), the warnings on the tuned
    values and on what the search covered (searched: coverage_lines), and the target."""
    lines = [
        "",
        "## Variants",
        "",
        "| variant | tuned | preset | test loss at the budget: median [min, max] | diverged | "
        "to target (s): median, reached |",
        "|---|---|---|---|---|---|",
    ]
    for variant in variants:
        sub = runs[runs.variant == variant.name] if len(runs) else runs
        losses = sub["test_loss_at_1"].to_numpy(float) if len(sub) else np.empty(0)
        present = losses[~np.isnan(losses)]
        reach = sub["time_to_target"].to_numpy(float) if len(sub) else np.empty(0)
        tuned = tuned_text([study[variant.name] for study in best])
        preset = (
            ", ".join(
                f"{k}={fmt(float(val)) if isinstance(val, (int, float)) else val}"
                for k, val in variant.preset.items()
            )
            or "-"
        )
        spread = (
            f"{fmt(float(np.median(present)))} [{fmt(float(present.min()))}, "
            f"{fmt(float(present.max()))}]"
            if present.size
            else "-"
        )
        lines.append(
            f"| {variant.name} | {tuned} | {preset} | {spread} | {int(np.isinf(present).sum())} of "
            f"{present.size} | {fmt(float(np.median(reach))) if reach.size else '-'}, "
            f"{int(np.isfinite(reach).sum())} of {reach.size} |"
        )
    lines += edge_lines(variants, best, trials)
    lines += list(searched)
    lines += [
        "",
        f"Target: {fmt(target)}, the median test loss of {target_variant or '-'} (the lowest) at "
        "the budget; a run that never reaches it counts as infinite. Losses at 1/4 and 1/2 of the "
        "budget and per seed: runs.csv; every comparison at every fraction with its p-values: "
        "comparisons.csv; trials: trials.csv and sensitivity.png; curves: report/.",
    ]
    return lines


def tuned_text(per_study: list[dict]) -> str:
    """A variant's tuned settings, each key with its value in every tuning study in turn
    (learning_rate=0.001, 0.0021, 0.0013): the spread the tuning itself leaves."""
    keys = list(dict.fromkeys(key for settings in per_study for key in settings))
    return (
        "; ".join(
            f"{key}=" + ", ".join(fmt(float(s[key])) if key in s else "-" for s in per_study)
            for key in keys
        )
        or "as configured"
    )


def trial_rows(folder: Path, variants: list[Variant], studies: int = 1) -> list[dict]:
    """trials.csv: every trial of the first `studies` tuning studies, variant by variant within a
    study."""
    import optuna

    from physgrad.comparison.tuning import journal_storage, optuna_study_name, trial_params

    path = folder / "tuning.journal"
    if not path.exists():
        return []
    storage = journal_storage(path)
    rows = []
    for k, variant in ((k, v) for k in range(studies) for v in variants):
        study = optuna.load_study(study_name=optuna_study_name(variant, k), storage=storage)
        for t in study.trials:
            # a trial set aside (params that are not the variant's search space) is listed without
            # them: they are data of unknown origin
            params = trial_params(t, variant.space)
            value = t.value if isinstance(t.value, (int, float)) else math.nan
            rows.append(
                {
                    "variant": variant.name,
                    "study": k,
                    "trial": t.number,
                    **(params or {}),
                    "validation_loss": value,
                    "state": t.state.name if params is not None else "SET_ASIDE",
                }
            )
    return rows
