"""Unit layer of the verdict over repeated tuning studies (physgrad.replication), the power it
states (physgrad.power) and the divergence flag: synthetic study medians and seeds with known
answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from physgrad.power import detectable_ratio, power_at, wrong_side_allowed
from physgrad.readout import Curve
from physgrad.replication import (
    STUDY_ALPHA,
    STUDY_CAP,
    across_studies,
    between_studies,
    over_studies,
)
from physgrad.verdict import (
    A_BETTER,
    LOG_CAP,
    UNDECIDED,
    compare_variants,
    divergence_flag,
    paired,
)


def test_between_studies_is_the_one_sample_t_interval_of_the_study_medians():
    """Equal weights: Hartung-Knapp's interval is the t interval of the studies' medians, its p
    scipy's one-sample t test."""
    medians = [-1.0, -1.2, -0.8, -1.1]
    draws = between_studies(medians, alpha=0.05)
    expected = stats.ttest_1samp(medians, 0.0)
    assert draws.mean == pytest.approx(np.mean(medians))
    assert draws.p == pytest.approx(expected.pvalue)
    low, high = expected.confidence_interval(0.95)
    assert (draws.low, draws.high) == pytest.approx((low, high))


def test_between_studies_clips_divergences_and_huge_ratios_and_leaves_out_missing_medians():
    """A study median of -LOG_CAP (B diverged on most seeds) or of a 1000x ratio counts as a ratio
    of 10 (STUDY_CAP); a study without a median (NaN) is left out; equal medians give p 0."""
    draws = between_studies([-LOG_CAP, -math.log(1000.0), -2.0, math.nan])
    assert draws.estimates == pytest.approx((-STUDY_CAP, -STUDY_CAP, -2.0))
    assert draws.studies == 3
    same = between_studies([-0.5] * 4)
    assert same.p == 0.0 and same.low == same.high == -0.5
    assert between_studies([0.0] * 4).p == 1.0
    assert between_studies([-0.5]).p == 1.0  # one study is no draw of the spread


@pytest.mark.parametrize(
    "medians, verdict, why",
    [
        # three studies 2x and one at 1: the studies as draws do not exclude 1 at 0.01
        ([-0.7, -0.7, -0.7, -0.02], UNDECIDED, "taken as draws"),
        ([-0.7, -0.6, -0.75, -0.65], A_BETTER, "over the studies"),
        # a study whose median is a divergence counts as the cap, not against
        ([-LOG_CAP, -2.2, -2.0, -2.3], A_BETTER, "over the studies"),
        ([-0.7, -0.6, -0.7, 0.05], UNDECIDED, "study 4's median ratio is not on that side"),
        # a study without a median neither counts for nor against
        ([-0.7, -0.6, -0.7, math.nan], A_BETTER, "over the studies"),
    ],
)
def test_a_better_over_studies_needs_the_studies_as_draws_to_agree(medians, verdict, why):
    found = [A_BETTER, A_BETTER, A_BETTER, UNDECIDED]
    got, reason = over_studies(found, medians=medians)
    assert got == verdict and why in reason, reason
    assert "study 4's median ratio is not" not in reason or medians[3] > 0


def test_the_rule_before_the_test_between_studies_is_kept_for_comparison():
    """study_alpha=None: the majority, none against, every median on its side, no test between
    studies (what experiments/study_luck.py calls "before")."""
    per_study = [compare_variants(curves(-0.7, k), 1.0) for k in range(3)]
    per_study.append(compare_variants(curves(-0.1, 3, noise=0.3), 1.0))
    assert per_study[3][0].verdict == UNDECIDED and per_study[3][0].at[1.0].median < 0
    assert across_studies(per_study, study_alpha=None)[0].verdict == A_BETTER
    (combined,) = across_studies(per_study)
    assert combined.verdict == UNDECIDED and "taken as draws" in combined.verdicts[1.0][1]


