"""Unit layer of the verdict rule (physgrad.verdict) on synthetic seeds: better, equivalent and
undecided, the loss at the budget, divergences, NaN, zero and negative losses, trends, reversals,
Holm's correction, verdicts over tuning studies, a lead resting on step costs, and levels."""

import math

import numpy as np
import pytest

from physgrad.readout import Curve
from physgrad.replication import across_studies
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    EQUIVALENT,
    LOG_CAP,
    UNDECIDED,
    compare_variants,
    decide,
    holm,
    paired,
    seeds_needed,
)

SEEDS = range(10)


def flat_curves(
    finals: dict[int, float], budget: float = 100.0, start: float = 1.0
) -> dict[int, Curve]:
    """Per seed a curve that falls linearly from `start` to its final loss, evaluated every 10 % of
    the budget."""
    x = np.linspace(0, budget, 11)
    return {s: Curve(x, np.linspace(start, final, 11), budget) for s, final in finals.items()}


def test_a_variant_20_percent_better_in_every_seed_is_better_and_stable():
    rng = np.random.default_rng(1)
    base = np.exp(rng.normal(0, 0.5, 10))  # seeds differ a lot; the pairing removes it
    a = {s: 0.8 * base[s] * math.exp(rng.normal(0, 0.02)) for s in SEEDS}
    b = {s: base[s] for s in SEEDS}
    (result,) = compare_variants({"A": flat_curves(a), "B": flat_curves(b)}, 100.0)
    assert result.verdict == A_BETTER and result.stable
    assert result.at[1.0].ratio == pytest.approx(0.8, rel=0.05) and result.at[1.0].wins_a == 10
    assert result.at[1.0].high < -math.log(1.1)
    (swapped,) = compare_variants({"B": flat_curves(b), "A": flat_curves(a)}, 100.0)
    assert swapped.verdict == B_BETTER


def test_two_identical_variants_are_equivalent_never_better():
    rng = np.random.default_rng(2)
    base = np.exp(rng.normal(0, 0.5, 10))
    a = {s: base[s] * math.exp(rng.normal(0, 0.01)) for s in SEEDS}
    (result,) = compare_variants(
        {"A": flat_curves(a), "B": flat_curves(dict(enumerate(base)))}, 100.0
    )
    assert result.verdict == EQUIVALENT
    exact = paired(list(base), list(base))  # bit-identical runs: every log ratio 0
    assert decide(exact, exact.p_difference, exact.p_equivalent)[0] == EQUIVALENT


def test_a_difference_at_the_margin_is_undecided_and_a_small_one_equivalent():
    """10 % better with 5 % run noise: different in every seed, but neither clearly beyond the 10 %
    margin nor within it; 5 % better with 1 % noise: level within 10 %."""
    rng = np.random.default_rng(3)
    base = np.exp(rng.normal(0, 0.5, 10))
    edge = {s: base[s] / 1.1 * math.exp(rng.normal(0, 0.05)) for s in SEEDS}
    (result,) = compare_variants(
        {"A": flat_curves(edge), "B": flat_curves(dict(enumerate(base)))}, 100.0
    )
    assert result.verdict == UNDECIDED and "not by 10%" in result.verdicts[1.0][1], result.verdicts[
        1.0
    ]
    small = {s: 0.95 * base[s] * math.exp(rng.normal(0, 0.01)) for s in SEEDS}
    (result,) = compare_variants(
        {"A": flat_curves(small), "B": flat_curves(dict(enumerate(base)))}, 100.0
    )
    assert result.verdict == EQUIVALENT


