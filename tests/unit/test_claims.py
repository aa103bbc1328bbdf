"""Unit layer of the claims (experiments/claims.py) on synthetic curves: close, trend, stall and
level parts, the regime map's time-to-target ratio, the presets' twins, decisions over tuning
studies, joining studies, runs tables read as data, and what a claim not run or not settled says."""

import math
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))

import claim_budget  # noqa: E402
import claims  # noqa: E402
import regime_map  # noqa: E402
import studies as study_lists  # noqa: E402
from claims import FAILS, HOLDS, OPEN  # noqa: E402

from physgrad.readout import Curve  # noqa: E402

X = np.arange(0, 1001, 100, dtype=float)

TEN = range(10)


def falling(final: float, start: float = 1.0, half: float | None = None) -> Curve:
    """A loss from start to final over 1000 iterations, at `half` at 500 (default: geometric in
    between)."""
    loss = start * (final / start) ** (X / X[-1])
    if half is not None:
        loss = np.interp(X, [0, 500, 1000], [start, half, final])
    return Curve(X, loss, X[-1])


class FakeStudy(claims.StudyRuns):
    """A study's runs as synthetic curves: variant -> seed -> Curve (column -> ... for other
    columns)."""

    def __init__(self, name, by_variant, columns=None, budget=1000.0):
        super().__init__(
            Path(name), "iteration", budget, {v: dict.fromkeys(by) for v, by in by_variant.items()}
        )
        self.by_variant, self.columns = by_variant, columns or {}

    def curves(self, variant, column="loss"):
        table = self.columns.get(column) or self.by_variant
        if variant not in table:  # another name of a variant (its runs under the same paths)
            variant = next(v for v in table if self.paths.get(v) is self.paths.get(variant))
        return table[variant]


def seeds_of(fn) -> dict:
    rng = np.random.default_rng(abs(hash(fn.__name__ if hasattr(fn, "__name__") else 0)) % 2**32)
    return {s: fn(s, rng) for s in TEN}


def base(s: int) -> float:
    return 0.1 * (1 + 0.3 * s)  # seeds differ a lot; the pairing removes it


def claim_of(*parts) -> claims.Claim:
    return claims.Claim("test", "a paper's claim", parts)


def test_close_holds_within_its_margin_and_fails_beyond_it(tmp_path, studies):
    rng = np.random.default_rng(3)
    studies["s"] = FakeStudy(
        "s",
        {
            "wig": {s: falling(base(s)) for s in TEN},
            "near": {s: falling(1.12 * base(s) * math.exp(rng.normal(0, 0.01))) for s in TEN},
            "far": {s: falling(1.6 * base(s)) for s in TEN},
        },
    )
    # 12% worse: not "lower", not equivalent within 10%, but within 25%
    assert claims.decide_claim(claim_of(claims.Lower("s", "near", "wig")), tmp_path)[0] == FAILS
    assert (
        claims.decide_claim(claim_of(claims.Close("s", "near", "wig", 1.25)), tmp_path)[0] == HOLDS
    )
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Close("s", "far", "wig", 1.25)), tmp_path
    )
    assert verdict == FAILS and "B better" in d.why


def test_a_trend_holds_only_where_the_advantage_grows(tmp_path, studies):
    """C/R 0.9 at the easy end and 0.3 at the hard end: grows; 0.3 at both ends (a uniform
    advantage, which the hard end alone would pass): does not hold."""
    rng = np.random.default_rng(4)

    def study(name, ratio):
        studies[name] = FakeStudy(
            name,
            {
                "C": {s: falling(ratio * base(s) * math.exp(rng.normal(0, 0.05))) for s in TEN},
                "R": {s: falling(base(s)) for s in TEN},
            },
        )

    study("easy", 0.9), study("hard", 0.3), study("easy_uniform", 0.3)
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Grows("easy", "hard", "C", "R")), tmp_path
    )
    assert verdict == HOLDS and "hard / easy = 0.3" in d.measured
    assert (
        claims.decide_claim(claim_of(claims.Grows("easy_uniform", "hard", "C", "R")), tmp_path)[0]
        == FAILS
    )
    assert (
        claims.decide_claim(
            claim_of(
                claims.Lower("hard", "C", "R"), claims.Grows("easy_uniform", "hard", "C", "R")
            ),
            tmp_path,
        )[0]
        == FAILS
    )
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Grows("missing", "hard", "C", "R")), tmp_path
    )
    assert verdict == OPEN and "missing has no finished study" in d.why


def test_stall_tells_a_stalled_variant_from_a_slow_and_an_unstable_one(tmp_path, studies):
    """Stalled: the error at the budget within 10% of the error at half of it; still falling 3x
    (Adam on the toy's second component): fails, as slow; rising above the start (Gauss-Newton):
    fails, as unstable."""
    rng = np.random.default_rng(5)
    noise = lambda: math.exp(rng.normal(0, 0.01))  # noqa: E731
    error = {
        "stalled": {s: falling(0.50 * base(s) * noise(), base(s), 0.5 * base(s)) for s in TEN},
        "slow": {s: falling(0.1 * base(s) * noise(), base(s), 0.3 * base(s)) for s in TEN},
        "unstable": {s: falling(3.0 * base(s) * noise(), base(s), 0.9 * base(s)) for s in TEN},
        "diverged": {s: Curve(X, np.where(X < 300, 1.0, np.inf), 300.0, True) for s in TEN},
    }
    studies["toy"] = FakeStudy("toy", error, columns={"error_second": error})
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Stalls("toy", "stalled", "error_second")), tmp_path
    )
    assert verdict == HOLDS and "equivalent" in d.why
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Stalls("toy", "slow", "error_second")), tmp_path
    )
    assert verdict == FAILS and "still falling" in d.why and "= 0.33" in d.measured
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Stalls("toy", "unstable", "error_second")), tmp_path
    )
    assert verdict == FAILS and "rising" in d.why and "start: 2.99" in d.measured
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Stalls("toy", "diverged", "error_second")), tmp_path
    )
    # not a tie of infinities
    assert verdict == FAILS and "rising" in d.why and "diverged in 10 of 10" in d.measured
    # half the seeds 30% up, half 30% down: undecided, said once (no empty label before the test's)
    error["mixed"] = {
        s: falling((0.65 if s % 2 else 0.35) * base(s) * noise(), base(s), 0.5 * base(s))
        for s in TEN
    }
    studies["toy"] = FakeStudy("toy", error, columns={"error_second": error})
    verdict, ((_, d),) = claims.decide_claim(
        claim_of(claims.Stalls("toy", "mixed", "error_second")), tmp_path
    )
    assert verdict == OPEN and d.why.startswith("undecided (") and ":  (" not in d.why, d.why


def test_a_claim_without_its_study_is_open_and_says_why(tmp_path, studies):
    verdict, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("nowhere", "a", "b")), tmp_path)
    assert verdict == OPEN and "no finished study" in d.why
    studies["s"] = FakeStudy(
        "s",
        {"a": {s: falling(0.5 * base(s)) for s in TEN}, "c": {s: falling(base(s)) for s in TEN}},
    )
    verdict, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert verdict == OPEN and d.verdict == claims.NOT_RUN and "no runs of b" in d.why
    # a part the study does not run (a presets' twin without the clipping variants) leaves the
    # verdict to the rest
    verdict, rows = claims.decide_claim(
        claim_of(claims.Lower("s", "a", "b"), claims.Lower("s", "a", "c")), tmp_path
    )
    assert verdict == HOLDS and [d.verdict for _, d in rows] == [claims.NOT_RUN, HOLDS]


