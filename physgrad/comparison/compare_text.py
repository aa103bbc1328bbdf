"""compare.md's sections on the verdicts and the variants: the verdict table with what each study
decided and could detect, the rule in words, and each variant's tuned settings and losses (the
timing section is physgrad.comparison.clock_text)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from physgrad.comparison.clock_text import busy_calibration
from physgrad.comparison.coverage import edge_lines
from physgrad.comparison.spec import StudySettings, Variant
from physgrad.power import POWER, detectable_ratio, measured
from physgrad.readout import fmt
from physgrad.replication import majority
from physgrad.verdict import divergence_flag, ratio_of, seeds_for_one_against

if TYPE_CHECKING:
    import pandas as pd

    from physgrad.verdict import Paired, PairVerdict


def _ratio_text(p: Paired) -> str:
    return f"{fmt(p.ratio)} [{fmt(ratio_of(p.low))}, {fmt(ratio_of(p.high))}]"


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
    if settings.tuned_in is not None:
        return (
            f"Not tuned here: every variant at the settings tuned in {settings.tuned_in} (the "
            "best trial of each of its tuning studies, by their validation loss at that study's "
            "budget), evaluated at this study's budget."
        )
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