def test_the_loss_at_the_budget_is_the_last_evaluation_not_the_best_so_far():
    """Non-monotone: A dips to 0.1 halfway and ends at 2.0; B ends at 1.0: B is better at the
    budget."""
    x = np.array([0, 25, 50, 75, 100.0])
    a = {s: Curve(x, np.array([3.0, 1.0, 0.1, 1.5, 2.0]) * (1 + 0.01 * s), 100.0) for s in SEEDS}
    b = {s: Curve(x, np.array([3.0, 2.0, 1.5, 1.2, 1.0]) * (1 + 0.01 * s), 100.0) for s in SEEDS}
    (result,) = compare_variants({"A": a, "B": b}, 100.0)
    assert result.verdict == B_BETTER and result.at[1.0].ratio == pytest.approx(2.0)
    assert result.verdicts[0.5][0] == A_BETTER and not result.stable  # at X/2 A was ahead
    assert result.trend in ("gap widening", "gap narrowing", "steady")


def test_a_nan_held_out_loss_counts_as_diverged_and_keeps_its_pair():
    x = np.linspace(0, 100, 11)
    a = flat_curves({s: 0.5 for s in SEEDS})
    # status completed, NaN loss at the end
    a[3] = Curve(x, np.r_[np.linspace(1, 0.5, 10), np.nan], 100.0)
    b = flat_curves({s: 1.0 for s in SEEDS})
    (result,) = compare_variants({"A": a, "B": b}, 100.0)
    p = result.at[1.0]
    assert p.pairs == 10 and p.missing == 0 and p.diverged_a == 1 and p.log_ratios[3] == LOG_CAP
    assert p.wins_a == 9


def test_a_run_that_ended_early_without_diverging_leaves_its_pair_out():
    interrupted = Curve(np.array([0, 10.0]), np.array([1.0, 0.5]), 40.0)
    assert interrupted.at(20) == 0.5 and math.isnan(interrupted.at(100))
    a = flat_curves({s: 0.5 for s in SEEDS})
    a[0] = interrupted
    (result,) = compare_variants({"A": a, "B": flat_curves({s: 1.0 for s in SEEDS})}, 100.0)
    assert result.at[1.0].pairs == 9 and result.at[1.0].missing == 1


def diverged_curves(seeds) -> dict:
    """Runs stopped as diverged at iteration 30 of a budget of 100."""
    x = np.array([0.0, 10.0, 20.0])
    return {s: Curve(x, np.array([1.0, 0.8, 0.9]), 30.0, diverged=True) for s in seeds}


def test_both_diverged_is_never_evidence_of_equivalence():
    """Both variants diverge on every seed: no pair says anything, so no verdict (a tie rule called
    this "equivalent"); nine seeds of double divergence and one where A is 5x B: one pair,
    undecided; identical losses on 6 seeds beside 4 double divergences: equivalent on the 6, with
    the 4 counted."""
    (both,) = compare_variants({"A": diverged_curves(SEEDS), "B": diverged_curves(SEEDS)}, 100.0)
    p = both.at[1.0]
    assert p.pairs == 0 and p.both_diverged == 10 and p.missing == 0 and p.seeds == 10
    assert both.verdict == UNDECIDED and "both diverged on 10 of 10 seeds" in both.verdicts[1.0][1]
    a, b = diverged_curves(range(1, 10)), diverged_curves(range(1, 10))
    a.update(flat_curves({0: 5.0}))
    b.update(flat_curves({0: 1.0}))
    (one,) = compare_variants({"A": a, "B": b}, 100.0)
    assert one.at[1.0].pairs == 1 and one.verdict == UNDECIDED
    a, b = diverged_curves(range(6, 10)), diverged_curves(range(6, 10))
    a.update(flat_curves({s: 0.5 for s in range(6)}))
    b.update(flat_curves({s: 0.5 for s in range(6)}))
    (alike,) = compare_variants({"A": a, "B": b}, 100.0)
    assert alike.at[1.0].pairs == 6 and alike.at[1.0].both_diverged == 4
    assert alike.verdict == EQUIVALENT


def test_one_side_diverged_still_counts_against_it():
    """B diverges on every seed, A on none: A better, whatever the losses."""
    (result,) = compare_variants(
        {"A": flat_curves({s: 3.0 for s in SEEDS}), "B": diverged_curves(SEEDS)}, 100.0
    )
    assert result.at[1.0].pairs == 10 and result.at[1.0].both_diverged == 0
    assert result.verdict == A_BETTER