def test_a_presets_twin_that_fixes_the_clipping_says_why_it_leaves_a_part_out(tmp_path, studies):
    """The StableBPTT twins run one clipping mode (none) only: the clipped parts say so,
    and the claim's presets' verdict speaks for the unclipped part."""
    study = study_lists.Study(
        "cartx",
        ("task=multicart", "optim.backprop=R,C", "optim.clip=none,value"),
        8,
        10,
        1,
        1,
        preset="optim.clip=none",
    )
    studies["cartx-preset"] = FakeStudy(
        "cartx-preset",
        {
            "backprop=C clip=none": {s: falling(0.5 * base(s)) for s in TEN},
            "backprop=R clip=none": {s: falling(base(s)) for s in TEN},
        },
    )
    claim = claim_of(
        claims.Lower("cartx", "backprop=C clip=none", "backprop=R clip=none"),
        claims.Lower("cartx", "backprop=C clip=value", "backprop=R clip=value"),
    )
    verdict, rows = claims.decide_claim(claim, tmp_path, "-preset", profile=(study,))
    assert verdict == HOLDS and [d.verdict for _, d in rows] == [HOLDS, claims.NOT_RUN]
    assert rows[1][1].why == (
        "the presets' twin runs optim.clip=none only "
        "(to save time; the tuned study runs the others)"
    )


def test_a_presets_only_study_at_the_papers_budget_decides_the_claim_alone(tmp_path, studies):
    """A study of the claims-paper profile evaluates the presets untuned in its own folder, with
    no twin, costs its evaluation only, and decides the claim's unclipped part under the tuned
    study's variant names; the clipped part says the presets run optim.clip=none only."""
    study = next(s for s in study_lists.PROFILES["claims-paper"] if s.name == "cart_4")
    command = study.command(tmp_path)
    assert not study.twin and study_lists.slices(study) == [study]
    assert "compare.tune=false" in command and f"compare.dir={tmp_path / 'cart_4'}" in command
    assert "compare.studies=1" in command and "trainer.iterations=32000" in command
    assert study.seconds() == pytest.approx(study.eval_jobs() * study.eval_seconds)
    studies["cart_4"] = FakeStudy(
        "cart_4",
        {
            "backprop=C": {s: falling(0.5 * base(s)) for s in TEN},
            "backprop=R": {s: falling(base(s)) for s in TEN},
        },
    )
    claim = claim_of(
        claims.Lower("cart_4", "backprop=C clip=none", "backprop=R clip=none"),
        claims.Lower("cart_4", "backprop=C clip=value", "backprop=R clip=value"),
    )
    paper = study_lists.PROFILES["claims-paper"]
    verdict, rows = claims.decide_claim(claim, tmp_path, profile=paper)
    assert verdict == HOLDS and [d.verdict for _, d in rows] == [HOLDS, claims.NOT_RUN]
    assert "runs optim.clip=none only" in rows[1][1].why


def test_the_regime_map_cell_is_the_time_to_target_ratio(tmp_path, studies, monkeypatch):
    """HIG reaches the target (the lower median loss at the budget) at 200 iterations in every seed,
    Adam at 800: ratio 0.25; a seed where Adam never reaches it counts as infinite."""
    x = X

    def reaching(at, final):
        return Curve(x, np.where(x < at, 1.0, final), x[-1])

    study = study_lists.Study(
        "map_toy_0.01_b16",
        ("task=toy", "optim=adam,hig", "task.scale=0.01"),
        2,
        10,
        1,
        1,
        preset=False,
    )
    studies[study.name] = FakeStudy(
        study.name,
        {
            "hig": {s: reaching(200, 0.1) for s in TEN},
            "adam": {s: reaching(800 if s else 2000, 0.1) for s in TEN},
        },
    )
    (tmp_path / study.name).mkdir()
    (tmp_path / study.name / "calibration.json").write_text(
        '{"costs": {"hig": {"step_seconds": 0.03}, "adam": {"step_seconds": 0.01}}}'
    )
    cell = regime_map.map_cell(tmp_path, study)
    assert (
        cell.ratio == pytest.approx(0.25)
        and cell.reached == (10, 9, 10)
        and cell.verdict == "A better"
    )
    assert cell.cost_ratio == pytest.approx(3.0) and cell.conditioning == 0.01
    monkeypatch.setattr(regime_map, "MAP", (study,))
    text = regime_map.regime_map(tmp_path, tmp_path)
    assert "| map_toy_0.01_b16 | 0.01 | 3 | 0.25 [" in text
    assert (tmp_path / "payoff.png").stat().st_size > 10_000


def test_the_regime_map_target_is_what_the_slower_variant_typically_reaches(tmp_path, studies):
    """HIG falls from 1 to 0.05, Adam to 0.2 (x 1 + 0.05 seed; geometric in iterations): the target
    is Adam's median at the budget (0.245), which HIG passes at 500 iterations in every seed and
    Adam only at 1000 in the 5 seeds that end below it. The lower median (HIG's, compare's target)
    would leave 5 pairs ties of two misses; here every pair is a HIG win: ratio 0.5 in 5 seeds and 0
    (Adam never there) in 5, median 0, HIG first."""
    study = study_lists.Study(
        "map_oscillator_1",
        ("task=oscillator", "optim=adam,hig", "task.alpha=1"),
        2,
        10,
        1,
        1,
        preset=False,
    )
    studies[study.name] = FakeStudy(
        study.name,
        {
            "hig": {s: falling(0.05 * (1 + 0.05 * s)) for s in TEN},
            "adam": {s: falling(0.2 * (1 + 0.05 * s)) for s in TEN},
        },
    )
    cell = regime_map.map_cell(tmp_path, study)
    assert cell.reached == (10, 5, 10) and cell.ratio == 0.0 and cell.high == pytest.approx(0.5)
    assert cell.verdict == "A better" and regime_map.MAP_VERDICTS[cell.verdict] == "HIG first"
    # no calibration file: no cost, no crash
    assert math.isnan(cell.cost_ratio) and cell.conditioning == 1.0
    # Adam diverged in most seeds: its median is not finite, the target is HIG's own median, reached
    # by HIG in half its seeds and by Adam never: HIG first where it got there, ties elsewhere
    studies[study.name] = FakeStudy(
        study.name,
        {
            "hig": {s: falling(0.05 * (1 + 0.05 * s)) for s in TEN},
            "adam": {s: Curve(X, np.where(X < 300, 1.0, np.inf), X[-1], True, None) for s in TEN},
        },
    )
    cell = regime_map.map_cell(tmp_path, study)
    assert cell.reached[:2] == (5, 0) and cell.verdict == "undecided"
    # both diverged everywhere: no target, nobody reaches it, all ties
    studies[study.name] = FakeStudy(
        study.name,
        {
            v: {s: Curve(X, np.where(X < 300, 1.0, np.inf), X[-1], True, None) for s in TEN}
            for v in ("hig", "adam")
        },
    )
    cell = regime_map.map_cell(tmp_path, study)
    assert (
        cell.reached == (0, 0, 10)
        and cell.verdict == regime_map.NO_TARGET
        and math.isnan(cell.ratio)
    )
    # a blank cell, drawn
    regime_map.plot_map({"oscillators": [cell]}, tmp_path / "payoff.png", "a machine")
    assert (tmp_path / "payoff.png").stat().st_size > 10_000


def test_a_study_without_a_presets_twin_says_so_for_the_presets(tmp_path, studies):
    """The claims profile runs every study's presets' twin; the longer profiles run none."""
    studies["quantum_control_5"] = FakeStudy(
        "quantum_control_5",
        {
            "backprop=C": {s: falling(0.5 * base(s)) for s in TEN},
            "backprop=R": {s: falling(base(s)) for s in TEN},
        },
    )
    claim = claim_of(claims.Lower("quantum_control_5", "backprop=C", "backprop=R"))
    assert all(s.preset for s in study_lists.STUDIES)
    assert not any(s.preset for s in study_lists.LONG + study_lists.GPU)
    assert claims.decide_claim(claim, tmp_path, profile=study_lists.LONG)[0] == HOLDS
    verdict, ((_, d),) = claims.decide_claim(claim, tmp_path, "-preset", profile=study_lists.LONG)
    assert verdict == claims.NOT_RUN and "no presets' twin" in d.why


