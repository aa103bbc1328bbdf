"""experiments/claims.py: physgrad's verdict rule (physgrad.verdict, tested in test_verdict.py) as the claims'
holds / does not hold / not settled on synthetic curves, the reading of runs into paired curves, claims.md and
the pay-off map."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "experiments"))
import claims  # noqa: E402
from claims import FAILS, HOLDS, OPEN, Curve, combine, decide  # noqa: E402
from physgrad.results import Run  # noqa: E402

X = np.arange(0, 1001, 100, dtype=float)


def power_law(scale: float, rate: float = 1.0) -> Curve:
    """A loss falling as scale / (1 + x)^rate, evaluated every 100 iterations up to 1000."""
    return Curve(X, scale / (1 + X) ** rate, X[-1])


def seeds(*curves: Curve) -> dict[int, Curve]:
    return dict(enumerate(curves))


TEN = range(1, 11)


def test_lower_in_ten_seeds_by_the_margin_holds():
    d = decide(seeds(*(power_law(0.5 * s) for s in TEN)), seeds(*(power_law(s) for s in TEN)))
    assert (d.verdict, d.pairs, d.wins, d.budget) == (HOLDS, 10, 10, 1000)
    assert d.ratio == pytest.approx(0.5) and d.half_ratio == pytest.approx(0.5) and "A better" in d.why


def test_the_other_lower_does_not_hold():
    d = decide(seeds(*(power_law(2.0 * s) for s in TEN)), seeds(*(power_law(s) for s in TEN)))
    assert d.verdict == FAILS and d.wins == 0 and d.ratio == pytest.approx(2.0) and "B better" in d.why


def test_level_within_the_margin_does_not_hold():
    d = decide(seeds(*(power_law(0.95 * (1 + 0.001 * s)) for s in TEN)), seeds(*(power_law(1) for _ in TEN)))
    assert d.verdict == FAILS and d.wins == 10 and "equivalent" in d.why  # 5% is inside the 10% margin


def test_three_unanimous_seeds_are_not_settled():
    """The old unanimity rule said holds; three pairs cannot reach p < 0.05 (3 of 3 happens by chance 1 in 8)."""
    d = decide(seeds(*(power_law(0.1 * s) for s in (1, 2, 3))), seeds(*(power_law(s) for s in (1, 2, 3))))
    assert d.verdict == OPEN and d.pairs == 3 and d.wins == 3 and "at least 6 needed" in d.why


def test_mixed_seeds_are_not_settled():
    d = decide(seeds(*(power_law(f) for f in (0.5, 2.0, 1.05, 0.6, 1.7, 0.9, 1.2, 0.8, 1.5, 0.7))),
               seeds(*(power_law(1) for _ in TEN)))
    assert d.verdict == OPEN and d.wins == 5


def test_a_gap_that_closes_is_reported_as_closing_whichever_side_it_favours():
    """A ahead at half the budget and level at its end: the claim does not hold at X, and the row says the gap
    narrowed (the old rule only ever read a trend in the claim's favour)."""
    better = seeds(*(Curve(X, (1 + X) ** -1.0 * np.where(X <= 500, 0.3, 1.0) * (1 + 0.001 * s), X[-1]) for s in TEN))
    worse = seeds(*(Curve(X, (1 + X) ** -1.0, X[-1]) for _ in TEN))
    d = decide(better, worse)
    assert d.verdict == FAILS and d.half_ratio == pytest.approx(0.3, rel=0.01) and "gap narrowing" in d.why


def test_divergence_counts_as_infinite_and_both_diverged_pairs_are_ties():
    diverged = Curve(X[:3], np.array([1.0, 0.9, 0.8]), 250.0, diverged=True)
    d = decide(seeds(*[power_law(1)] * 9, diverged), seeds(*[diverged] * 9, power_law(1)))
    # pairs 0..8: only B diverged (A wins); pair 9: A diverged: 9 of 10, median ratio 0
    assert (d.pairs, d.wins, d.budget) == (10, 9, 1000) and d.ratio == 0.0 and d.verdict == HOLDS
    both = decide(seeds(diverged, *[power_law(0.5)] * 9), seeds(diverged, *[power_law(1)] * 9))
    assert both.pairs == 10 and both.wins == 9 and both.verdict == HOLDS


def test_the_budget_is_the_shortest_completed_run_and_nothing_after_it_is_read():
    short = Curve(X[:6], 0.5 / (1 + X[:6]), 500.0)
    d = decide(seeds(short, *[power_law(0.5)] * 9), seeds(*(power_law(1) for _ in TEN)))
    assert d.budget == 500 and d.ratio == pytest.approx(0.5)
    # on the time axis, the evaluation after the step that crossed the budget is not read at the budget
    late = Curve(np.array([0.0, 60.4, 120.3]), np.array([1.0, 0.5, 0.25]), 120.0)
    assert late.at(120.0) == 0.5 and late.at(60.0) == 1.0
    stopped = Curve(X[:3], np.ones(3), 200.0)  # interrupted before the budget: says nothing there
    assert math.isnan(stopped.at(500.0))


def test_combine():
    assert combine([HOLDS, HOLDS]) == HOLDS
    assert combine([HOLDS, FAILS, OPEN]) == FAILS
    assert combine([HOLDS, OPEN]) == OPEN
    assert combine([]) == OPEN


def fake_run(tmp: str, seed: int, config: dict, scale: float, status: str = "completed", **attrs) -> Run:
    """A results file's content as read back, for a run whose test loss is scale / (1 + iteration)."""
    attrs = {"task": config["task"]["name"], "optim": config["optim"]["name"], "seed": seed, "status": status,
             "variant": config["optim"]["name"],
             "unroll": config.get("unroll") or 10, "config": yaml.safe_dump(config), **attrs}
    loss = scale * (1 + seed) / (1 + X)
    # as the runner writes them: a train row's iteration is the step's index, an evaluation's the steps done
    return Run(Path(tmp) / f"{seed}.h5", attrs, {"iteration": X[1:] - 1, "wall_time": X[1:] / 100, "loss": loss[1:]},
               {"iteration": X, "wall_time": X / 100, "loss": loss})


def test_a_claim_pairs_runs_by_seed_through_their_configuration(tmp_path):
    runs = [fake_run(tmp_path, s, {"task": {"name": "multicart", "poles": poles}, "optim": {"name": "bptt", "backprop": mode}},
                     scale)
            for s in range(8) for poles, mode, scale in [(3, "C", 0.5), (3, "R", 1.0), (4, "C", 1.0), (4, "R", 0.5)]]
    claim = next(c for c in claims.CLAIMS if c.figure == "fig4_multicart")
    verdict, rows = claims.measure(claim, runs)
    assert [row["decision"].verdict for row in rows] == [HOLDS, FAILS] and verdict == FAILS
    assert rows[0]["better"] == pytest.approx([0.5 * (1 + s) / 1001 for s in range(8)])


@pytest.mark.parametrize("axis", ["iteration", "wall_time"])
def test_a_real_run_s_curve_ends_at_its_last_evaluation(tmp_path, axis):
    from physgrad.experiment import run_experiment
    from physgrad.results import read_run
    from tests.test_configs import load as compose

    _, path = run_experiment(compose("task=toy", "trainer.iterations=6", "trainer.eval_every=3"), tmp_path)
    run = read_run(path)
    c = claims.curve(run, axis)
    assert c.end == pytest.approx(run.eval[axis][-1]) and run.eval["iteration"][-1] == 6
    assert c.at(c.end) == run.eval["loss"][-1] != run.eval["loss"][-2]


def test_claims_md_and_payoff_map_from_runs_on_disk(tmp_path):
    """Results files written by the real writer (the oscillator's map needs its folders; the claim rows read
    them)."""
    from physgrad.results import ResultsWriter

    root = tmp_path / "runs"
    for n, variant, scale in [(2, "hig", 0.5), (2, "adam", 1.0), (4, "hig", 2.0), (4, "adam", 1.0)]:
        for seed in range(6):
            config = {"task": {"name": "oscillator", "oscillators": n}, "optim": {"name": variant}}
            run = fake_run(tmp_path, seed, config, scale)
            folder = root / ("fig1_oscillator" if n == 2 else "hig_payoff") / f"n={n},{variant},seed={seed}"
            writer = ResultsWriter(folder / "results.h5", {k: v for k, v in run.attrs.items() if k != "status"})
            for group in ("train", "eval"):
                for i in range(getattr(run, group)["iteration"].size):
                    writer.append(group, {k: float(v[i]) for k, v in getattr(run, group).items()})
            writer.finish("completed")
    text = claims.write(root, tmp_path / "out")
    assert (tmp_path / "out" / "claims.md").read_text() == text
    assert "**oscillators: HIG below Adam and Gauss-Newton: not settled**" in text  # no Gauss-Newton runs
    assert "| hig: 0.00175 (0.0005-0.003) | adam: 0.0035 (0.000999-0.00599) | 6 of 6, 0.5; 0.5 | holds" in text
    assert "**KS: correction beats prediction: not settled**" in text and "0 paired seeds" in text
    assert (tmp_path / "out" / "payoff.png").stat().st_size > 10_000
    table = claims.payoff(root)
    assert {n for n, _ in table} == {2, 4} and len(table) == 8
    assert all(d.verdict == HOLDS for (n, _), d in table.items() if n == 2)
    assert all(d.verdict == FAILS and d.ratio == pytest.approx(2.0) for (n, _), d in table.items() if n == 4)


def test_spread_over_seeds_says_how_many_diverged():
    assert claims._spread([1.0, math.inf, 3.0]) == "2 (1-3); 1 of 3 diverged"
    assert claims._spread([math.inf, 4.5e-6, math.inf]) == "4.5e-06; 2 of 3 diverged"
    assert claims._spread([math.inf] * 3) == "3 of 3 diverged" and claims._spread([]) == "no runs"
    assert claims._ratio(0.0, "hig", "adam") == "0 (adam diverged)" and claims._ratio(0.25, "hig", "adam") == "0.25"
    assert claims._ratio(math.inf, "hig", "adam") == "inf (hig diverged)"


def test_a_time_budget_run_ends_at_its_budget_whatever_its_last_step():
    """A budget is checked after each step: a slow variant's final evaluation, a long step after the budget, is
    not its loss at the budget (the crossing step counts against it); the budget, not the fastest run's
    overshoot, is X."""
    config = {"task": {"name": "oscillator"}, "optim": {"name": "hig"}, "trainer": {"time_budget": 9.0}}
    run = fake_run("/nowhere", 0, config, 1.0, stopped_by="time_budget")  # a step and an evaluation every second
    run.train["wall_time"][-1] = run.eval["wall_time"][-1] = 12.0  # a last step of 3 s: ends 3 s after the budget
    c = claims.curve(run, "wall_time")
    assert c.end == 9.0 and c.x[-1] == 12.0 and c.x[-2] == 9.0  # the evaluation at 9 s and the final one
    assert c.at(9.0) == run.eval["loss"][-2] != run.eval["loss"][-1]  # the step that crossed counts against it
    assert c.at(4.5) == run.eval["loss"][4]  # the last evaluation at or before the time
    untouched = claims.curve(fake_run("/nowhere", 0, config, 1.0), "wall_time")  # not stopped by its budget
    assert untouched.end == 10.0


def test_a_diverged_run_and_an_init_from_offset_through_curve():
    config = {"task": {"name": "toy"}, "optim": {"name": "adam"}}
    diverged = fake_run("/nowhere", 0, config, 1.0, status="diverged")
    c = claims.curve(diverged, "iteration")
    assert c.diverged and c.end == 1000 and c.at(500.0) == diverged.eval["loss"][5] and c.at(1000.0) == math.inf
    continued = fake_run("/nowhere", 0, config, 1.0, init_iterations=300, init_train_seconds=3.0)
    assert claims.curve(continued, "iteration").end == 1300 and claims.curve(continued, "iteration").x[0] == 300
    assert claims.curve(continued, "wall_time").x[-1] == pytest.approx(13.0)


def test_zero_losses_give_a_defined_ratio():
    zero = Curve(X, np.zeros(X.size), X[-1])
    assert decide(seeds(zero, zero, zero), seeds(zero, zero, zero)).ratio == 1.0
    assert decide(seeds(power_law(1), power_law(1), power_law(1)), seeds(zero, zero, zero)).ratio == math.inf


def test_two_runs_of_one_seed_on_one_side_are_named_not_silently_chosen(tmp_path):
    claim = next(c for c in claims.CLAIMS if c.figure == "fig4_multicart")
    runs = [fake_run(tmp_path / name, s, {"task": {"name": "multicart", "poles": 3},
                                          "optim": {"name": "bptt", "backprop": mode}}, 1.0)
            for s in range(3) for mode in ("C", "R") for name in ("a", "b")[:1 + (s == 1 and mode == "C")]]
    verdict, rows = claims.measure(claim, runs)
    assert verdict == OPEN and rows[0]["decision"].verdict == OPEN and "seed 1 matches" in rows[0]["decision"].why
    assert "move the one that does not belong" in claims.claim_rows(claim, runs)[0]


def test_the_payoff_map_leaves_out_a_chain_length_with_two_runs_of_one_seed(tmp_path, monkeypatch, capsys):
    runs = [fake_run(tmp_path / name, s, {"task": {"name": "oscillator", "oscillators": n}, "optim": {"name": v}}, 1.0)
            for n in (2, 4) for v in ("hig", "adam") for s in range(3)
            for name in ("a", "b")[:1 + (n == 4 and v == "hig" and s == 0)]]
    monkeypatch.setattr(claims, "load", lambda root, folders: runs)
    assert {n for n, _ in claims.payoff(tmp_path)} == {2}
    assert "without n = 4: seed 0 matches" in capsys.readouterr().err


def test_an_unreadable_results_file_is_left_out_and_named(tmp_path, capsys):
    (tmp_path / "fig2_quantum" / "job").mkdir(parents=True)
    (tmp_path / "fig2_quantum" / "job" / "results.h5").write_bytes(b"not an HDF5 file")
    assert claims.load(tmp_path, ("fig2_quantum",)) == []
    assert "left out" in capsys.readouterr().err


def test_ks_claim_orders_wig_nog_one():
    claim = next(c for c in claims.CLAIMS if c.name.startswith("KS: WIG best"))
    assert [c.label for c in claim.comparisons] == [("WIG", "NOG"), ("WIG", "ONE"), ("NOG", "ONE")]


def test_payoff_cuts_lie_on_the_evaluation_grid_of_a_time_budget_run():
    from physgrad.runner import EVALUATIONS_PER_BUDGET

    assert all(float(f * EVALUATIONS_PER_BUDGET).is_integer() for f in claims.PAYOFF_FRACTIONS)


def test_the_ks_study_table_says_when_a_claim_has_nothing_to_compare():
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("ks_study", Path(__file__).parents[1] / "experiments" / "ks_study.py")
    ks_study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ks_study)
    text = ks_study.claims({("correct", "WIG", 2): {0: (0.1, 0.0)}})  # no prediction runs
    assert "nothing to compare" in text and "nan" not in text