def test_a_median_or_interval_next_to_a_divergence_is_not_a_ratio_of_e500():
    """10 seeds, B diverged in 5: the median averages a diverged pair with a finite one; it and the
    interval ends that do so are reported as the divergence (ratio 0), the others as finite
    ratios."""
    a = [0.5] * 10
    b = [math.inf] * 5 + [1.0] * 5
    p = paired(a, b)
    assert p.median == -LOG_CAP and p.ratio == 0.0 and p.low == -LOG_CAP
    assert p.high == pytest.approx(math.log(0.5)) or p.high == -LOG_CAP


def test_a_median_halfway_between_a_divergence_and_a_tie_is_the_divergence():
    """6 seeds: B diverged in 3 where A did not, both diverged in 3: the median averages -LOG_CAP
    with 0 to exactly -LOG_CAP / 2, which is the divergence boundary, not a ratio of e^-500."""
    p = paired([0.5] * 3 + [math.inf] * 3, [math.inf] * 6)
    assert p.median == -LOG_CAP and p.ratio == 0.0
    p = paired([math.inf] * 3 + [0.5] * 3, [0.5] * 3 + [math.inf] * 3)
    # ties of +-LOG_CAP: the median is an even split, not a boundary
    assert p.median == 0.0 and p.ratio == 1.0


def test_too_few_seeds_are_undecided_whatever_the_data():
    assert [seeds_needed(0.05, m) for m in (1, 3, 6)] == [6, 7, 8]
    few = {s: 0.5 for s in range(6)}
    results = compare_variants(
        {
            "A": flat_curves(few),
            "B": flat_curves({s: 1.0 for s in range(6)}),
            "C": flat_curves({s: 2.0 for s in range(6)}),
        },
        100.0,
    )
    assert all(
        r.verdict == UNDECIDED and "at least 7 needed" in r.verdicts[1.0][1] for r in results
    )


def test_the_trend_is_reported_in_both_directions():
    x = np.array([0, 50, 100.0])
    closing = compare_variants(
        {
            "A": {s: Curve(x, np.array([1, 0.1, 0.8]), 100.0) for s in SEEDS},
            "B": {s: Curve(x, np.array([1, 1.0, 1.0]), 100.0) for s in SEEDS},
        },
        100.0,
    )[0]
    opening = compare_variants(
        {
            "A": {s: Curve(x, np.array([1, 0.8, 0.1]), 100.0) for s in SEEDS},
            "B": {s: Curve(x, np.array([1, 1.0, 1.0]), 100.0) for s in SEEDS},
        },
        100.0,
    )[0]
    assert closing.trend == "gap narrowing" and opening.trend == "gap widening"


def test_holm_runs_over_the_comparisons_of_one_study():
    rng = np.random.default_rng(4)
    curves = {
        name: flat_curves({s: f * math.exp(rng.normal(0, 0.02)) for s in SEEDS})
        for name, f in (("A", 0.5), ("B", 1.0), ("C", 2.0))
    }
    results = compare_variants(curves, 100.0)
    assert [(r.a, r.b) for r in results] == [("A", "B"), ("A", "C"), ("B", "C")]
    raw = [r.at[1.0].p_difference for r in results]
    assert [r.p_difference[1.0] for r in results] == pytest.approx(holm(raw))
    assert [r.verdict for r in results] == [A_BETTER, A_BETTER, A_BETTER]