def test_a_studys_runs_table_is_data_its_paths_stay_in_the_study_folder(tmp_path):
    """runs.csv names each run's file; the claims read it from the study's own eval/ whatever the
    table says (an absolute path elsewhere, a path through ..), and a row they cannot read so (a
    seed or budget that is no number, a path without eval/, a link out of eval/) is one line."""
    from physgrad.errors import UserError

    read_study = claims.read_study

    study = tmp_path / "study"
    (study / "eval" / "+compare_job=eval_v0" / "seed=0").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    header = "variant,study,seed,axis,budget,path\n"

    def table(*rows: str) -> None:
        (study / "runs.csv").write_text(header + "".join(f"{row}\n" for row in rows))

    table("adam,0,0,iteration,30,/anywhere/eval/+compare_job=eval_v0/seed=0/results.h5")
    found = read_study(study)
    assert found.paths == {
        "adam": {0: str(study / "eval" / "+compare_job=eval_v0" / "seed=0" / "results.h5")}
    }
    (study / "eval" / "out").symlink_to(tmp_path / "elsewhere")
    for row, why in (
        ("adam,0,abc,iteration,30,eval/x/results.h5", "not a run of this study"),
        ("adam,0,0,iteration,30,/etc/passwd", "not a run of this study"),
        ("adam,0,0,iteration,30,eval/../../elsewhere/results.h5", "leaves"),
        ("adam,0,0,iteration,30,eval/out/results.h5", "leaves"),
        ("adam,0,0,iteration,x,eval/x/results.h5", "is not a number"),
        ("adam,0,²,iteration,30,eval/x/results.h5", "not a run of this study"),
        (f"adam,0,{'9' * 5000},iteration,30,eval/x/results.h5", "not a run of this study"),
    ):
        table(row)
        with pytest.raises(UserError, match=why):
            read_study(study)
    # repeated tuning studies: each study's runs, and a bad row named by its line in the table
    table(
        "adam,0,0,iteration,30,eval/+compare_job=eval_v0/seed=0/results.h5",
        "adam,1,0,iteration,30,eval/+compare_job=eval_st1_v0/seed=0/results.h5",
        "adam,1,1,iteration,30,eval/../../elsewhere/results.h5",
    )
    with pytest.raises(UserError, match="line 4: its path leaves"):
        read_study(study)
    table(
        "adam,0,0,iteration,30,eval/+compare_job=eval_v0/seed=0/results.h5",
        "adam,1,0,iteration,30,eval/+compare_job=eval_st1_v0/seed=0/results.h5",
        "adam,2,0,iteration,30,eval/+compare_job=eval_st2_v0/seed=0/results.h5",
    )
    found = read_study(study)
    assert len(found.tuning) == 3 and found.paths == found.tuning[0].paths
    assert found.tuning[2].paths["adam"][0].endswith("eval_st2_v0/seed=0/results.h5")
    # a runs.csv that is no table: one line
    for content in (b"", b"\x00\xff\xfe" * 100, b'"unclosed\n'):
        (study / "runs.csv").write_bytes(content)
        with pytest.raises(UserError, match="not a table of runs") as refused:
            read_study(study)
        assert "\n" not in str(refused.value)
    # an eval/ that is itself a link: every path through it would resolve "inside" it
    table("adam,0,0,iteration,30,eval/+compare_job=eval_v0/seed=0/results.h5")
    (study / "eval").rename(tmp_path / "their eval")
    (study / "eval").symlink_to(tmp_path / "their eval")
    with pytest.raises(UserError, match="eval: a link: refused"):
        read_study(study)


def tuned(name: str, a_over_b: list[float]) -> FakeStudy:
    """A study of three tuning studies; in study k, a's loss is a_over_b[k] times b's (every
    seed, with the seeds' spread); 1.0: the two within noise of each other."""
    rng = np.random.default_rng(7)
    studies = []
    for k, factor in enumerate(a_over_b):
        noise = rng.normal(0, 0.3, 10) if factor == 1.0 else np.zeros(10)
        studies.append(
            FakeStudy(
                f"{name}-{k}",
                {
                    "a": {s: falling(factor * base(s) * np.exp(noise[s])) for s in TEN},
                    "b": {s: falling(base(s)) for s in TEN},
                },
            )
        )
    first = studies[0]
    first.tuning = tuple(studies)
    return first


