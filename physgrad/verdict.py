"""The verdict rule: which of two variants reaches the lower held-out loss, how sure that is, and
whether it holds as the budget grows. One implementation, used by `physgrad compare` and by the
papers' claims (experiments/claims.py); docs/protocol.md gives the reasons and sources.

For variants A and B trained on the same seeds (paired: same data and initial network), at a budget
x:
- each run's loss at x is read by physgrad.readout (Curve.at): its last evaluation at or before x,
  infinite if it diverged by x, missing (NaN) if it ended before x without diverging: such a pair is
  left out and counted;
- per seed r = log(loss_A / loss_B); a pair where both diverged is left out and counted (it is
  no evidence of a difference nor of equivalence), one diverged is +-LOG_CAP (beyond any finite
  ratio: it only enters through ranks and the median); a negative loss leaves its pair out and the
  verdict undecided (losses are compared by ratios); a loss below LOSS_FLOOR (0 included)
  counts as LOSS_FLOOR;
- the median of r with a percentile bootstrap 95% interval (scipy.stats.bootstrap, 10,000 resamples,
  fixed seed); one-sided Wilcoxon signed-rank tests for "A lower" and "B lower" (zeros split), whose
  smaller p, doubled, is the comparison's p of a difference; two one-sided Wilcoxon tests of |r| <
  log(MARGIN) for equivalence; both p-values Holm-corrected over the comparisons of one study;
- verdict: A better when the interval lies below -log(MARGIN) and the corrected p of a difference is
  below ALPHA; B better when it lies above log(MARGIN) and p < ALPHA; equivalent (within 10%) when
  the corrected equivalence p is below ALPHA and both diverged on as many seeds; undecided
  otherwise (also with fewer than MIN_PAIRS pairs); at a calibrated time budget a "better" must
  survive the step costs' intervals (clock_check);
- over independent tuning studies (across_studies): a majority, none against, every median on the
  side of a "better"; each verdict states the ratio it could detect (detectable_ratio);
- decided at x = X/4, X/2 and X (X the budget), and called stable where the verdicts at X/2 and X
  agree; the median ratio's movement from X/2 to X is reported in both directions (the gap widens or
  narrows).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from physgrad.paired_stats import (  # noqa: F401 - the rule's statistics, also read from here
    CONFIDENCE,
    LOG_CAP,
    LOSS_FLOOR,
    MARGIN,
    RESAMPLES,
    Paired,
    holm,
    log_ratio,
    median_interval,
    paired,
    ratio_of,
    snap,
)
from physgrad.readout import FRACTIONS, Curve

ALPHA = 0.05
MIN_PAIRS = 5  # below this no test can reach ALPHA after correction; the verdict stays undecided
A_BETTER, B_BETTER, EQUIVALENT, UNDECIDED = "A better", "B better", "equivalent", "undecided"


def seeds_for_one_against(alpha: float = ALPHA, comparisons: int = 1) -> int:
    """The fewest paired seeds with which "better" can be decided with one seed on the other side:
    the exact two-sided p of the signed-rank test when that seed has the smallest |r|, 4 / 2^n, must
    be below alpha / comparisons (Holm's strictest step). 7 for one comparison at 0.05, 8 for three,
    9 for six. With fewer, every seed must lie on one side."""
    n = 1
    while 4.0 / 2.0**n >= alpha / comparisons:
        n += 1
    return n


def seeds_needed(alpha: float = ALPHA, comparisons: int = 1) -> int:
    """The fewest paired seeds with which a comparison can be decided at all: the smallest two-sided
    p of the signed-rank test, 2 / 2^n (every seed on one side), must be below alpha / comparisons
    (Holm's strictest step). 6 for one comparison at 0.05, 7 for three, 8 for six."""
    n = 1
    while 2.0 ** (1 - n) >= alpha / comparisons:
        n += 1
    return max(n, MIN_PAIRS)


def decide(
    p: Paired,
    p_difference: float,
    p_equivalent: float,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    comparisons: int = 1,
) -> tuple[str, str]:
    """The verdict and why, from the paired statistics and the Holm-corrected p-values. Equivalence
    also needs as many divergences on each side: a variant that diverged on more seeds than the
    other does not train alike, however close the rest."""
    delta = math.log(margin)
    if p.negative:
        return UNDECIDED, (
            f"a loss below 0 on {p.negative} of {p.seeds} seeds: losses are compared by their "
            "ratios, so give the scene a loss of at least 0"
        )
    if p.pairs < MIN_PAIRS:
        return UNDECIDED, _too_few(p, alpha, comparisons)
    if p.high < -delta and p_difference < alpha:
        return A_BETTER, f"interval below 1/{margin:g}, p = {p_difference:.2g}"
    if p.low > delta and p_difference < alpha:
        return B_BETTER, f"interval above {margin:g}, p = {p_difference:.2g}"
    if p_equivalent < alpha and p.diverged_a == p.diverged_b:
        return EQUIVALENT, f"within {100 * (margin - 1):.0f}%, p = {p_equivalent:.2g}"
    if p_equivalent < alpha:
        return UNDECIDED, (
            f"within {100 * (margin - 1):.0f}% where both trained (p = {p_equivalent:.2g}), but "
            f"A diverged on {p.diverged_a} and B on {p.diverged_b} of {p.seeds} seeds"
        )
    if p_difference < alpha:
        return (
            UNDECIDED,
            f"different (p = {p_difference:.2g}), but not by {100 * (margin - 1):.0f}% with "
            "confidence",
        )
    if p.pairs < seeds_needed(alpha, comparisons):
        return UNDECIDED, _too_few(p, alpha, comparisons)
    unequal = (
        f"; A diverged on {p.diverged_a} and B on {p.diverged_b} of {p.seeds} seeds"
        if p.diverged_a != p.diverged_b
        else ""
    )
    return (
        UNDECIDED,
        f"p = {p_difference:.2g} (difference), {p_equivalent:.2g} (equivalence){unequal}",
    )


def _too_few(p: Paired, alpha: float, comparisons: int) -> str:
    """Why a comparison of few pairs is undecided: how many it would take at Holm's strictest
    step."""
    needed = seeds_needed(alpha, comparisons)
    both = f"; both diverged on {p.both_diverged} of {p.seeds} seeds" if p.both_diverged else ""
    return (
        f"{p.pairs} paired seeds cannot reach p < {alpha:g} over {comparisons} comparisons "
        f"(at least {needed} needed){both}"
    )


@dataclass
class PairVerdict:
    """A against B at X/4, X/2 and X: statistics, corrected p-values and verdicts per budget
    fraction."""

    a: str
    b: str
    budget: float
    at: dict = field(default_factory=dict)  # fraction -> Paired
    p_difference: dict = field(default_factory=dict)  # fraction -> Holm-corrected
    p_equivalent: dict = field(default_factory=dict)
    verdicts: dict = field(default_factory=dict)  # fraction -> (verdict, why)
    # over repeated tuning studies (across_studies): each study's own verdicts
    studies: list = field(default_factory=list)

    @property
    def verdict(self) -> str:
        return self.verdicts[1.0][0]

    @property
    def stable(self) -> bool:
        return self.verdicts[0.5][0] == self.verdicts[1.0][0]

    @property
    def reversed(self) -> bool:
        """One variant better at one fraction of the budget and the other at another (X/4, X/2, X):
        the ranking flips as training goes on, which the X/2-against-X flag alone cannot see."""
        found = {self.verdicts[f][0] for f in FRACTIONS}
        return A_BETTER in found and B_BETTER in found

    @property
    def trend(self) -> str:
        """How the median ratio moved from X/2 to X, in either direction."""
        half, full = self.at[0.5].median, self.at[1.0].median
        if not (math.isfinite(half) and math.isfinite(full)):
            return "-"
        change = abs(full) - abs(half)
        if abs(change) < math.log(MARGIN) / 2:
            return "steady"
        return "gap widening" if change > 0 else "gap narrowing"


def losses_at(curves: dict[int, Curve], seeds: list[int], x: float) -> list[float]:
    return [curves[s].at(x) if s in curves else math.nan for s in seeds]


def compare_variants(
    curves: dict[str, dict[int, Curve]],
    budget: float,
    pairs: list[tuple[str, str]] | None = None,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    fractions: Sequence[float] = FRACTIONS,
    cost_spread: dict[str, tuple[float, float]] | None = None,
) -> list[PairVerdict]:
    """Every pair (A, B) of variants (default: all pairs, in the given order) decided at each
    fraction of the budget; Holm's correction runs over the pairs at each fraction. curves: variant
    -> seed -> Curve. cost_spread (calibrated-time budgets): each variant's step-cost interval as
    factors of its cost; a "better" is then checked against the clock (clock_check)."""
    names = list(curves)
    pairs = (
        pairs
        if pairs is not None
        else [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names))]
    )
    results = [PairVerdict(a, b, budget) for a, b in pairs]
    for fraction in fractions:
        x = budget * fraction
        for result in results:
            seeds = sorted(set(curves[result.a]) | set(curves[result.b]))
            result.at[fraction] = paired(
                losses_at(curves[result.a], seeds, x), losses_at(curves[result.b], seeds, x), margin
            )
        diff = holm([r.at[fraction].p_difference for r in results])
        equiv = holm([r.at[fraction].p_equivalent for r in results])
        for result, pd, pe in zip(results, diff, equiv):
            result.p_difference[fraction], result.p_equivalent[fraction] = pd, pe
            result.verdicts[fraction] = decide(
                result.at[fraction], pd, pe, margin, alpha, len(results)
            )
            if cost_spread:
                result.verdicts[fraction] = clock_check(
                    result, fraction, curves, cost_spread, margin, alpha, len(results)
                )
    return results


