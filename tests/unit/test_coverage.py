"""Unit layer (pure functions) of the tests of: what a study's search could have found (warnings on
presets outside every trial, untried decades of a range, too few trials per study)."""

import math

from omegaconf import OmegaConf

from physgrad.comparison import Variant, halton_points, study_settings
from physgrad.comparison.coverage import (
    MIN_TRIALS,
    coverage_lines,
    planned_points,
    tried_values,
)
from physgrad.comparison.points import point_dimensions
from physgrad.comparison.spec import StudyPlan

RANGE = (1e-3, 1.0)


def variant(name="gauss_newton", preset=1.0, space=None):
    config = OmegaConf.create({"optim": {"learning_rate": preset}})
    return Variant(
        name, [f"optim={name}"], config, {"learning_rate": RANGE} if space is None else space
    )


def warnings_of(lines):
    return [line for line in lines if line]


def test_a_preset_above_every_trial_is_named_with_the_highest_tried():
    """The newcomer's case: Gauss-Newton ships learning_rate=1, two trials never went above
    0.165."""
    (line,) = [
        x
        for x in coverage_lines([variant()], {"gauss_newton": {"learning_rate": [0.01, 0.165]}}, 8)
        if "preset" in x
    ]
    assert "gauss_newton's preset learning_rate=1 lies above every trial" in line
    assert "the highest tried: 0.165" in line and "compare.search.learning_rate" in line
    (below,) = [
        x
        for x in coverage_lines(
            [variant(preset=1e-3)], {"gauss_newton": {"learning_rate": [0.01, 0.165]}}, 8
        )
        if "preset" in x
    ]
    assert "lies below every trial (the lowest tried: 0.01)" in below


def test_a_preset_among_the_trials_or_not_a_number_is_not_warned_about():
    tried = {"gauss_newton": {"learning_rate": [0.01, 0.1, 2.0]}}
    assert not [x for x in coverage_lines([variant()], tried, 8) if "preset" in x]
    for preset in (None, "auto", True):
        assert not [x for x in coverage_lines([variant(preset=preset)], tried, 8) if "preset" in x]


def test_a_preset_outside_the_range_says_so():
    tried = {"gauss_newton": {"learning_rate": [0.01, 0.1]}}
    (line,) = [x for x in coverage_lines([variant(preset=5.0)], tried, 8) if "preset" in x]
    assert "outside the range [0.001, 1] searched" in line


def test_the_widest_untried_stretch_of_a_decade_or_more_is_named():
    # trials at 0.002 and 0.004 in [1e-3, 1]: 0.004 .. 1 untried, 2.4 decades
    (line,) = [
        x
        for x in coverage_lines(
            [variant(preset=0.003)], {"gauss_newton": {"learning_rate": [0.002, 0.004]}}, 8
        )
        if "no trial" in x
    ]
    assert "between 0.004 and 1 (2.4 decades of its range [0.001, 1] untried)" in line
    # one trial every half decade: nothing to say
    even = [10 ** (-3 + 0.5 * k) for k in range(7)]
    assert (
        coverage_lines([variant(preset=0.01)], {"gauss_newton": {"learning_rate": even}}, 8, 4)
        == []
    )
    # the ends of the range count: a gap from the lowest end to the first trial
    (line,) = [
        x
        for x in coverage_lines(
            [variant(preset=0.5)], {"gauss_newton": {"learning_rate": [0.05, 0.2, 0.5, 1.0]}}, 8
        )
        if "no trial" in x
    ]
    assert "between 0.001 and 0.05" in line


def test_too_few_trials_per_study_is_said_once_and_enough_is_not():
    tried = {"gauss_newton": {"learning_rate": [0.01, 0.1, 0.5]}}
    few = warnings_of(coverage_lines([variant(), variant("hig")], tried, 2))
    assert sum("trials per tuning study" in x for x in few) == 1
    assert "one of 2 points" in few[0] and f"compare.trials={MIN_TRIALS}" in few[0]
    assert not any("per tuning study" in x for x in coverage_lines([variant()], tried, MIN_TRIALS))


def test_a_variant_with_nothing_tuned_gets_no_warning():
    assert coverage_lines([variant(space={})], {}, 1) == []


def test_the_values_tried_are_read_from_the_trial_rows_without_set_aside_ones():
    rows = [
        {"variant": "adam", "study": 0, "trial": 0, "learning_rate": 0.01, "state": "COMPLETE"},
        {"variant": "adam", "study": 1, "trial": 0, "learning_rate": 0.2, "validation_loss": 1.0},
        {"variant": "adam", "study": 0, "trial": 1, "state": "SET_ASIDE"},
        {"variant": "adam", "study": 0, "trial": 2, "learning_rate": math.nan},
        {"variant": "gd", "study": 0, "trial": 0, "learning_rate": 0.5, "state": "FAIL"},
    ]
    assert tried_values(rows) == {
        "adam": {"learning_rate": [0.01, 0.2]},
        "gd": {"learning_rate": [0.5]},
    }