@pytest.mark.parametrize(
    "factors, verdict",
    [
        # 2 of 3 studies, none against, but the third's median at 1: taken as draws, the three
        # studies do not exclude a ratio of 1 (tuning luck could make it)
        ([0.5, 0.5, 1.0], OPEN),
        ([0.5, 0.5, 0.6], HOLDS),
        ([0.5, 0.5, 0.5], HOLDS),
        ([0.5, 1.0, 1.0], OPEN),  # 1 of 3
        ([0.5, 2.0, 0.5], OPEN),  # the studies disagree
        ([2.0, 2.0, 1.0], FAILS),
    ],
)
def test_a_lower_part_is_decided_over_the_tuning_studies(tmp_path, studies, factors, verdict):
    """With repeated tuning studies a Lower part holds where A is better in a majority of the
    studies and in none is it worse, by the package's rule (physgrad.replication.across_studies)."""
    studies["s"] = tuned("s", factors)
    found, ((_, decision),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == verdict, decision
    assert "over 3 tuning studies" in decision.measured


@pytest.mark.parametrize(
    "factors, planned, verdict",
    [
        ([0.5, 0.5], 0, HOLDS),  # two studies, the two it has: both
        ([0.5, 0.5], 4, OPEN),  # two of four run: a majority of four is three
        ([0.5, 0.5, 0.5], 4, HOLDS),
        ([0.5], 4, OPEN),
        ([2.0, 2.0, 2.0], 4, FAILS),
    ],
)
def test_a_study_with_tuning_studies_still_to_run_needs_a_majority_of_those_planned(
    tmp_path, studies, factors, planned, verdict
):
    """A study whose tuning studies run one compare each (on any machine) is decided over the
    studies kept so far, by a majority of all it is to have: two of four agreeing do not settle a
    part, the why says how many ran, and an unsettled part's cause is the studies still to run
    (not what the seeds of those run show)."""
    from physgrad.claim_words import STUDIES_TO_RUN

    first = tuned("s", factors)
    for study in first.tuning or (first,):
        study.planned = planned
    studies["s"] = first
    found, ((_, decision),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == verdict, decision
    if planned > len(factors):
        assert f"({len(factors)} of {planned} tuning studies run)" in decision.why
    if found == OPEN:
        assert decision.cause == (STUDIES_TO_RUN, f"{len(factors)} of {planned} tuning studies run")
    else:
        assert decision.cause == ("", "")


def test_a_level_part_with_tuning_studies_still_to_run_says_so_before_stuck_seeds(
    tmp_path, studies
):
    """Stuck seeds in the one tuning study run of four: the cause is the studies still to run;
    with all four run, the stuck seeds."""
    from physgrad.claim_words import SEEDS_DISAGREE, STUDIES_TO_RUN

    finals = [1e-3] * 8 + [0.45, 0.45]
    for count, planned, cause in ((1, 4, STUDIES_TO_RUN), (4, 4, SEEDS_DISAGREE)):
        study = three_studies(
            "toy_1",
            [{"adam": {s: falling(v, 1.0, 2 * v) for s, v in zip(TEN, finals)}}] * count,
        )
        for each in study.tuning or (study,):
            each.planned = planned
        studies["toy_1"] = study
        found, ((_, d),) = claims.decide_claim(
            claim_of(claims.Reaches("toy_1", "adam", 1e-2)), tmp_path
        )
        assert found == claims.OPEN and d.cause[0] == cause, d


def poisson_row_with_the_gpu_holding(tmp_path, studies) -> str:
    """The headline's Poisson row where claims-gpu's study has HIG at half Adam's loss."""
    studies[str(tmp_path / "claims-gpu" / "poisson_continue")] = FakeStudy(
        "poisson_continue",
        {
            "hig": {s: falling(0.5 * base(s)) for s in TEN},
            "adam": {s: falling(base(s)) for s in TEN},
        },
    )
    further = (
        (tmp_path / "claims-long", study_lists.LONG),
        (tmp_path / "claims-gpu", study_lists.GPU),
    )
    table = claims.headline_table(tmp_path, study_lists.PROFILES["claims"], further)
    return next(line for line in table.splitlines() if "Poisson" in line)


def test_a_turn_that_comes_with_the_gpu_profile_is_told_apart(tmp_path, studies):
    """Poisson does not hold on 2 cores and holds in claims-gpu: the machine changed with the
    budget, so the row says so, not "reverses with the budget"."""
    studies["poisson_continue"] = FakeStudy(
        "poisson_continue",
        {
            "hig": {s: falling(2.0 * base(s)) for s in TEN},
            "adam": {s: falling(base(s)) for s in TEN},
        },
    )
    row = poisson_row_with_the_gpu_holding(tmp_path, studies)
    assert row.startswith("| **turns with a GPU's budget**: Poisson"), row
    assert "**does not hold**" in row and "claims-gpu" in row and "**holds**" in row


def test_a_claim_run_only_at_a_longer_budget_shows_that_budget_s_verdicts(tmp_path, studies):
    """A claim whose study of the claims profile has not run, but which a profile of longer budgets
    ran (here Poisson on the GPU), is "not run yet" for the claims profile, with the parts of the
    profiles that would run it and their hours, and gives the longer budget's verdicts beside it,
    not nothing."""
    row = poisson_row_with_the_gpu_holding(tmp_path, studies)
    assert row.startswith("| Poisson") and f"| {claims.NOT_YET}: decidable on 2 cores: " in row
    assert "needs a GPU: claims-gpu parts 1, 2, 3, 4, about " in row and " h on one GPU" in row
    assert row.count("|") == 11, row
    assert "claims-gpu" in row and "**holds**" in row, row
    alone = claims.headline_table(tmp_path, study_lists.PROFILES["claims"])
    assert next(x for x in alone.splitlines() if "Poisson" in x).endswith("| |")


def test_the_headline_states_what_a_study_ran_from_its_own_tables(tmp_path):
    """Trials per variant and tuning study from trials.csv, the tuning studies and seeds from
    runs.csv: what ran, not what the profile asked for."""
    study = tmp_path / "cart_4"
    rows = ["variant,study,seed,axis,budget,path"]
    trials = ["variant,study,trial,learning_rate,validation_loss,state"]
    for k in range(3):
        for variant in ("a", "b"):
            for seed in range(10):
                job = f"eval_st{k}_{variant}"
                (study / "eval" / job).mkdir(parents=True, exist_ok=True)
                rows.append(f"{variant},{k},{seed},iteration,1500,eval/{job}/results.h5")
            trials += [f"{variant},{k},{t},0.001,0.5,COMPLETE" for t in range(8)]
    (study / "runs.csv").write_text("\n".join(rows) + "\n")
    (study / "trials.csv").write_text("\n".join(trials) + "\n")
    assert claims.study_protocol(study) == (8, 3, 10)
    assert claims.study_protocol(tmp_path / "nothing") is None
    cart = next(c for c in claims.CLAIMS if c.name.startswith("cart"))
    runs = claims.read_study(study)
    assert claim_budget.share_text(cart, runs) == (
        "1500 iterations: 4.7% of the paper's 32,000 iterations"
    )
    oscillators = next(c for c in claims.CLAIMS if c.name.startswith("oscillators"))
    timed = replace(runs, axis="calibrated_time", budget=15.0)
    assert claim_budget.share_text(oscillators, timed) == (
        "15 s (calibrated clock): 0.42% of the paper's 3,600 s per method "
        "(its run scripts: 60 x 60 s)"
    )


def three_studies(name: str, per_study: list[dict]) -> FakeStudy:
    """A study of len(per_study) tuning studies, study k's runs per_study[k]."""
    found = [FakeStudy(f"{name}-{k}", by) for k, by in enumerate(per_study)]
    found[0].tuning = tuple(found)
    return found[0]


@pytest.mark.parametrize(
    "hard_ratios, verdict, why",
    [
        ([0.3, 0.3, 0.3], HOLDS, "3 of 3 tuning studies"),
        ([0.3, 0.3, 0.9 / 1.1], HOLDS, "2 of 3 tuning studies"),  # the third undecided
        ([0.3, 0.3, 1.2], OPEN, "disagree"),  # the third against: does not grow
        ([0.3, 0.9 / 1.1, 0.9 / 1.1], OPEN, "1 of 3 tuning studies decided"),
        ([1.2, 1.2, 1.2], FAILS, "3 of 3 tuning studies"),
    ],
)
def test_a_trend_is_decided_in_each_tuning_study_and_then_over_them(
    tmp_path, studies, hard_ratios, verdict, why
):
    """C/R 0.9 at the easy end in every study; at the hard end 0.3 (grows), 0.9/1.1 (lower by the
    margin itself: undecided) or 1.2 (higher: does not grow) per study. Over three studies
    by the package's rule: a majority, none against."""
    spread = np.linspace(-0.05, 0.05, 10)  # the seeds' scatter, the same in every study

    def runs(ratio):
        return {
            "C": {s: falling(ratio * base(s) * math.exp(spread[(3 * s) % 10])) for s in TEN},
            "R": {s: falling(base(s)) for s in TEN},
        }

    studies["easy"] = three_studies("easy", [runs(0.9) for _ in hard_ratios])
    studies["hard"] = three_studies("hard", [runs(r) for r in hard_ratios])
    found, ((_, d),) = claims.decide_claim(
        claim_of(claims.Grows("easy", "hard", "C", "R")), tmp_path
    )
    assert found == verdict and why in d.why, d
    assert "in 3 tuning studies" in d.measured


@pytest.mark.parametrize(
    "slopes, verdict",
    [
        (["stalled", "stalled", "stalled"], HOLDS),
        (["stalled", "stalled", "slow"], OPEN),  # one study still falling: against the majority
        (["slow", "slow", "slow"], FAILS),
    ],
)
def test_a_stall_is_decided_in_each_tuning_study_and_then_over_them(
    tmp_path, studies, slopes, verdict
):
    rng = np.random.default_rng(12)
    noise = lambda: math.exp(rng.normal(0, 0.01))  # noqa: E731
    shapes = {"stalled": (0.5, 0.5), "slow": (0.1, 0.3)}

    def runs(kind):
        final, half = shapes[kind]
        return {
            "adam": {s: falling(final * base(s) * noise(), base(s), half * base(s)) for s in TEN}
        }

    studies["toy"] = three_studies("toy", [runs(k) for k in slopes])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Stalls("toy", "adam")), tmp_path)
    assert found == verdict, d
    assert "in 3 tuning studies" in d.measured