UNDECIDED_BY_THE_CLOCK = "undecided by the clock"


def clock_check(
    result: PairVerdict,
    fraction: float,
    curves: dict[str, dict[int, Curve]],
    cost_spread: dict[str, tuple[float, float]],
    margin: float,
    alpha: float,
    comparisons: int,
) -> tuple[str, str]:
    """A "better" at a calibrated time budget x, decided again with the winner's step cost at the
    top of its interval and the loser's at the bottom: the winner then trains for a share rho =
    (loser's low / cost) / (winner's high / cost) of the loser's time, so its losses are read at
    rho x (Holm replaced by Bonferroni over the comparisons, the stricter). Where that is not the
    same verdict the direction rests on a step-cost difference the calibration could not resolve:
    undecided, and why says so (two copies of one rule measured apart on a busy machine)."""
    verdict, why = result.verdicts[fraction]
    if verdict not in (A_BETTER, B_BETTER):
        return verdict, why
    winner, loser = (result.a, result.b) if verdict == A_BETTER else (result.b, result.a)
    rho = cost_spread[loser][0] / cost_spread[winner][1]
    if rho >= 1.0:
        return verdict, why
    x = result.budget * fraction
    seeds = sorted(set(curves[result.a]) | set(curves[result.b]))
    at = {winner: rho * x, loser: x}
    shifted = paired(
        losses_at(curves[result.a], seeds, at[result.a]),
        losses_at(curves[result.b], seeds, at[result.b]),
        margin,
    )
    again, _ = decide(
        shifted,
        min(1.0, comparisons * shifted.p_difference),
        min(1.0, comparisons * shifted.p_equivalent),
        margin,
        alpha,
        comparisons,
    )
    if again == verdict:
        return verdict, why
    return UNDECIDED, (
        f"{UNDECIDED_BY_THE_CLOCK}: {verdict} ({why}), but {again} with {winner}'s step cost at "
        f"the top of its calibrated interval and {loser}'s at the bottom ({winner} trains "
        f"{100 * (1 - rho):.0f}% less)"
    )


def divergence_test(diverged_a: int, n_a: int, diverged_b: int, n_b: int) -> float:
    """Two-sided Fisher exact test of the divergence counts k of n (scipy.stats.fisher_exact)."""
    from scipy.stats import fisher_exact

    if n_a == 0 or n_b == 0:
        return math.nan
    return float(
        fisher_exact([[diverged_a, n_a - diverged_a], [diverged_b, n_b - diverged_b]]).pvalue
    )


def divergence_flag(p: Paired, a: str = "A", b: str = "B", alpha: float = ALPHA) -> str:
    """Divergence as its own endpoint beside the loss verdict: where the two variants' divergence
    counts differ by Fisher's exact test at alpha, "a diverged on k of n, b on m of n (Fisher p =
    ...)", whatever the verdict on the losses; "" otherwise."""
    p_value = divergence_test(p.diverged_a, p.seeds, p.diverged_b, p.seeds)
    if math.isnan(p_value) or p_value >= alpha:
        return ""
    return (
        f"{a} diverged on {p.diverged_a} of {p.seeds} seeds, {b} on {p.diverged_b} "
        f"(Fisher p = {p_value:.2g})"
    )