def test_the_planned_points_are_the_points_each_tuning_study_will_try():
    settings = study_settings({"trials": 3, "studies": 2})
    variants = [variant("adam", 1e-3, {"learning_rate": (1e-5, 0.1)}), variant()]
    plan = StudyPlan(variants, settings, [], set(), "iteration", 100)
    planned = planned_points(plan)
    dimensions = point_dimensions([v.space for v in variants])
    for v in variants:
        expected = [
            p["learning_rate"]
            for k in range(2)
            for p in halton_points(v.space, 3, settings.tune_seed + k, dimensions)
        ]
        assert planned[v.name]["learning_rate"] == expected


def test_a_coarse_grid_is_said_with_how_coarse_and_a_fine_one_is_not():
    """4 trials in each of 4 tuning studies over 4 decades are 4 points a decade (their points
    interleave into one grid): below 6, a note with the spacing; 8 x 4 over 4 decades pass."""
    from physgrad.comparison.coverage import PER_DECADE

    four = {"learning_rate": (1e-5, 1e-1)}
    coarse = coverage_lines([variant("adam", 1e-3, four)], {}, trials=4, studies=4)
    (line,) = [x for x in coarse if x.startswith("note: the tuning's grid is coarse")]
    assert f"fewer than {PER_DECADE} points a decade" in line
    assert "adam's learning_rate 16 points over 4 decades (one every 0.25 decade)" in line
    fine = coverage_lines([variant("adam", 1e-3, four)], {}, trials=8, studies=4)
    assert not any("coarse" in x for x in fine)


def test_every_variant_at_the_same_point_in_every_study_is_said():
    """Three rules each tuned to the same normalised point of its own range in every study (the
    newcomer's 4-trial study: 0.00439 of adam's range, the same place of soap's and muon's) is a
    note; one study where they differ, or one variant, is not."""
    from physgrad.comparison.coverage import same_point_line

    ranges = {"adam": (1e-5, 1e-1), "hig": (1e-3, 1e1), "gd": (1e-4, 1e1)}
    variants = [variant(n, 1.0, {"learning_rate": r}) for n, r in ranges.items()]

    def at(place):  # each variant's rate at the same fraction of its log range
        return {n: {"learning_rate": lo * (hi / lo) ** place} for n, (lo, hi) in ranges.items()}

    (note,) = same_point_line(variants, [at(0.3), at(0.7), at(0.1)])
    assert note.startswith("note: every variant was tuned to the same point")
    differ = [at(0.3), {**at(0.7), "gd": {"learning_rate": 1.0}}]
    assert same_point_line(variants, differ) == []
    assert same_point_line(variants[:1], [at(0.3), at(0.7)]) == []
    assert same_point_line(variants, [at(0.3)]) == []  # one study: a coincidence, not the grid


def test_the_plan_says_what_it_does_on_stderr_unless_quiet(capsys, monkeypatch):
    from physgrad.comparison.plan import say_progress

    say_progress("plan: compiling and timing adam (1 of 2)")
    assert capsys.readouterr().err == "plan: compiling and timing adam (1 of 2)\n"
    monkeypatch.setenv("PHYSGRAD_QUIET", "1")
    say_progress("plan: compiling and timing gd (2 of 2)")
    assert capsys.readouterr().err == ""


def test_a_variant_with_fewer_than_100_steps_in_the_budget_is_said_with_the_budget_it_needs():
    """HIG at 1.46 s a step in a 15 s budget: about 10 steps, and the budget for 100 (146 s,
    rounded up to 150); Adam's 7,000 steps and a variant with no measured step say nothing."""
    from physgrad.comparison.coverage import FEW_STEPS, few_steps_lines

    lines = few_steps_lines({"adam": 7000.0, "hig": 15 / 1.46, "gone": math.nan}, 15.0)
    assert lines[0] == "" and len(lines) == 2
    assert lines[1].startswith(
        "note: hig gets about 10 steps in the budget of 15 s, fewer than 100"
    )
    assert "trainer.time_budget=150 gives it about 100" in lines[1]
    assert few_steps_lines({"hig": FEW_STEPS}, 15.0) == []  # 100 is enough
    assert "time_budget=1100 " in few_steps_lines({"kfac": 9.5}, 100.0)[1]  # 1052.6 -> 1100
    assert "time_budget=1000 " in few_steps_lines({"x": 0.2}, 10.0)[1]  # at least one step
