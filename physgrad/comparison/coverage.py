"""What a study's search could have found: warnings, in `--plan` before anything runs and in
compare.md after, where the trial points leave out what a verdict silently relies on.

- a variant's preset (the value its config ships, often the one its paper used) lies outside every
  value tried: the tuning never tried the setting the variant is known to work at;
- a decade or more of a key's log range holds no trial: a best setting there cannot be found;
- fewer than MIN_TRIALS trials per tuning study: each tuned value is one of those few points,
  whatever the verdict then says;
- fewer than PER_DECADE points per decade of a key's range over all tuning studies (their points
  interleave, so together they are one finer grid): a note that each tuned value is a point of a
  coarse grid, and how coarse;
- every variant tuned to the same point of its range in every tuning study (compare.md only): the
  tuned values are the shared grid, not a search that told the rules apart;
- a tuned value in the outer tenth of its range (compare.md only): the best may lie beyond it,
  unless the edge is a plateau, which a note says instead;
- a variant that gets fewer than FEW_STEPS steps in a time budget (from its measured step in
  `--plan`, from its runs' iterations in compare.md): its verdict says more about what a step
  costs on this machine than about where the rule goes; the note gives the budget that would
  give it that many.

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
# points per decade of a range, over all tuning studies, below which the grid is called coarse: a
# point every 1/6 decade places a tuned value within about 20% of the grid's best
PER_DECADE = 6
# steps of a rule in a time budget below which its verdict is one about its step's cost (a Jacobian
# rule's step can cost hundreds of Adam's): said in --plan, compare.md and the leaderboard
FEW_STEPS = 100


def few_steps_lines(steps: Mapping[str, float], budget: float) -> list[str]:
    """A note per variant with fewer than FEW_STEPS steps in a time budget of `budget` seconds
    (steps: variant -> its steps in it, expected or run), with the budget that gives it that
    many."""
    lines = []
    for name, count in steps.items():
        if math.isfinite(count) and count < FEW_STEPS:
            needed = budget * FEW_STEPS / max(count, 1.0)
            lines.append(
                f"note: {name} gets about {count:.0f} steps in the budget of {budget:g} s, "
                f"fewer than {FEW_STEPS}: a verdict on it says more about what its step costs on "
                "this machine than about where the rule goes (trainer.time_budget="
                f"{_round_up(needed)} gives it about {FEW_STEPS})"
            )
    return [""] + lines if lines else []


def _round_up(seconds: float) -> str:
    """A budget rounded up to two significant figures."""
    digits = 10 ** max(0, math.floor(math.log10(seconds)) - 1)
    return f"{math.ceil(seconds / digits) * digits:g}"


def planned_points(plan: StudyPlan) -> dict[str, dict[str, list[float]]]:
    """Every value each variant's tuning studies will try, key by key (the shifted Halton points
    of physgrad.comparison.tuning, known before anything runs)."""
    from physgrad.comparison.points import halton_points, point_dimensions

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
    variants: Sequence[Variant],
    tried: Mapping[str, Mapping[str, list[float]]],
    trials: int,
    studies: int = 1,
) -> list[str]:
    """The warnings of the module docstring, one line each (empty where the search covers what it
    should). tried: the values each variant's trials tried (or will try), by key; trials: the
    trials per tuning study; studies: the tuning studies."""
    lines = []
    if trials < MIN_TRIALS and any(variant.space for variant in variants):
        lines.append(
            f"warning: {trials} trial{'s' if trials != 1 else ''} per tuning study: each tuned "
            f"value is one of {trials} point{'s' if trials != 1 else ''} of its range, and a best "
            "setting elsewhere cannot be found, whatever the verdicts say "
            f"(compare.trials={MIN_TRIALS} or more)"
        )
    coarse = []
    for variant in variants:
        for key, (low, high) in sorted(variant.space.items()):
            decades = math.log10(high / low)
            points = trials * studies
            if decades > 0 and points / decades < PER_DECADE:
                coarse.append(
                    f"{variant.name}'s {key} {points} points over {decades:.2g} decades (one every "
                    f"{decades / points:.2g} decade)"
                )
    if coarse:
        lines.append(
            "note: the tuning's grid is coarse (fewer than "
            f"{PER_DECADE} points a decade over all tuning studies): "
            + "; ".join(coarse)
            + ": each tuned value is a point of that grid, not a finer search "
            "(compare.trials, or a narrower compare.search range)"
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


def same_point_line(
    variants: Sequence[Variant], best: Sequence[Mapping[str, Mapping]]
) -> list[str]:
    """A note where every variant (two or more, tuned) chose the same point of its learning-rate
    range in every tuning study (two or more; best: per study, variant -> its tuned values): the
    tuned values are then the shared grid's point, not a search that told the rules apart."""
    from physgrad.comparison.points import is_rate_key

    tuned = [v for v in variants if v.space]
    if len(tuned) < 2 or len(best) < 2:  # one study's coincidence says nothing of the grid
        return []
    for study in best:
        places = set()
        for variant in tuned:
            key = next((k for k in variant.space if is_rate_key(k)), None)
            value = study.get(variant.name, {}).get(key) if key else None
            if not isinstance(value, (int, float)) or not value > 0:
                return []
            low, high = variant.space[key]
            places.add(round(math.log(value / low) / math.log(high / low), 6))
        if len(places) > 1:
            return []
    return [
        "note: every variant was tuned to the same point of its learning-rate range in every "
        "tuning study: the tuned rates are the shared grid's point, not a search that told the "
        "rules apart (compare.trials: more points)"
    ]