def curves(
    log_ratio: float, study: int, negative: int = 0, diverged_a: int = 0, noise: float = 0.01
) -> dict:
    """Ten paired seeds whose log ratios A/B are log_ratio plus a little noise; the first
    `negative` of A's losses below 0, the last `diverged_a` of A's runs diverged."""
    rng = np.random.default_rng(study)
    a, b = {}, {}
    for s in range(10):
        loss = math.exp(log_ratio + rng.normal(0, noise))
        if s < negative:
            loss = -loss
        diverged = s >= 10 - diverged_a
        a[s] = Curve(np.array([1.0]), np.array([math.inf if diverged else loss]), math.inf)
        b[s] = Curve(np.array([1.0]), np.array([1.0]), math.inf)
    return {"A": a, "B": b}


def test_the_combined_row_counts_every_left_out_seed():
    """Negative losses on 9 of 10 seeds of one study leave that study undecided and its seeds out
    of the ratios, but the combined row counts them (negative = 9), so they do not disappear."""
    per_study = [compare_variants(curves(-0.7, k, negative=9 * (k == 3)), 1.0) for k in range(4)]
    (combined,) = across_studies(per_study)
    p = combined.at[1.0]
    assert p.negative == 9 and p.pairs == 31 and p.seeds == 40


def test_divergence_is_flagged_as_its_own_endpoint():
    """24 of 40 against none (Fisher p 8e-10): flagged beside whatever the loss verdict is; 1
    against 0 is not."""
    a = [math.inf] * 24 + [1.0] * 16
    b = [1.0] * 40
    flag = divergence_flag(paired(a, b), "rule", "adam")
    assert flag.startswith("rule diverged on 24 of 40 seeds, adam on 0")
    assert "(Fisher p = 7.7e-10)" in flag
    assert divergence_flag(paired([math.inf] + [1.0] * 9, [1.0] * 10)) == ""


def test_wrong_side_allowed_is_what_the_rule_itself_still_calls_better():
    """With `allowed` pairs where the better variant diverged (the rest 10x lower), a study of n
    seeds still calls it better by compare_variants; with one more it cannot."""
    for n in (10, 16, 20):
        allowed = wrong_side_allowed(n)
        for wrong, expected in ((allowed, A_BETTER), (allowed + 1, UNDECIDED)):
            a = [math.inf] * wrong + [0.1 * (1 + 0.01 * s) for s in range(n - wrong)]
            found = compare_variants(
                {
                    "A": {s: Curve(np.array([1.0]), np.array([a[s]]), math.inf) for s in range(n)},
                    "B": {s: Curve(np.array([1.0]), np.array([1.0]), math.inf) for s in range(n)},
                },
                1.0,
                fractions=(1.0,),
            )[0].verdict
            assert found == expected, (n, wrong)


def test_the_stated_power_counts_divergences_and_the_studies_spread():
    """At spread 0.3, 10 seeds, 4 studies: divergences at 20% per run make 2x nearly unreachable
    (the better variant diverging on one seed of ten already keeps a study from calling it
    better), the studies' own spread raises the detectable ratio, and zero spread states the
    margin itself ("any ratio above it")."""
    plain = detectable_ratio(0.3, 10, 1, 4)
    assert 1.3 < plain < 1.8
    assert detectable_ratio(0.3, 10, 1, 4, between=0.3) > plain
    assert detectable_ratio(0.3, 10, 1, 4, divergence=0.2) == math.inf
    assert power_at(2.0, 0.3, 10, 1, 4, divergence=0.2) < 0.05
    assert detectable_ratio(0.0, 10, 1, 4) == 1.1
    assert power_at(1.1, 0.0, 10, 1, 4) == 0.0  # the margin itself is never "better"
    assert STUDY_ALPHA == 0.01


@pytest.mark.parametrize("tau", [0.0, 0.5, 1.0])
def test_the_test_between_studies_keeps_its_level_whatever_the_tuning_luck(tau):
    """Four study medians, each the pair's seed noise (sd 0.12: a median of 10 seeds at spread 0.3)
    plus the study's tuning offset (sd tau), no true difference: p < 0.01 in about 1% of 10,000
    draws (binomial 99.9% bounds), however large tau; the offsets only widen the interval."""
    rng = np.random.default_rng(int(10 * tau))
    hits = sum(
        between_studies(rng.normal(0, 0.12, 4) + rng.normal(0, tau, 4)).p < 0.01
        for _ in range(10_000)
    )
    assert 65 <= hits <= 140, hits  # 1% of 10,000 is 100; clipping at 10x only lowers it
