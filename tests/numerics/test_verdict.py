"""Numerics layer of the verdict rule (physgrad.verdict): the budget's edge, blow-ups and log ratios
of diverged, zero and negative losses, the signed-rank p-value against scipy, Holm's correction by
hand, and the error rates and power of the rule and of the trend rule on simulated studies."""

import math

import numpy as np
import pytest

from physgrad.readout import Curve, target_loss
from physgrad.replication import across_studies
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    EQUIVALENT,
    LOG_CAP,
    compare_variants,
    decide,
    divergence_test,
    holm,
    log_ratio,
    paired,
)
from tests.unit.test_verdict import (
    SEEDS,
    flat_curves,
)


def test_the_step_that_crosses_a_time_budget_counts_against_its_variant():
    """An evaluation after the budget (the run's step crossed it) is not read at the budget."""
    slow = Curve(np.array([0.0, 60.0, 130.0]), np.array([1.0, 0.5, 0.01]), math.inf)
    assert slow.at(100.0) == 0.5
    assert slow.at(130.0) == 0.01


def test_a_blow_up_without_nan_counts_as_diverged():
    """HIG on a heat equation: held-out loss 1.0 -> 3.2e5 in two evaluations, never NaN."""
    curve = Curve(np.array([0, 10, 20, 30.0]), np.array([1.0, 0.5, 3.2e5, 3.0e5]), 30.0)
    assert curve.at(10) == 0.5 and curve.at(20) == math.inf and curve.at(30) == math.inf
    assert Curve(curve.x, curve.loss, 30.0, divergence_factor=None).at(30) == 3.0e5
    assert Curve(np.array([0, 5.0]), np.array([1.0, 0.5]), 5.0, diverged=True).at(10) == math.inf


def test_no_median_or_interval_end_is_a_blend_of_a_divergence_and_a_finite_ratio():
    """300 random sets of 6 to 12 pairs with losses spread over 12 decades, divergences on either
    side and on both, ties and losses of 0: the median and both interval ends are the divergence
    (+-LOG_CAP) or lie within the finite log ratios of the pairs, and every reported ratio is 0,
    infinite or within their range (never e^+-300 from a diverged pair averaged or interpolated
    with a finite one); the same for the pooled median over tuning studies."""
    from physgrad.verdict import ratio_of

    rng = np.random.default_rng(7)

    def draw(n):
        a, b = 10.0 ** rng.uniform(-6, 6, n), 10.0 ** rng.uniform(-6, 6, n)
        for losses in (a, b):
            losses[rng.random(n) < rng.uniform(0, 0.5)] = math.inf
            losses[rng.random(n) < 0.05] = 0.0
        tied = rng.random(n) < 0.1
        b[tied] = a[tied]
        return a, b

    def within(value, ratios):
        finite = np.abs([r for r in ratios if abs(r) < LOG_CAP])
        bound = finite.max() if finite.size else 0.0
        return math.isnan(value) or abs(value) == LOG_CAP or abs(value) <= bound + 1e-12

    for case in range(300):
        n = int(rng.integers(6, 13))
        a, b = draw(n)
        p = paired(list(a), list(b), seed=case)
        ratios = [r for r in p.log_ratios if not math.isnan(r)]
        for value in (p.median, p.low, p.high):
            assert within(value, ratios), (case, value, ratios)
            shown = ratio_of(value)
            # a finite loss against another spans at most 12 decades; a loss of 0 counts as
            # LOSS_FLOOR (2.2e-308), so a pair with one reaches its ratio, never 0 or inf
            assert math.isnan(shown) or shown in (0.0, math.inf) or 1e-320 < shown < 1e320
            if abs(value) == LOG_CAP:
                assert shown in (0.0, math.inf)
    # the regime map's case: HIG missed the target in 2 of 6 seeds; the interval's upper end had
    # read e^498.8 (3.2e216), the average of a missed seed's LOG_CAP and a finite ratio
    p = paired([0.1] * 3 + [math.inf] * 2 + [0.2], [1.0] * 6)
    assert p.high == LOG_CAP and p.low == pytest.approx(math.log(0.1))
    assert p.median == pytest.approx((math.log(0.1) + math.log(0.2)) / 2)
    studies = []
    for _ in range(3):
        a, b = draw(10)
        curves = {
            name: {
                s: Curve(np.array([0.0]), np.array([v]), 1.0, False, None) for s, v in enumerate(x)
            }
            for name, x in (("A", a), ("B", b))
        }
        studies.append(compare_variants(curves, 1.0))
    (pooled,) = across_studies(studies)
    assert within(pooled.at[1.0].median, pooled.at[1.0].log_ratios)