def _outermost(values: list[float], bounds: tuple | None) -> float:
    """The value nearest either end of its log range."""
    if bounds is None:
        return values[0]
    low, high = (math.log(b) for b in bounds)
    return max(values, key=lambda v: abs((math.log(v) - low) / (high - low) - 0.5) if v > 0 else 0)


EDGE = 0.1  # a tuned value in the outer tenth of its log range is at the range's edge


FLAT = 1.25  # trials on the edge's side whose validation losses lie within this factor: a plateau


def edge_lines(
    variants: list[Variant], best: list[dict[str, dict]], trials: Sequence[Mapping] = ()
) -> list[str]:
    """A warning per tuned value in the outer tenth of its log-uniform range (in any tuning study;
    best: per study): the best trial may lie beyond the range, which should then be widened
    (compare.search.KEY=[low,high]). Where the trials of every study in the outer fifth on that
    side (three or more) scored within a factor FLAT of each other, the edge is a plateau (the
    rule barely trains at any value there, so the lowest score falls anywhere on it): a note says
    so instead, with the scores, since no range would move it."""
    lines = []
    for variant in variants:
        found = {}
        for study in best:
            for key, value in study[variant.name].items():
                found.setdefault(key, []).append(value)
        for key, values in found.items():
            value = _outermost(values, variant.space.get(key))
            low, high = variant.space.get(key, (None, None))
            if low is None or not value > 0:
                continue
            where = (math.log(value) - math.log(low)) / (math.log(high) - math.log(low))
            if EDGE <= where <= 1 - EDGE:
                continue
            side = "lowest" if where < EDGE else "highest"
            tuned, bounds = fmt(float(value)), f"[{fmt(float(low))}, {fmt(float(high))}]"
            flat = _plateau(variant, key, trials, low, high, side)
            if flat:
                lines.append(
                    f"note: {variant.name}'s tuned {key}={tuned} lies in the {side} tenth of its "
                    f"range {bounds}, on a plateau: its trials in the {side} fifth scored "
                    f"{flat} (within {FLAT:g}x of each other), so it barely trains at any {key} "
                    "there and a wider range would not move the verdict"
                )
                continue
            lines.append(
                f"warning: {variant.name}'s tuned {key}={tuned} lies in the {side} tenth of its "
                f"range {bounds}: the best setting may lie beyond it; widen the range "
                f"(compare.search.{key}=[low,high])"
            )
    return ([""] + lines) if lines else []


def _plateau(
    variant: Variant, key: str, trials: Sequence[Mapping], low: float, high: float, side: str
) -> str:
    """The validation losses of the variant's trials in the outer fifth of the range on `side`,
    as "0.46 to 0.52", where there are three or more, all finite and within FLAT of each other;
    "" otherwise."""
    scores = []
    for row in trials:
        if str(row.get("variant")) != variant.name:
            continue
        value, score = row.get(key), row.get("validation_loss")
        if not isinstance(value, (int, float)) or not isinstance(score, (int, float)):
            continue
        where = (math.log(value) - math.log(low)) / (math.log(high) - math.log(low))
        if (where < 2 * EDGE) if side == "lowest" else (where > 1 - 2 * EDGE):
            scores.append(float(score))
    if len(scores) < 3 or not all(math.isfinite(v) and v > 0 for v in scores):
        return ""
    if max(scores) > FLAT * min(scores):
        return ""
    return f"{fmt(min(scores))} to {fmt(max(scores))}"