def test_an_advantage_that_grows_is_found_and_a_uniform_one_is_not():
    """A/B is 0.9 at the easy end and 0.3 at the hard end (run noise 10%): grows, by about 3x; the
    same 0.5 at both ends (a uniform advantage, which a test of the hard end alone would pass): does
    not grow."""
    from physgrad.trend import DOES_NOT_GROW, GROWS, interaction

    rng = np.random.default_rng(11)
    easy = np.log(0.9) + rng.normal(0, 0.1, 10)
    hard = np.log(0.3) + rng.normal(0, 0.1, 10)
    result = interaction(easy, hard)
    assert result.verdict == GROWS and result.p < 0.01
    assert result.factor == pytest.approx(1 / 3, rel=0.15) and result.high < -math.log(1.1)
    uniform = interaction(
        np.log(0.5) + rng.normal(0, 0.1, 10), np.log(0.5) + rng.normal(0, 0.1, 10)
    )
    assert uniform.verdict == DOES_NOT_GROW and uniform.low > -math.log(1.1)
    reversed_ = interaction(hard, easy)  # the advantage shrinks
    assert reversed_.verdict == DOES_NOT_GROW and reversed_.difference > 0


def test_a_trend_with_few_pairs_missing_pairs_or_wide_noise_is_undecided():
    from physgrad.trend import interaction
    from physgrad.verdict import UNDECIDED

    rng = np.random.default_rng(12)
    few = interaction(np.zeros(4), np.full(4, -2.0))  # a large effect, but 4 pairs at the easy end
    assert (
        few.verdict == UNDECIDED and few.pairs_easy == 4 and few.difference == pytest.approx(-2.0)
    )
    with_nan = interaction(
        [0.0, math.nan, *rng.normal(0, 0.05, 8)], [-1.0, math.nan, *(-1 + rng.normal(0, 0.05, 8))]
    )
    assert (
        with_nan.pairs_easy == 9
        and with_nan.pairs_hard == 9
        and with_nan.factor == pytest.approx(math.exp(-1), rel=0.1)
    )
    noisy = interaction(rng.normal(0, 2.0, 8), -0.3 + rng.normal(0, 2.0, 8))
    assert noisy.verdict == UNDECIDED and noisy.low < -math.log(1.1) < noisy.high


def test_a_diverged_baseline_at_the_hard_end_counts_as_a_growing_advantage():
    """B diverged in every seed at the hard end (log ratio -LOG_CAP): the advantage is as large as
    it gets."""
    from physgrad.trend import GROWS, interaction

    rng = np.random.default_rng(13)
    result = interaction(rng.normal(-0.1, 0.1, 10), np.full(10, -LOG_CAP))
    assert result.verdict == GROWS and result.factor == 0.0


def test_an_undecided_trend_with_divergences_on_both_sides_says_why_in_ratios():
    """Half the hard end's pairs diverged on A's side and half on B's: undecided, its interval
    reaching both divergences, said as 0 and inf (e^+-LOG_CAP is past float64: it was an
    OverflowError)."""
    from physgrad.trend import interaction

    rng = np.random.default_rng(14)
    result = interaction(rng.normal(0, 0.1, 10), np.array([-LOG_CAP, LOG_CAP] * 5))
    assert result.verdict == UNDECIDED and "interval [0, inf]" in result.why


def test_the_seeds_for_a_verdict_with_one_seed_against_match_scipys_exact_test():
    """One seed on the other side, with the smallest |r| (the most favourable place): the first
    seed count at which scipy's exact two-sided signed-rank p is below alpha / comparisons."""
    from scipy.stats import wilcoxon

    from physgrad.verdict import seeds_for_one_against

    for comparisons in (1, 3, 6, 15):
        n = 2
        while True:
            r = np.r_[-0.5, np.arange(1, n) + 0.5]
            if wilcoxon(r, method="exact").pvalue < 0.05 / comparisons:
                break
            n += 1
        assert seeds_for_one_against(0.05, comparisons) == n, comparisons


def test_a_ranking_that_flips_with_the_budget_is_called_reversed():
    """A falls fast and stalls at 0.5, B falls slowly to 0.1: A better at X/4, B better at X; a
    steady advantage is not reversed."""
    x = np.linspace(0, 100, 11)
    a = {s: Curve(x, np.r_[1.0, np.full(10, 0.5)] * (1 + 0.01 * s), 100.0) for s in SEEDS}
    b = {s: Curve(x, np.linspace(1.0, 0.1, 11) * (1 + 0.01 * s), 100.0) for s in SEEDS}
    (flip,) = compare_variants({"A": a, "B": b}, 100.0)
    assert flip.verdicts[0.25][0] == A_BETTER and flip.verdict == B_BETTER and flip.reversed
    steady = flat_curves({s: 0.5 for s in SEEDS})
    (same,) = compare_variants({"A": steady, "B": flat_curves({s: 1.0 for s in SEEDS})}, 100.0)
    assert same.verdict == A_BETTER and not same.reversed