def test_the_lowest_and_highest_median_targets():
    """The lowest median is the best group's typical loss, the highest the worst finite one; a group
    diverged in most runs has no finite median and sets neither; NaN (missing) losses are left out;
    none finite: NaN."""
    from physgrad.readout import highest_median, lowest_median

    losses = {"A": [0.1, 0.2, 0.3, math.nan], "B": [0.4, 0.5, 0.6], "C": [math.inf, math.inf, 0.01]}
    assert lowest_median(losses) == ("A", pytest.approx(0.2))
    assert highest_median(losses) == ("B", pytest.approx(0.5))
    # a tie: the first group
    assert highest_median({"A": [1.0, 2.0], "B": [2.0, 1.0]}) == (
        "A",
        1.5,
    )
    for rule in (lowest_median, highest_median):
        name, value = rule({"C": [math.inf, 1.0, math.inf], "D": [math.nan]})
        assert name == "" and math.isnan(value)


def test_log_ratios_of_diverged_zero_and_negative_losses():
    """Diverged: +-LOG_CAP (both: 0); a loss below float32's smallest normal number (0 included)
    counts as it, so 0 against 1e-30 is a ratio of 1.2e-8 (not 0, which reads as a divergence)
    and two losses below it tie;
    a negative loss has no ratio (NaN, the pair is left out and counted)."""
    from physgrad.verdict import LOSS_FLOOR

    assert log_ratio(math.inf, math.inf) == 0.0 and log_ratio(0.0, 0.0) == 0.0
    assert log_ratio(math.inf, 1.0) == LOG_CAP and log_ratio(1.0, math.inf) == -LOG_CAP
    assert log_ratio(0.0, 1e-30) == pytest.approx(math.log(LOSS_FLOOR / 1e-30))
    assert 1e-9 < math.exp(log_ratio(0.0, 1e-30)) < 1e-7
    assert log_ratio(1e-320, 1e-310) == 0.0 and log_ratio(0.0, 1e-39) == 0.0
    assert log_ratio(0.0, math.inf) == -LOG_CAP and math.isnan(log_ratio(math.nan, 1.0))
    assert math.isnan(log_ratio(-0.5, 1.0)) and math.isnan(log_ratio(1.0, -2.0))
    assert log_ratio(2.0, 1.0) == pytest.approx(math.log(2.0))


def test_holm_against_hand_computed_values():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert holm([0.5]) == [0.5]
    assert holm([0.9, 0.8]) == pytest.approx([1.0, 1.0])
    assert holm([0.001, 0.2, 0.01, 0.04]) == pytest.approx([0.004, 0.2, 0.03, 0.08])


def test_the_signed_rank_p_value_is_scipys_with_ties_zeros_and_divergences():
    """The vectorised exact sign-flip enumeration against scipy.stats.wilcoxon's own (zero_method
    'zsplit') on log ratios with ties, zeros and +-LOG_CAP, and without, up to 15 pairs (beyond 13
    scipy alone decides); and the closed form: n distinct positive ratios have P(W+ >= observed) =
    2^-n."""
    from scipy.stats import wilcoxon

    from physgrad.paired_stats import _wilcoxon

    rng = np.random.default_rng(5)
    for trial in range(
        12
    ):  # scipy's own enumeration is the slow one: ties at up to 9 pairs, 1 to 15 without
        r = (
            rng.choice(
                [-LOG_CAP, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, LOG_CAP], int(rng.integers(2, 10))
            )
            if trial % 2
            else rng.normal(0.3, 1.0, int(rng.integers(2, 16)))
        )
        if not np.any(r):
            continue
        for alternative in ("less", "greater"):
            assert _wilcoxon(r, alternative) == pytest.approx(
                wilcoxon(r, zero_method="zsplit", alternative=alternative).pvalue,
                rel=1e-12,
                abs=1e-15,
            ), (r, alternative)
    for n in (2, 5, 10, 13):
        assert _wilcoxon(np.arange(1.0, n + 1), "greater") == pytest.approx(2.0**-n, rel=1e-12)
        assert _wilcoxon(np.arange(1.0, n + 1), "less") == pytest.approx(1.0, rel=1e-12)