def test_a_continuing_study_gets_a_start_network_for_every_tuning_seed(tmp_path):
    """A study that continues networks (init_from) tunes each tuning study on its own seed
    (compare's tune_seed + k): each tuning study (a compare of its own) gets a start network for
    its tuning seed and its evaluation seeds, the presets' twin for its, and the plan costs
    them."""
    from physgrad.comparison import split_overrides, study_settings

    study = next(s for s in study_lists.STUDIES if s.name == "poisson_continue")

    def needs(command):
        settings = study_settings(split_overrides(command)[0])
        tuning = {settings.tune_seed + k for k in range(settings.study_count)}
        return tuning | set(settings.evaluation_seeds)

    assert set(study.start_seeds()) == needs(study.command(tmp_path))
    for piece in study_lists.slices(study):
        assert set(piece.start_seeds()) == needs(piece.command(tmp_path))
        assert len(piece.start_seeds()) == study.seeds + 1
    assert set(study.start_seeds(preset=True)) == needs(study.command(tmp_path, preset=True))
    starts = study.start.job_seconds * len(study.start_seeds())
    # the start networks' cost apart (without them the seeds would train together: another plan)
    whole_without_start = replace(study, start=replace(study.start, job_seconds=0.0)).seconds()
    assert study.seconds() - whole_without_start == pytest.approx(starts)


@pytest.mark.parametrize(
    "finals, verdict",
    [
        ([[1e-3] * 10] * 3, HOLDS),
        # one study undecided (7 of 10): a majority of 2, none against
        ([[1e-3] * 10, [1e-3] * 10, [1e-3] * 7 + [1.0] * 3], HOLDS),
        ([[1e-3] * 10, [1e-3] * 7 + [1.0] * 3, [1e-3] * 7 + [1.0] * 3], OPEN),
        ([[0.2] * 10] * 3, FAILS),
        ([[1e-3] * 10, [1e-3] * 10, [0.2] * 10], OPEN),  # one study against
    ],
)
def test_a_level_is_reached_by_the_sign_test_in_each_tuning_study(
    tmp_path, studies, finals, verdict
):
    """ "All three reach 1e-2" (the book's toy at lambda = 1): the seeds below the level by the
    package's sign test, in each of three tuning studies, then the majority with none against."""
    studies["toy_1"] = three_studies(
        "toy_1",
        [{"hig": {s: falling(v, 1.0, 2 * v) for s, v in zip(TEN, values)}} for values in finals],
    )
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Reaches("toy_1", "hig", 1e-2)), tmp_path)
    assert found == verdict, d
    assert "in 3 tuning studies" in d.measured and "below 0.01 in" in d.measured
    missing = claims.decide_claim(claim_of(claims.Reaches("toy_1", "adam", 1e-2)), tmp_path)
    assert missing[1][0][1].verdict == claims.NOT_RUN


def test_a_presets_only_study_decides_from_its_kept_evidence_alone_under_the_tuned_names(
    tmp_path,
):
    """Kept evidence of an untuned study of the claims-paper profile (one evaluation, no trials):
    its one study decides (no majority of tuning studies to wait for, though the claims profile's
    study of that name plans four), and its variants are found under the tuned study's names,
    which carry the fixed axis ("backprop=C" as "backprop=C clip=none")."""
    from evidence import kept_row, write_kept

    rows = [
        kept_row(0, variant, s, "loss", falling(factor * base(s)), 1000.0)
        for variant, factor in (("backprop=C", 0.5), ("backprop=R", 1.0))
        for s in TEN
    ]
    # "planned" as an earlier keep wrote it: the claims profile's four
    about = {"axis": "iteration", "budget": 1000.0, "trials": 0, "studies": 1, "seeds": 10}
    write_kept(tmp_path, "cart_4", rows, {**about, "planned": 4})
    claim = claim_of(claims.Lower("cart_4", "backprop=C clip=none", "backprop=R clip=none"))
    paper = study_lists.PROFILES["claims-paper"]
    verdict, decided = claims.decide_claim(claim, tmp_path, profile=paper)
    assert verdict == HOLDS, decided[0][1]
    assert "lower in 10 of 10" in decided[0][1].measured
    # the longer-budget column says what ran: the presets untuned, not "0 x 1" trials
    longer, _, _, _ = claims._longer_budgets(claim, "cart_4", ((tmp_path, paper),))
    assert "(presets untuned, 10 seeds)" in longer[0], longer


def test_a_study_that_joins_another_adds_its_variants_under_their_full_names(tmp_path):
    """The cart's clipping modes run as compares of their own (cart_4_value, cart_4_norm) join the
    kept study without clipping: a part naming "backprop=C clip=value" is decided from the joining
    study's runs, the study's own variants stay its own, and a joining study at another budget is
    one line, not a mixed verdict."""
    from evidence import kept_row, write_kept

    about = {"axis": "iteration", "budget": 1000.0, "trials": 0, "studies": 1, "seeds": 10}

    def keep(name, factors, budget=1000.0):
        rows = [
            kept_row(0, variant, s, "loss", falling(factor * base(s)), budget)
            for variant, factor in factors
            for s in TEN
        ]
        write_kept(tmp_path, name, rows, {**about, "budget": budget})

    keep("cart_4", (("backprop=C", 0.5), ("backprop=R", 1.0)))
    keep("cart_4_value", (("backprop=C", 2.0), ("backprop=R", 1.0)))  # C above R with clipping
    paper = study_lists.PROFILES["claims-paper"]
    parts = [
        claims.Lower("cart_4", f"backprop=C clip={mode}", f"backprop=R clip={mode}")
        for mode in ("none", "value", "norm")
    ]
    _, decided = claims.decide_claim(claim_of(*parts), tmp_path, profile=paper)
    assert [d.verdict for _, d in decided] == [HOLDS, claims.FAILS, claims.NOT_RUN]
    keep("cart_4_norm", (("backprop=C", 0.5), ("backprop=R", 1.0)), budget=500.0)
    with pytest.raises(claims.UserError, match="joins .*cart_4.* run them alike"):
        claims.decide_claim(claim_of(*parts), tmp_path, profile=paper)


def test_a_part_not_settled_says_its_cause_where_the_evidence_shows_one(tmp_path, studies):
    """Stuck seeds at the full budget: 8 of 10 below the level in each of three studies, 2 stuck
    at 0.45 (the toy's Adam at lambda = 1): not settled, because the seeds disagree, with the
    counts. Tuning studies reaching opposite verdicts: not settled, because they disagree."""
    from physgrad.claim_words import SEEDS_DISAGREE, STUDIES_DISAGREE

    finals = [1e-3] * 8 + [0.45, 0.45]
    studies["toy_1"] = three_studies(
        "toy_1", [{"adam": {s: falling(v, 1.0, 2 * v) for s, v in zip(TEN, finals)}}] * 3
    )
    found, ((_, d),) = claims.decide_claim(
        claim_of(claims.Reaches("toy_1", "adam", 1e-2)), tmp_path
    )
    assert found == claims.OPEN
    assert d.cause == (SEEDS_DISAGREE, "adam: 24 of 30 seeds below 0.01, 6 stuck at or above it")
    studies["s"] = tuned("s", [0.5, 2.0, 0.5])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == claims.OPEN and d.cause[0] == STUDIES_DISAGREE
    assert "A better, B better, A better" in d.cause[1]


def test_physgrad_s_own_questions_stand_in_their_own_table_below_the_papers_claims(tmp_path):
    table = claims.headline_table(tmp_path, study_lists.PROFILES["claims"]).splitlines()
    marker = table.index("physgrad's own questions, not claims of the papers:")
    own = {c.name for c in claims.CLAIMS if c.own}
    assert own == {"KS: a best unroll length"}
    rows = [line.split(" | ")[0].lstrip("| ") for line in table if line.startswith("| ")]
    below = [
        r for r in rows if table.index(next(x for x in table if x.startswith(f"| {r} "))) > marker
    ]
    assert set(below) - {"claim"} == own


