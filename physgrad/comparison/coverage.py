"""What a study's search could have found: warnings, in `--plan` before anything runs and in
compare.md after, where the trial points leave out what a verdict silently relies on.

- a variant's preset (the value its config ships, often the one its paper used) lies outside every
  value tried: the tuning never tried the setting the variant is known to work at;
- a decade or more of a key's log range holds no trial: a best setting there cannot be found;
- fewer than MIN_TRIALS trials per tuning study: each tuned value is one of those few points,
  whatever the verdict then says.

A verdict between tuned variants is only as good as their tuning (docs/protocol.md); these say where
the tuning was too thin to trust it, in the numbers of the study itself.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from physgrad.comparison.spec import StudyPlan, Variant
from physgrad.readout import fmt

MIN_TRIALS = 4  # below it, a tuned value is one of a handful of points of its range
DECADE = 1.0  # the widest untried stretch of a log range that passes unremarked (log10 units)


def planned_points(plan: StudyPlan) -> dict[str, dict[str, list[float]]]:
    """Every value each variant's tuning studies will try, key by key (the shifted Halton points
    of physgrad.comparison.tuning, known before anything runs)."""
    from physgrad.comparison.tuning import halton_points, point_dimensions

    settings = plan.settings
    dimensions = point_dimensions([variant.space for variant in plan.variants])
    tried: dict[str, dict[str, list[float]]] = {}
    for variant in plan.variants:
        keys = tried.setdefault(variant.name, {key: [] for key in variant.space})
        for study in range(settings.study_count):
            points = halton_points(
                variant.space, settings.trials, settings.tune_seed + study, dimensions
            )
            for point in points:
                for key, value in point.items():
                    keys[key].append(value)
    return tried


def tried_values(rows: Sequence[Mapping]) -> dict[str, dict[str, list[float]]]:
    """The values trials.csv's rows tried, by variant and key (rows set aside have none)."""
    skip = {"variant", "study", "trial", "validation_loss", "state"}
    tried: dict[str, dict[str, list[float]]] = {}
    for row in rows:
        keys = tried.setdefault(str(row["variant"]), {})
        for key, value in row.items():
            if key not in skip and isinstance(value, (int, float)) and math.isfinite(value):
                keys.setdefault(key, []).append(float(value))
    return tried


def coverage_lines(
    variants: Sequence[Variant], tried: Mapping[str, Mapping[str, list[float]]], trials: int
) -> list[str]:
    """The warnings of the module docstring, one line each (empty where the search covers what it
    should). tried: the values each variant's trials tried (or will try), by key; trials: the
    trials per tuning study."""
    lines = []
    if trials < MIN_TRIALS and any(variant.space for variant in variants):
        lines.append(
            f"warning: {trials} trial{'s' if trials != 1 else ''} per tuning study: each tuned "
            f"value is one of {trials} point{'s' if trials != 1 else ''} of its range, and a best "
            "setting elsewhere cannot be found, whatever the verdicts say "
            f"(compare.trials={MIN_TRIALS} or more)"
        )
    for variant in variants:
        preset = variant.preset if variant.config is not None else {}
        for key, (low, high) in sorted(variant.space.items()):
            values = sorted(v for v in tried.get(variant.name, {}).get(key, []) if v > 0)
            if not values:
                continue
            lines += _preset_line(variant.name, key, preset.get(key), values, low, high)
            lines += _gap_line(variant.name, key, values, low, high)
    return ([""] + lines) if lines else []


def _preset_line(
    name: str, key: str, preset: object, values: list[float], low: float, high: float
) -> list[str]:
    """A warning where the preset lies outside every value tried."""
    if not isinstance(preset, (int, float)) or isinstance(preset, bool) or not preset > 0:
        return []
    if values[0] <= preset <= values[-1]:
        return []
    side, nearest = ("above", values[-1]) if preset > values[-1] else ("below", values[0])
    outside = not low <= preset <= high
    where = (
        f"outside the range [{fmt(low)}, {fmt(high)}] searched"
        if outside
        else f"{side} every trial (the {'highest' if side == 'above' else 'lowest'} tried: "
        f"{fmt(nearest)})"
    )
    return [
        f"warning: {name}'s preset {key}={fmt(float(preset))} lies {where}: the tuning never "
        f"tried the setting the variant ships with; widen the range or add trials "
        f"(compare.search.{key}=[low,high], compare.trials)"
    ]


def _gap_line(name: str, key: str, values: list[float], low: float, high: float) -> list[str]:
    """A warning for the widest stretch of the log range without a trial, where it is a decade or
    more."""
    ends = [math.log10(low), *(math.log10(v) for v in values), math.log10(high)]
    width, start = max((b - a, a) for a, b in zip(ends, ends[1:]))
    if width < DECADE - 1e-9:
        return []
    return [
        f"warning: no trial of {name}'s {key} between {fmt(10**start)} and "
        f"{fmt(10 ** (start + width))} ({width:.1f} decades of its range [{fmt(low)}, "
        f"{fmt(high)}] untried)"
    ]