def test_error_rates_of_the_rule_under_the_null_and_under_a_known_effect():
    """Simulated studies of 10 paired seeds with log-normal seed and run noise: identical variants
    are called different in at most alpha of them; a variant 30 % better (run noise 10 %) is found
    in almost all."""
    rng = np.random.default_rng(5)
    false_calls, found = 0, 0
    trials = 200
    for _ in range(trials):
        base = np.exp(rng.normal(0, 1.0, 10))
        a_null = base * np.exp(rng.normal(0, 0.1, 10))
        p = paired(list(a_null), list(base * np.exp(rng.normal(0, 0.1, 10))))
        false_calls += decide(p, p.p_difference, p.p_equivalent)[0] in (A_BETTER, B_BETTER)
        a_better = 0.7 * base * np.exp(rng.normal(0, 0.1, 10))
        p = paired(list(a_better), list(base * np.exp(rng.normal(0, 0.1, 10))))
        found += decide(p, p.p_difference, p.p_equivalent)[0] == A_BETTER
    assert false_calls / trials <= 0.05
    assert found / trials >= 0.9


def test_divergence_counts_and_the_target():
    assert divergence_test(0, 10, 10, 10) < 1e-4 and divergence_test(3, 10, 3, 10) == pytest.approx(
        1.0
    )
    curves = {"A": flat_curves({s: 0.2 for s in SEEDS}), "B": flat_curves({s: 0.5 for s in SEEDS})}
    assert target_loss(curves, 100.0) == ("A", pytest.approx(0.2))
    assert curves["B"][0].reaches(0.2, 100.0) == math.inf
    assert curves["A"][0].reaches(0.2, 100.0) == pytest.approx(100.0)
    assert curves["A"][0].reaches(0.5, 100.0) == pytest.approx(70.0)


def test_the_trend_rule_under_the_null_calls_growth_rarely_and_finds_a_known_one():
    """200 simulated pairs of settings, 10 seeds each, seed noise 30% on the log ratio: no trend is
    called "grows" in at most alpha of them; a halving of A/B at the hard end is found in most."""
    from physgrad.trend import GROWS, interaction

    rng = np.random.default_rng(14)
    false_calls = found = 0
    for trial in range(200):
        false_calls += (
            interaction(rng.normal(-0.2, 0.3, 10), rng.normal(-0.2, 0.3, 10), seed=trial).verdict
            == GROWS
        )
        found += (
            interaction(
                rng.normal(-0.2, 0.3, 10), rng.normal(-0.2 - math.log(2), 0.3, 10), seed=trial
            ).verdict
            == GROWS
        )
    assert false_calls / 200 <= 0.05
    assert found / 200 >= 0.7


@pytest.mark.parametrize(
    "found, verdict, why",
    [
        (["A better"] * 3, "A better", "3 of 3 tuning studies"),
        (["A better", "undecided", "A better"], "A better", "2 of 3 tuning studies"),
        (["A better", "undecided", "undecided"], "undecided", "1 of 3 tuning studies decided, 2"),
        (["A better", "A better", "B better"], "undecided", "disagree"),
        (["A better", "A better", "equivalent"], "undecided", "disagree"),
        (["grows", "does not grow", "undecided"], "undecided", "disagree"),
        (["grows", "grows", "undecided"], "grows", "2 of 3"),
        (["B better"] * 2, "B better", "2 of 2"),
        (["B better", "undecided"], "undecided", "1 of 2 tuning studies decided, 2 needed"),
    ],
)
def test_one_verdict_over_tuning_studies_needs_a_majority_and_none_against(found, verdict, why):
    from physgrad.replication import over_studies

    got, reason = over_studies(found)
    assert got == verdict and why in reason, reason