def test_a_level_part_can_ask_that_a_variant_stays_at_or_above_it(tmp_path, studies):
    """ "Adam stays above the book's 1e-2" (the toy at lambda = 0.01): holds where the sign test
    puts the seeds at or above the level, does not hold where it puts them below."""
    for finals, verdict in (([0.2] * 10, claims.HOLDS), ([1e-3] * 10, claims.FAILS)):
        studies["toy_0.01"] = three_studies(
            "toy_0.01", [{"adam": {s: falling(v, 1.0, 2 * v) for s, v in zip(TEN, finals)}}] * 3
        )
        part = claims.Reaches("toy_0.01", "adam", 1e-2, above=True)
        assert part.text() == "adam stays at or above loss 0.01"
        found, ((_, d),) = claims.decide_claim(claim_of(part), tmp_path)
        assert found == verdict, d


def test_the_plan_lists_every_compare_a_part_runs_the_presets_twins_included(capsys):
    """--plan prints each study's command and, for a study with a presets' twin, the twin's
    (compare.tune=false into <name>-preset), once: a part run from the plan's lines alone runs
    the twins too."""
    import study_profiles

    study_profiles.print_claims_plan("claims", Path("outputs/experiments/claims"))
    lines = [line.strip() for line in capsys.readouterr().out.splitlines()]
    commands = [line for line in lines if line.startswith("physgrad compare ")]
    twins = [s for part in study_profiles.claims_parts("claims") for s in part if s.twin]
    listed = [c for c in commands if "-preset " in c]
    assert twins and len(listed) == len(twins)
    assert all("compare.tune=false" in c for c in listed)
    folders = {c.split("compare.dir=")[1].split()[0] for c in listed}
    assert folders == {f"outputs/experiments/claims/{s.name}-preset" for s in twins}


def test_a_part_run_again_skips_what_is_kept_as_evidence(tmp_path, monkeypatch, capsys):
    """Part 3 of the claims (a quantum tuning study, then Poisson's first tuning study from the
    networks it continues, with its presets' twin): with quantum's four tuning studies kept, only
    Poisson's start networks and its two compares run, and the skipped study is named; a damaged
    evidence table stops the part in one line, running nothing."""

    import study_profiles

    evidence = tmp_path / "evidence" / "claims"
    evidence.mkdir(parents=True)
    for suffix in (".csv", ".json"):
        shutil.copy(REPO / "docs" / "evidence" / "claims" / f"quantum{suffix}", evidence)
    monkeypatch.setattr(study_lists, "EVIDENCE", evidence)
    ran = []
    monkeypatch.setattr(study_profiles, "run_child", lambda command, env=None: ran.append(command))
    monkeypatch.setattr(
        study_profiles, "run_start", lambda start, seeds, root: ran.append([start.name]) or 0
    )
    monkeypatch.setattr(claims, "write", lambda *args: None)
    part = study_profiles.claims_parts("claims")[2]
    assert [s.label for s in part][:2] == [
        "quantum (tuning study 4 of 4)",
        "poisson_continue (tuning study 1 of 4)",
    ]
    study_profiles.run_claims("claims", [3], tmp_path / "root", tmp_path / "out", "")
    folders = [next(a for a in c if a.startswith("compare.dir=")) for c in ran if len(c) > 1]
    assert ran[0] == ["poisson_start"]
    assert [f.rsplit("/", 2)[-2:] for f in folders] == [
        ["poisson_continue", "study-1"],
        ["root", "poisson_continue-preset"],
    ]
    assert "reproduce: quantum (tuning study 4 of 4) is kept in" in capsys.readouterr().out
    (evidence / "quantum.csv").write_text("study,variant\n0,adam\n")
    ran.clear()
    code = study_profiles.study_profile("claims", "3", False, tmp_path / "out", "")
    assert code == 2 and not ran
    assert capsys.readouterr().err.startswith("reproduce: error: ")


def test_a_part_not_settled_names_tuning_luck_and_a_lean_against_the_claim(tmp_path, studies):
    """Three tuning studies all 'A better' whose sizes (0.9, 0.2, 0.9) leave a ratio of 1 inside
    the 99% interval over them taken as draws: the cause is tuning luck, not a disagreement (they
    agree). B better in one study and the others undecided: it leans against the claim, with the
    seeds. A trend whose studies reach opposite verdicts says so as its cause."""
    from physgrad.claim_words import LEANS_AGAINST, STUDIES_DISAGREE, TUNING_LUCK

    studies["s"] = tuned("s", [0.9, 0.2, 0.9])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == OPEN and d.cause[0] == TUNING_LUCK, d
    assert "A better, A better, A better" in d.cause[1] and "(99% interval" in d.cause[1]
    studies["s"] = tuned("s", [2.0, 1.0, 1.0])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == OPEN and d.cause[0] == LEANS_AGAINST, d
    assert (
        d.cause[1].startswith("a vs b in 3 tuning studies: B better, ")
        and "a lower in" in d.cause[1]
    )
    spread = np.linspace(-0.05, 0.05, 10)

    def runs(ratio):
        return {
            "C": {s: falling(ratio * base(s) * math.exp(spread[(3 * s) % 10])) for s in TEN},
            "R": {s: falling(base(s)) for s in TEN},
        }

    studies["easy"] = three_studies("easy", [runs(0.9) for _ in range(3)])
    studies["hard"] = three_studies("hard", [runs(r) for r in (0.3, 1.2, 0.3)])
    found, ((_, d),) = claims.decide_claim(
        claim_of(claims.Grows("easy", "hard", "C", "R")), tmp_path
    )
    assert found == OPEN and d.cause[0] == STUDIES_DISAGREE, d
    assert "grows, does not grow, grows" in d.cause[1]


def test_the_causes_of_several_parts_are_said_together_once_each():
    from physgrad.claim_words import SEEDS_DISAGREE, STUDIES_DISAGREE, combined_causes

    seeds, apart = (SEEDS_DISAGREE, "a lower in 30 of 40 seeds"), (STUDIES_DISAGREE, "x: A, B")
    assert combined_causes([("", ""), seeds, apart, seeds]) == (
        SEEDS_DISAGREE,
        "a lower in 30 of 40 seeds; tuning studies disagree as well: x: A, B",
    )
    assert combined_causes([("", "")]) == ("", "")


def test_a_claim_short_of_the_papers_budget_says_what_its_run_at_that_budget_found(
    tmp_path, monkeypatch
):
    """The cart (4 poles) tuned at 1,000 of the paper's 32,000 iterations with M not having left
    its start: "not tested at the paper's budget with tuning", never plain "not tested at the
    paper's budget" where a profile ran it there (the presets at 32,000: claims-paper), whose
    verdict at that budget is said beside it."""

    def stretched(curve, budget):
        return Curve(curve.x * budget / 1000, curve.loss, budget)

    def study(name, final_of, budget):
        by = {
            v: {s: stretched(falling(f * base(s), 2 * base(s)), budget) for s in TEN}
            for v, f in final_of.items()
        }
        return FakeStudy(name, by, budget=budget)

    modes = next(c for c in claims.CLAIMS if c.name.startswith("cart (4 poles)"))
    monkeypatch.setattr(claims, "CLAIMS", (modes,))
    paper = tmp_path / "claims-paper"
    # read afresh each time, as from disk (an untuned study's runs are renamed as they are read).
    # Tuned at 1,000: M fell from 2 to 1.6 (1.25x), not trained; C and S below it
    fresh = {
        str(tmp_path / "cart_4_modes"): lambda: study(
            "cart_4_modes", {"backprop=C": 0.5, "backprop=M": 1.6, "backprop=S": 1.2}, 1000.0
        ),
        str(paper / "cart_4_modes"): lambda: study(
            "cart_4_modes", {"backprop=C": 0.1, "backprop=M": 1.0, "backprop=S": 1.0}, 32000.0
        ),
    }
    monkeypatch.setattr(
        claims, "read_study", lambda f: fresh[str(f)]() if str(f) in fresh else None
    )
    monkeypatch.setattr(
        claims, "study_protocol", lambda f: (0, 1, 10) if f.parent == paper else (8, 4, 10)
    )
    table = claims.headline_table(
        tmp_path,
        study_lists.PROFILES["claims"],
        ((paper, study_lists.PROFILES["claims-paper"]),),
    )
    row = next(line for line in table.splitlines() if line.startswith("| cart (4 poles)"))
    assert "| **not tested at the paper's budget with tuning** (" in row, row
    assert "; at the paper's budget: claims-paper, 32000 iterations (" in row, row
    assert "(presets untuned, 10 seeds): holds)" in row, row
    # without that run, the budget alone is the cause
    alone = claims.headline_table(tmp_path, study_lists.PROFILES["claims"])
    row = next(line for line in alone.splitlines() if line.startswith("| cart (4 poles)"))
    assert "| **not tested at the paper's budget** (" in row and "at the paper's budget:" not in row


