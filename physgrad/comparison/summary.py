"""Phase 3 of a study: the verdicts (physgrad.verdict) from the TEST loss, and what they are written
to: compare.md, trials.csv, runs.csv and comparisons.csv."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

from physgrad.comparison.calibration import cost_spread
from physgrad.comparison.clock_text import timing_lines
from physgrad.comparison.compare_text import detectable, variant_lines, verdict_lines
from physgrad.comparison.coverage import (
    coverage_lines,
    few_steps_lines,
    same_point_line,
    tried_values,
)
from physgrad.comparison.spec import StudySettings, Variant
from physgrad.files import replaced
from physgrad.readout import run_record, target_loss
from physgrad.replication import across_studies
from physgrad.verdict import (
    FRACTIONS,
    compare_variants,
    divergence_test,
    ratio_of,
)

if TYPE_CHECKING:
    import pandas as pd

    from physgrad.readout import Curve
    from physgrad.results import Run
    from physgrad.verdict import PairVerdict


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
        if settings.tune and settings.tuned_in is None
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


def trial_rows(folder: Path, variants: list[Variant], studies: int = 1) -> list[dict]:
    """trials.csv: every trial of the first `studies` tuning studies, variant by variant within a
    study."""
    import optuna

    from physgrad.comparison.journal import journal_storage
    from physgrad.comparison.tuning import optuna_study_name, trial_params

    path = folder / "tuning.journal"
    if not path.exists():
        return []
    storage = journal_storage(path)
    rows = []
    for k, variant in ((k, v) for k in range(studies) for v in variants):
        search = optuna.load_study(study_name=optuna_study_name(variant, k), storage=storage)
        for t in search.trials:
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