# one spread in make test, a narrow and a wide one in make test-long
@pytest.mark.parametrize(
    "sd",
    [pytest.param(0.1, marks=pytest.mark.long), 0.3, pytest.param(1.0, marks=pytest.mark.long)],
)
def test_a_difference_of_the_detectable_ratio_is_found_about_four_times_in_five(sd):
    """physgrad.power.detectable_ratio against simulation: a true ratio at the detectable one,
    Gaussian log ratios of spread sd on 10 seeds, is called A better in 65-93% of 200 simulated
    comparisons (the promise is 80%; a normal approximation at 10 seeds); at half its log ratio,
    in fewer than half. And spread() reads sd back from normal log ratios."""
    from physgrad.power import detectable_ratio, spread

    rng = np.random.default_rng(3)
    ratio = detectable_ratio(sd, 10)

    def found(log_effect):
        hits, spreads = 0, []
        for _ in range(200):
            r = rng.normal(-log_effect, sd, 10)
            curves = {
                "A": {
                    s: Curve(np.array([1.0]), np.array([math.exp(r[s])]), math.inf) for s in SEEDS
                },
                "B": {s: Curve(np.array([1.0]), np.array([1.0]), math.inf) for s in SEEDS},
            }
            (result,) = compare_variants(curves, 1.0, fractions=(1.0,))
            hits += result.verdict == A_BETTER
            spreads.append(spread(result.at[1.0]))
        return hits / 200, float(np.median(spreads))

    rate, measured = found(math.log(ratio))
    assert 0.65 <= rate <= 0.93, (ratio, rate)
    assert measured == pytest.approx(sd, rel=0.25)
    assert found(math.log(ratio) / 2)[0] < 0.5
    assert detectable_ratio(sd, 5) == math.inf  # too few seeds for any verdict


def test_a_baseline_compares_each_variant_with_it_alone_and_holm_runs_over_those():
    """compare.baseline=B: the pairs (A, B) and (C, B), not (A, C); Holm's factor is 2, not 3.
    A is 10x lower than B on every seed, C equal to B: A better, C equivalent."""
    from physgrad.comparison.spec import study_settings

    seeds = range(10)
    rng = np.random.default_rng(0)
    noise = {s: math.exp(0.05 * rng.normal()) for s in seeds}
    level = {"A": 0.1, "B": 1.0, "C": 1.0}
    curves = {
        name: {
            s: Curve(np.array([1.0]), np.array([v * (noise[s] if name != "B" else 1.0)]), 1.0)
            for s in seeds
        }
        for name, v in level.items()
    }
    settings = study_settings({"baseline": "B"})
    assert settings.comparisons(3) == 2 and study_settings({}).comparisons(3) == 3
    results = compare_variants(curves, 1.0, pairs=settings.pairs(list(curves)), fractions=(1.0,))
    assert [(r.a, r.b) for r in results] == [("A", "B"), ("C", "B")]
    a, c = results
    assert a.verdict == A_BETTER and c.verdict == EQUIVALENT
    # A's is the smallest raw p-value: Holm's first step multiplies it by the comparisons, 2
    assert a.at[1.0].p_difference < c.at[1.0].p_difference
    assert a.p_difference[1.0] == pytest.approx(min(1.0, 2 * a.at[1.0].p_difference))
    # without a baseline, every pair: three comparisons, and A's p-value times 3
    every = compare_variants(curves, 1.0, fractions=(1.0,))
    assert [(r.a, r.b) for r in every] == [("A", "B"), ("A", "C"), ("B", "C")]
    assert every[0].p_difference[1.0] == pytest.approx(min(1.0, 3 * a.at[1.0].p_difference))