def test_a_clock_calibrated_on_a_busy_machine_is_flagged_and_never_kept_for_later_studies(
    tmp_path, monkeypatch
):
    """A calibration at load 5.4 on 2 cores charged every step several times its cost (Poisson's
    HIG 45 s, where a quiet machine measures 7 s): the claim's row says so, and it is not kept as
    the clock of the study's tuning studies still to run; a quiet one is."""
    import json

    from evidence import CLOCK, keep_clock

    def calibration(load: float) -> dict:
        return {
            "costs": {"adam": {"step_seconds": 0.004}, "hig": {"step_seconds": 45.0}},
            "load_start": load,
            "load_end": load,
            "machine": {"cpu_count": 2},
        }

    busy, quiet = tmp_path / "busy.json", tmp_path / "quiet.json"
    busy.write_text(json.dumps(calibration(5.42)))
    quiet.write_text(json.dumps(calibration(1.6)))
    clock = tmp_path / "kept" / CLOCK.format(name="poisson_scratch")
    keep_clock(busy, clock)
    assert not clock.exists()
    keep_clock(quiet, clock)
    assert json.loads(clock.read_text())["load_start"] == 1.6
    assert claim_budget.busy_clock_text(tmp_path / "kept", "poisson_scratch") == ""
    clock.write_text(busy.read_text())  # kept before the rule
    why = claim_budget.busy_clock_text(tmp_path / "kept", "poisson_scratch")
    assert why.startswith("; its clock was calibrated on a busy machine (load average 5.42")
    assert "fewer steps than it says" in why
    keep_clock(quiet, clock)  # a study run again on a quiet clock replaces the busy one
    assert json.loads(clock.read_text())["load_start"] == 1.6
    clock.write_text(busy.read_text())
    clock.write_text("not json")  # unreadable evidence is no flag, and no error here
    assert claim_budget.busy_clock_text(tmp_path / "kept", "poisson_scratch") == ""
    # the later tuning studies and the presets' twin run on the first study's clock, not a busy one
    spec = next(s for s in study_lists.PROFILES["claims"] if s.name == "poisson_scratch")
    first = tmp_path / "root" / "poisson_scratch" / "study-1" / "calibration.json"
    first.parent.mkdir(parents=True)
    evidence = tmp_path / "evidence"
    evidence.mkdir()
    (evidence / CLOCK.format(name="poisson_scratch")).write_text(busy.read_text())
    monkeypatch.setattr(study_lists, "EVIDENCE", evidence)
    first.write_text(busy.read_text())
    assert spec.clock(tmp_path / "root") is None
    first.write_text(quiet.read_text())
    assert spec.clock(tmp_path / "root") == first
    assert f"compare.calibration={first}" in spec.command(tmp_path / "root", preset=True)
    # studies kept on a busy clock are not kept for a part: they run again (a part skips the kept)
    # (a record of all four tuning studies, whatever the committed evidence holds today)
    shutil.copy(REPO / "docs/evidence/claims/poisson_scratch.csv", evidence)
    record = json.loads((REPO / "docs/evidence/claims/poisson_scratch.json").read_text())
    first_study = next(iter(record["tuning_studies"].values()))
    record["tuning_studies"] = {str(k): first_study for k in range(1, spec.studies + 1)}
    (evidence / "poisson_scratch.json").write_text(json.dumps(record))
    assert not spec.kept(evidence)
    (evidence / CLOCK.format(name="poisson_scratch")).write_text(quiet.read_text())
    assert spec.kept(evidence)


def test_a_presets_twin_is_commanded_after_its_study_ran_so_it_runs_on_that_clock(
    tmp_path, monkeypatch
):
    """A part runs a timed study's first tuning study, then its presets' twin: the twin's command
    is made once the study has run, on the clock it calibrated, not before it (when it has none,
    so the twin would calibrate one of its own, perhaps beside other work)."""
    import json

    from study_profiles import claims_parts, study_commands

    monkeypatch.setattr(study_lists, "EVIDENCE", tmp_path / "no evidence")
    study = next(
        s
        for part in claims_parts("claims")
        for s in part
        if s.name == "poisson_continue" and s.tuning_study == 1
    )
    commands = study_commands(study, tmp_path)
    preset, first = next(commands)
    assert not preset and not any(o.startswith("compare.calibration=") for o in first)
    clock = tmp_path / "poisson_continue" / "study-1" / "calibration.json"
    clock.parent.mkdir(parents=True)  # the study ran and calibrated
    clock.write_text(json.dumps({"load_start": 1.5, "load_end": 1.9, "machine": {"cpu_count": 2}}))
    preset, twin = next(commands)
    assert preset and f"compare.calibration={clock}" in twin


def test_a_failure_at_x4_between_networks_that_have_not_left_their_start_is_not_shown_as_one(
    tmp_path, monkeypatch
):
    """C, M and S all at 1.975 from 2 at X/4 (equivalent: "does not hold" for "C below M"), C at
    0.5 by X: the X/4 cell says not settled, a variant not having left its start, since
    equivalence between untrained networks is no evidence against the claim."""
    modes = next(c for c in claims.CLAIMS if c.name.startswith("cart (4 poles)"))
    monkeypatch.setattr(claims, "CLAIMS", (modes,))

    def study():
        by = {
            v: {s: falling(final * base(s), 2 * base(s), 1.95 * base(s)) for s in TEN}
            for v, final in (("backprop=C", 0.5), ("backprop=M", 1.9), ("backprop=S", 1.9))
        }
        return FakeStudy("cart_4_modes", by)

    monkeypatch.setattr(
        claims, "read_study", lambda f: study() if f == tmp_path / "cart_4_modes" else None
    )
    monkeypatch.setattr(claims, "study_protocol", lambda f: (8, 4, 10))
    assert claims.claim_verdicts(modes, tmp_path)[0.25] == FAILS  # as decided, untrained
    table = claims.headline_table(tmp_path, study_lists.PROFILES["claims"])
    row = next(line for line in table.splitlines() if line.startswith("| cart (4 poles)"))
    cells = [c.strip() for c in row.split("|")]
    assert cells[6] == "not settled (a variant had not left its start)", row
    assert cells[8] == "**holds**", row


def test_runs_from_uncommitted_changes_are_named_in_every_profile_kept_beside(tmp_path):
    """claims.md names the kept studies whose runs came from a dirty tree, the longer profiles'
    (claims-paper/NAME) as well as the claims profile's."""
    import json

    from study_runs import uncommitted_note

    claims_folder, paper = tmp_path / "claims", tmp_path / "claims-paper"
    for folder, name, commit in (
        (claims_folder, "toy_1", "283e262e0a28aaaa+dirty:b15f32bd9203"),
        (claims_folder, "oscillator", "0123456789abcdef"),
        (paper, "guidance_0.001", "78ac030950abffff+dirty:7661bd74117c"),
    ):
        folder.mkdir(exist_ok=True)
        (folder / f"{name}.json").write_text(json.dumps({"commits": [commit]}))
    assert uncommitted_note(claims_folder) == (
        "; runs from uncommitted changes: toy_1 (283e262e0a28+dirty:b15f32bd9203)"
    )
    assert uncommitted_note(claims_folder, paper).endswith(
        "toy_1 (283e262e0a28+dirty:b15f32bd9203), "
        "claims-paper/guidance_0.001 (78ac030950ab+dirty:7661bd74117c)"
    )