def one_tuning_study(kind: str, seed: int) -> list:
    """A study of A against B whose verdict at the budget is known: A 2x lower, B 2x lower,
    within 1% (equivalent) or noise of a factor 3 either way (undecided)."""
    rng = np.random.default_rng(seed)
    base = np.exp(rng.normal(0, 0.5, 10))
    factor = {"A": 0.5, "B": 2.0, "equivalent": 1.0, "undecided": 1.0}[kind]
    noise = 1.1 if kind == "undecided" else 0.003
    a = {s: factor * base[s] * math.exp(rng.normal(0, noise)) for s in SEEDS}
    studies = compare_variants(
        {"A": flat_curves(a), "B": flat_curves(dict(enumerate(base)))}, 100.0
    )
    expected = {"A": A_BETTER, "B": B_BETTER, "equivalent": EQUIVALENT, "undecided": UNDECIDED}
    assert studies[0].verdict == expected[kind]
    return studies


@pytest.mark.parametrize(
    "kinds, verdict",
    [
        (["A", "A", "A"], A_BETTER),
        # two of three, none against, but the third's median near 1: as draws, three studies do
        # not exclude 1 (t with 2 degrees of freedom at 0.01: 9.9 standard errors)
        (["A", "undecided", "A"], UNDECIDED),
        (["A", "A", "undecided"], UNDECIDED),
        (["A", "undecided", "undecided"], UNDECIDED),  # one tuning draw is not enough
        (["A", "B", "A"], UNDECIDED),  # a study against
        (["A", "equivalent", "A"], UNDECIDED),
        (["equivalent", "equivalent", "undecided"], EQUIVALENT),
        (["B", "B"], B_BETTER),  # of two studies, both
        (["B", "undecided"], UNDECIDED),
        (["undecided"] * 3, UNDECIDED),
    ],
)
def test_a_verdict_over_tuning_studies_needs_a_majority_and_none_against(kinds, verdict):
    per_study = [one_tuning_study(kind, seed) for seed, kind in enumerate(kinds)]
    (result,) = across_studies(per_study)
    assert result.verdict == verdict
    why = result.verdicts[1.0][1]
    assert f"of {len(kinds)} tuning studies" in why or "disagree" in why
    if kinds.count("A") == 2 and "undecided" in kinds:
        assert "taken as draws" in why
    # the pooled statistics count every study's pairs
    assert result.at[1.0].pairs == 10 * len(kinds) and len(result.studies) == len(kinds)
    assert result.at[1.0].wins_a == sum(s[0].at[1.0].wins_a for s in per_study)
    assert result.at[1.0].low == min(s[0].at[1.0].low for s in per_study)
    # the p-value of the majority's weakest study
    ranked = sorted(s[0].p_difference[1.0] for s in per_study)
    assert result.p_difference[1.0] == ranked[len(kinds) // 2]


def test_one_tuning_study_is_its_own_verdict():
    (study,) = one_tuning_study("A", 0)
    assert across_studies([[study]]) == [study]


def test_a_lead_that_rests_on_an_unresolved_step_cost_is_undecided_by_the_clock():
    """Two copies of one rule on the calibrated clock, their costs measured 20% apart (0.8 and 1 ms
    a step): in the same calibrated time A takes 25% more steps and reaches a lower loss in every
    seed. With cost intervals of +-25% the lead does not hold with A's cost at the top of its
    interval and B's at the bottom: undecided by the clock, in either order. With intervals of
    +-1% the costs are resolved, and A's lead, on the clock as measured, stands."""
    from physgrad.verdict import UNDECIDED_BY_THE_CLOCK

    budget, cost = 1.0, {"A": 0.8e-3, "B": 1.0e-3}
    rng = np.random.default_rng(2)
    level = np.exp(rng.normal(0, 0.3, 10))
    times = np.linspace(0, budget, 21)

    def curves(name):
        # the loss halves every 200 iterations: iterations = calibrated time / the step's cost
        return {
            s: Curve(times, level[s] * 0.5 ** (times / cost[name] / 200), budget) for s in SEEDS
        }

    wide = {"A": (0.75, 1.25), "B": (0.75, 1.25)}
    (plain,) = compare_variants({"A": curves("A"), "B": curves("B")}, budget)
    assert plain.verdict == A_BETTER
    for order in (("A", "B"), ("B", "A")):
        (result,) = compare_variants({n: curves(n) for n in order}, budget, cost_spread=wide)
        assert result.verdict == UNDECIDED, order
        assert result.verdicts[1.0][1].startswith(UNDECIDED_BY_THE_CLOCK)
    tight = {"A": (0.99, 1.01), "B": (0.99, 1.01)}
    (result,) = compare_variants({"A": curves("A"), "B": curves("B")}, budget, cost_spread=tight)
    assert result.verdict == A_BETTER


def test_few_seeds_are_decided_where_holms_correction_allows_them():
    """Two comparisons: A against B on 10 seeds (every seed A's: p = 2^-9, first in Holm's order)
    and A against C on only 6 (p = 2^-5 = 0.031, compared with alpha / 1 at Holm's second step):
    both A better. A rule that asked every pair for the seeds of Holm's strictest step (7 for two
    comparisons) had refused the second."""
    a = flat_curves({s: 0.5 for s in SEEDS})
    b = flat_curves({s: 1.0 for s in SEEDS})
    c = flat_curves({s: 1.0 for s in range(6)})
    results = compare_variants({"A": a, "B": b, "C": c}, 100.0, pairs=[("A", "B"), ("A", "C")])
    assert [r.at[1.0].pairs for r in results] == [10, 6]
    assert [r.verdict for r in results] == [A_BETTER, A_BETTER]
    assert results[1].p_difference[1.0] == pytest.approx(2.0**-5)


def test_a_variant_that_diverges_on_more_seeds_is_not_equivalent():
    """Identical losses on the seeds where both trained, and B diverged on 1 (then 3) of 10: the
    pairs that trained are alike, but B is not "equivalent" to A; the reason names the counts.
    Diverging alike on both sides still allows equivalence on the rest."""
    for diverged in (1, 3):
        a = flat_curves({s: 0.5 for s in SEEDS})
        b = flat_curves({s: 0.5 for s in range(diverged, 10)})
        b.update(diverged_curves(range(diverged)))
        (result,) = compare_variants({"A": a, "B": b}, 100.0)
        assert result.verdict == UNDECIDED, diverged
        assert f"A diverged on 0 and B on {diverged} of 10 seeds" in result.verdicts[1.0][1]
    alike_a = flat_curves({s: 0.5 for s in range(1, 10)})
    alike_a.update(diverged_curves([0]))
    alike_b = flat_curves({s: 0.5 for s in range(2, 10)})
    alike_b.update(diverged_curves([1]))
    alike_b.update(flat_curves({0: 0.5}))
    (result,) = compare_variants({"A": alike_a, "B": alike_b}, 100.0)
    assert result.at[1.0].diverged_a == result.at[1.0].diverged_b == 1


def test_a_negative_loss_leaves_its_pair_out_and_says_why():
    """A signed objective (a loss below 0 on some seeds) has no loss ratio: no crash after the
    study trained, the pairs are counted as negative, and the verdict says what to change."""
    a = flat_curves({s: (-0.5 if s < 3 else 0.5) for s in SEEDS})
    b = flat_curves({s: 1.0 for s in SEEDS})
    (result,) = compare_variants({"A": a, "B": b}, 100.0)
    p = result.at[1.0]
    assert p.negative == 3 and p.pairs == 7 and p.seeds == 10
    assert result.verdict == UNDECIDED
    assert "a loss below 0 on 3 of 10 seeds" in result.verdicts[1.0][1]


def test_a_loss_of_zero_against_a_tiny_one_reads_as_a_ratio_not_a_divergence():
    """Exact fits (0) against 1e-30 on every seed: A better with a finite ratio (the floor,
    float32's smallest normal 1.2e-38, over 1e-30), nothing counted as diverged; and below the
    floor losses tie: 1e-320 against 1e-310 and 0 against 1e-39 are both equivalent, one floor
    for both."""
    a = {s: Curve(np.array([100.0]), np.array([0.0]), 100.0) for s in SEEDS}
    b = {s: Curve(np.array([100.0]), np.array([1e-30]), 100.0) for s in SEEDS}
    (result,) = compare_variants({"A": a, "B": b}, 100.0)
    p = result.at[1.0]
    assert result.verdict == A_BETTER and p.diverged_a == p.diverged_b == 0
    assert 1e-9 < p.ratio < 1e-7
    for tiny_a, tiny_b in ((1e-320, 1e-310), (0.0, 1e-39)):
        a = {s: Curve(np.array([100.0]), np.array([tiny_a]), 100.0) for s in SEEDS}
        b = {s: Curve(np.array([100.0]), np.array([tiny_b]), 100.0) for s in SEEDS}
        (result,) = compare_variants({"A": a, "B": b}, 100.0)
        assert result.verdict == EQUIVALENT and result.at[1.0].ratio == 1.0


def test_a_level_is_reached_when_the_sign_test_says_so():
    from physgrad.claim_words import ABOVE, BELOW, against_level
    from physgrad.verdict import UNDECIDED

    assert against_level([1e-3] * 10, 1e-2)[0] == BELOW
    assert against_level([1e-3] * 9 + [1.0], 1e-2)[0] == BELOW  # 9 of 10: p = 0.021
    assert against_level([1e-3] * 8 + [1.0] * 2, 1e-2)[0] == UNDECIDED  # 8 of 10: p = 0.11
    assert against_level([1.0] * 9 + [1e-3], 1e-2)[0] == ABOVE
    # a diverged seed is above; a missing one is left out and counted
    verdict, why = against_level([math.inf] * 10, 1e-2)
    assert verdict == ABOVE and "0 of 10" in why
    verdict, why = against_level([1e-3] * 9 + [math.nan], 1e-2)
    assert verdict == BELOW and "9 of 9" in why and "1 missing" in why
    # at the level is not below it (a tie), and nothing known decides nothing
    assert against_level([1e-2] * 10, 1e-2)[0] == ABOVE
    assert against_level([math.nan] * 4, 1e-2)[0] == UNDECIDED
    assert against_level([1e-3] * 4, 1e-2)[0] == UNDECIDED  # 4 of 4: p = 0.125


def test_a_claim_is_contradicted_only_where_the_budget_could_test_it():
    from physgrad.claim_words import (
        CONTRADICTED,
        DIFFERENT_SETUP,
        NOT_SETTLED,
        NOT_TESTED,
        SEEDS_DISAGREE,
        STUDIES_DISAGREE,
        SUPPORTED,
        claim_word,
        left_start,
    )

    nan = math.nan
    # holds at X with every variant trained and no failure at X/2: supported
    assert claim_word(True, False, False, True, 0.01)[0] == SUPPORTED
    # holds at X but a variant never left its start (the cart's M at 1,500 iterations): the
    # budget could not test it
    word, why = claim_word(True, False, False, False, 0.047)
    assert word == NOT_TESTED and "holds at X, but a variant fell less than 2x" in why
    assert "4.7% of the paper's budget" in why
    # holds at X but failed at X/2: it turns with the budget
    word, why = claim_word(True, False, True, True, 0.5)
    assert word == NOT_TESTED and "turns with the budget" in why
    # fails at X and X/2 with every variant trained: contradicted, whatever the share
    assert claim_word(False, True, True, True, 0.02)[0] == CONTRADICTED
    assert claim_word(False, True, True, True, nan)[0] == CONTRADICTED
    # variants that have not left their start say nothing against the claim
    word, why = claim_word(False, True, True, False, 0.047)
    assert word == NOT_TESTED and "less than 2x" in why and "4.7% of the paper's budget" in why
    # turned between X/2 and X: not tested
    assert claim_word(False, True, False, True, 0.05)[0] == NOT_TESTED
    # at the paper's budget a failure is a contradiction, trained or not
    assert claim_word(False, True, False, False, 1.0)[0] == CONTRADICTED
    # not settled: by its cause where the parts found one, unless the variants have not left
    # their start below a budget the paper states: then the budget, the cause said beside it
    stuck = (SEEDS_DISAGREE, "adam: 32 of 40 seeds below 0.01, 8 stuck at or above it")
    assert claim_word(False, False, False, True, nan, cause=stuck) == stuck
    assert claim_word(False, False, False, True, 0.01, cause=stuck) == stuck
    assert claim_word(False, False, False, False, nan, cause=stuck) == stuck
    word, why = claim_word(False, False, False, False, 0.0047, cause=stuck)
    assert word == NOT_TESTED and "0.47% of the paper's budget" in why
    assert why.endswith(
        "; seeds disagree as well: adam: 32 of 40 seeds below 0.01, 8 stuck at or above it"
    )
    assert claim_word(False, False, False, False, 1.0, cause=stuck) == stuck
    apart = (STUDIES_DISAGREE, "a vs b in 4 tuning studies: A better, B better, ...")
    assert claim_word(False, False, False, True, 1.0, cause=apart) == apart
    # without one: the budget where a variant has not trained below the paper's, else the seeds
    assert claim_word(False, False, False, False, 0.1)[0] == NOT_TESTED
    assert claim_word(False, False, False, True, 1.0) == (
        NOT_SETTLED,
        "not settled at X: the seeds could not resolve it; 100% of the paper's budget",
    )
    assert claim_word(True, False, False, True, 0.1, "another network")[0] == DIFFERENT_SETUP
    # left its start: the median of final / start at most 1/2; diverged seeds count against
    assert left_start([1.0, 1.0, 1.0], [0.4, 0.5, 0.9])
    assert not left_start([1.0, 1.0, 1.0], [0.4, 0.6, 0.9])
    assert not left_start([1.0, 1.0, 1.0], [0.1, math.inf, math.inf])
    assert left_start([1.0, 1.0], [0.1, nan]) and not left_start([1.0], [nan])


def test_a_claims_word_names_the_budget_share_the_failing_parts_and_an_untrained_variant():
    """Every word's reason carries the share of the paper's budget where it states one (a
    "supported" at 0.42% says so); a "does not hold" names the parts that do not; where the paper
    states no budget, a variant that has not left its start is "not tested: a variant did not leave
    its start", since there is no paper's budget to fall short of."""
    from physgrad.claim_words import CONTRADICTED, NOT_TESTED, SUPPORTED, UNTRAINED, claim_word

    nan = math.nan
    word, why = claim_word(True, False, False, True, 0.0042)
    assert word == SUPPORTED and why.endswith("; 0.42% of the paper's budget")
    assert claim_word(True, False, False, True, nan) == (
        SUPPORTED,
        "holds at X, every variant having left its start",
    )
    word, why = claim_word(False, True, True, True, nan, failing="g saturates: does not hold")
    assert word == CONTRADICTED and why.endswith("(g saturates: does not hold)")
    for holds, fails in ((True, False), (False, True), (False, False)):
        assert claim_word(holds, fails, fails, False, nan)[0] == UNTRAINED
        assert claim_word(holds, fails, fails, False, 0.1)[0] == NOT_TESTED
    word, why = claim_word(False, True, True, False, nan, failing="hig below adam: does not hold")
    assert "less than 2x" in why and "(hig below adam: does not hold)" in why