def test_a_tuned_study_without_its_tuning_recorded_says_so_and_a_tuned_value_its_span(tmp_path):
    """Kept evidence from before the tuning was kept says "not recorded" for a tuned study (not for
    presets); a recorded value comes with the span its trials tried and the edge mark."""
    import json

    from tuned_settings import tuned_table

    (tmp_path / "old.json").write_text(json.dumps({"trials": 8, "tuning_studies": {"1": {}}}))
    (tmp_path / "old-preset.json").write_text(json.dumps({"trials": 0}))
    trials = [{"variant": "adam", "learning_rate": r} for r in (1e-4, 1e-3, 1e-2, 1e-1)]
    record = {"trials": trials, "tuned": {"adam": {"learning_rate": 0.1}}}
    (tmp_path / "new.json").write_text(json.dumps({"trials": 4, "tuning_studies": {"1": record}}))
    table = tuned_table(tmp_path)
    assert "\nTuned settings not recorded for old (kept before the evidence kept" in table
    assert "old-preset" not in table and "| old |" not in table
    assert "| new | adam | study 1: learning_rate=0.1 of [0.0001, 0.1] *edge* |" in table
    (tmp_path / "new.json").unlink()
    assert tuned_table(tmp_path) == (
        "\nTuned settings: not recorded for old (kept before the evidence kept its tuning; each "
        "tuning study's compare.md lists it).\n"
    )
    (tmp_path / "old.json").unlink()
    assert tuned_table(tmp_path) == "\nTuned settings: none of these studies was tuned.\n"


def test_a_ratio_that_a_divergence_makes_0_says_so(tmp_path, studies):
    """B diverged on 7 of 10 seeds: the median ratio A / B is 0, which the part says comes from
    B's divergence, not from a measured difference."""
    a = {s: falling(0.1 * base(s)) for s in TEN}
    b = {
        s: Curve(X, np.array([1.0] * 5 + [math.inf] * 6), X[-1], diverged=True)
        if s < 7
        else falling(base(s))
        for s in TEN
    }
    studies["s"] = FakeStudy("s", {"a": a, "b": b})
    _, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert d.measured.startswith("a / b = 0 (the median seed's b diverged) ["), d.measured
    assert "b diverged in 7 of 10" in d.measured


def test_a_part_the_presets_twin_skips_is_read_from_the_presets_at_the_papers_budget(
    tmp_path, monkeypatch
):
    """The cart's presets' twin runs clip=none only; claims-paper ran the presets under every
    clipping at the paper's 32,000 iterations: the twin's "not run" cell gives that run's verdict.
    A tuned longer run, or one short of the paper's budget, is no presets' verdict there."""
    import claim_budget

    cart = next(c for c in claims.CLAIMS if c.name.startswith("cart: C keeps"))
    paper = tmp_path / "claims-paper"
    budget = {"value": 32000.0}
    trials = {"value": 0}

    def decide(claim, folder, suffix, fraction, there):
        assert folder == paper and suffix == "" and fraction == 1.0
        part, other = claim.parts[0], claim.parts[1]
        return HOLDS, [
            (part, claims.Decision(HOLDS, "C / R = 0.07 [0.02, 0.1]; C lower in 9 of 10", "")),
            (other, claims.Decision(claims.NOT_RUN, "-", "not in this profile")),
        ]

    monkeypatch.setattr(
        claim_budget,
        "read_study",
        lambda f: FakeStudy(str(f), {}, budget=budget["value"]) if f.parent == paper else None,
    )
    monkeypatch.setattr(claim_budget, "study_protocol", lambda f: (trials["value"], 1, 10))
    further = ((paper, study_lists.PROFILES["claims-paper"]),)
    found = claim_budget.presets_at_paper_budget(cart, further, decide)
    assert found == {
        cart.parts[0].text(): (
            HOLDS,
            "with the presets at the paper's budget (claims-paper, 32000 iterations)",
            " (C / R = 0.07 [0.02, 0.1])",
        )
    }
    budget["value"] = 16000.0  # half the paper's: not its budget
    assert claim_budget.presets_at_paper_budget(cart, further, decide) == {}
    budget["value"], trials["value"] = 32000.0, 8  # tuned: not the presets
    assert claim_budget.presets_at_paper_budget(cart, further, decide) == {}
    assert claim_budget.presets_at_paper_budget(cart, (), decide) == {}


def test_a_failing_part_says_its_verdict_at_the_papers_budget_where_one_was_run():
    """Only the parts that fail are named; one the presets held at the paper's budget says so, one
    never run there is named alone."""
    fails, holds = claims.Decision(FAILS, "-", ""), claims.Decision(HOLDS, "-", "")
    first, second, third = (claims.Lower("s", a, "r") for a in ("a", "b", "c"))
    where = "with the presets at the paper's budget (claims-paper, 32000 iterations)"
    text = claim_budget.failing_text(
        [(first, fails), (second, holds), (third, fails)],
        {first.text(): (HOLDS, where, " (0.03)"), second.text(): (HOLDS, where, "")},
    )
    assert text == f"{first.text()}: does not hold (holds {where}); {third.text()}: does not hold"
    assert claim_budget.failing_text([(second, holds)], {}) == ""


def test_a_page_decides_a_claim_at_a_budget_once_and_only_while_it_is_written():
    """claim_budget.PageMemo: calls with the same arguments (defaults or not) are decided once
    within `page()`, every time outside it, and afresh in the next page (the evidence may change
    between two pages written in one process)."""
    calls = []

    def decide(claim, root, suffix="", fraction=1.0):
        calls.append((claim, root, suffix, fraction))
        return len(calls)

    memo = claim_budget.PageMemo(decide)
    assert memo("c", "r") == 1 and memo("c", "r") == 2  # outside a page: every call decides
    with memo.page():
        first = memo("c", "r")
        assert memo("c", "r", "", 1.0) == memo("c", root="r") == first == 3
        assert memo("c", "r", fraction=0.5) == 4 and memo("c", "r", "-preset") == 5
    with memo.page():
        assert memo("c", "r") == 6
    assert memo("c", "r") == 7 and len(calls) == 7


def test_a_half_run_study_resumes_on_its_clock_kept_since_under_another_name(tmp_path):
    """A later tuning study started on the first study's own calibration.json resumes on that file
    after the clock was kept into the evidence (the same clock: compare would refuse the folder as
    another study's under the new name); another clock, no record or a damaged one: the kept
    clock."""
    import json

    kept = tmp_path / "kept.calibration.json"
    kept.write_text(json.dumps({"costs": {"adam": {"step_seconds": 0.001}}, "load_start": 1.0}))
    own = tmp_path / "study-1" / "calibration.json"
    own.parent.mkdir()
    own.write_text(json.dumps(json.loads(kept.read_text()), indent=3))  # same clock, other bytes
    folder = tmp_path / "study-2"
    assert study_lists.started_clock(folder, kept) == kept  # nothing started there
    folder.mkdir()
    record = {"overrides": ["task=poisson", f"compare.calibration={own}"]}
    (folder / "study.json").write_text(json.dumps(record))
    assert study_lists.started_clock(folder, kept) == own
    own.write_text(json.dumps({"costs": {"adam": {"step_seconds": 0.002}}, "load_start": 1.0}))
    assert study_lists.started_clock(folder, kept) == kept  # another clock: not resumed on it
    for damaged in ("not json", '{"overrides": 3}', '{"overrides": ["task=poisson"]}'):
        (folder / "study.json").write_text(damaged)
        assert study_lists.started_clock(folder, kept) == kept
