"""Unit layer: what makes repeated tuning studies independent draws. Each study evaluates on a block
of seeds of its own, and shifts the whole set of trial points by a random vector of its own; within
a study every variant is tried at the same points of its own ranges, and a search key never moves
another key's points."""

import math

import numpy as np
import pytest
from scipy import stats

from physgrad.comparison import study_settings
from physgrad.comparison.points import (
    ROTATIONS,
    halton_cell,
    halton_points,
    point_dimensions,
    unit_points,
)
from physgrad.errors import UserError

RANGE = (1e-5, 1.0)


def test_each_tuning_study_evaluates_on_seeds_of_its_own():
    settings = study_settings({"seeds": 10, "studies": 3})
    blocks = [settings.study_seeds(k) for k in range(3)]
    assert blocks == [list(range(0, 10)), list(range(10, 20)), list(range(20, 30))]
    assert settings.evaluation_seeds == list(range(30))
    # untuned: one study, one block
    untuned = study_settings({"seeds": 10, "studies": 3, "tune": False})
    assert untuned.evaluation_seeds == list(range(10))


@pytest.mark.parametrize(
    "given, fragment",
    [
        # tuning seed 25 lies in study 2's evaluation seeds 20..29
        ({"seeds": 10, "studies": 3, "tune_seed": 25}, "overlap the evaluation seeds 0..29"),
        ({"seeds": 10, "studies": 3, "seed": 2**32 - 20}, "below 4294967296"),
    ],
)
def test_seeds_that_collide_or_overflow_are_one_line_errors(given, fragment):
    with pytest.raises(UserError, match=fragment) as error:
        study_settings(given)
    assert "\n" not in str(error.value)


def test_the_whole_point_set_is_shifted_per_study_and_keeps_its_spacing():
    """A shift moves every point by the same amount modulo 1: the gaps between sorted points stay
    those of the Halton set (1/8 for 8 points in one coordinate) and another seed gives another
    shift; the first study of a group (seed a multiple of ROTATIONS) is not rotated, so its n
    points begin its n + m points (a study given more trials keeps the ones it tried; the others
    rotate by a fraction of the count's cell, which moves with the count)."""
    for seed in range(20):
        points = unit_points(8, 1, seed)[:, 0]
        gaps = np.diff(np.sort(points))
        assert gaps == pytest.approx(np.full(7, 1 / 8))
        if seed % ROTATIONS == 0:
            assert unit_points(12, 1, seed)[:8, 0] == pytest.approx(points)
    assert not np.allclose(unit_points(8, 1, 0), unit_points(8, 1, 1))


def test_a_studys_first_point_is_uniform_over_the_unit_interval():
    """The shift, and so any one point, is uniform on [0, 1) over groups of tuning seeds
    (Kolmogorov-Smirnov over 2,000 groups; a scramble of 8 points would keep each in its eighth):
    the groups are independent draws of where the trials fall."""
    firsts = [unit_points(8, 2, ROTATIONS * group + 1)[0] for group in range(2000)]
    for column in np.array(firsts).T:
        assert stats.kstest(column, "uniform").pvalue > 1e-3
    # a coordinate's shift does not depend on how many coordinates there are
    assert unit_points(8, 3, 5)[:, 1] == pytest.approx(unit_points(8, 2, 5)[:, 1])


def test_a_search_key_cannot_move_another_keys_points():
    """A key that sorts before learning_rate (b1), given to one variant only, leaves that variant's
    learning-rate points where every other variant has them."""
    spaces = [{"learning_rate": RANGE, "b1": (0.5, 0.99)}, {"learning_rate": RANGE}]
    dimensions = point_dimensions(spaces)
    assert dimensions == ["learning_rate", "b1"]
    with_b1 = halton_points(spaces[0], 8, 11, dimensions)
    without = halton_points(spaces[1], 8, 11, dimensions)
    assert [p["learning_rate"] for p in with_b1] == [p["learning_rate"] for p in without]
    # and a rule whose rate is a schedule (learning_rate.init_value) is tried at the same rates
    schedule = halton_points({"learning_rate.init_value": RANGE}, 8, 11, dimensions)
    assert [p["learning_rate.init_value"] for p in schedule] == [
        p["learning_rate"] for p in without
    ]
    # alone, the rate is the first coordinate too
    assert halton_points(spaces[1], 8, 11) == without


def test_points_cover_the_log_range_of_every_key():
    points = halton_points({"learning_rate": (1e-5, 1e-1), "tau": (1e-8, 1e-4)}, 16, 7)
    for key, (low, high) in (("learning_rate", (1e-5, 1e-1)), ("tau", (1e-8, 1e-4))):
        logs = np.log10([p[key] for p in points])
        assert logs.min() >= math.log10(low) and logs.max() <= math.log10(high)
        assert len(set(np.floor(logs))) == 4  # every decade is tried
    # the rate's coordinate (base 2): 16 shifted points of 4 decades, four in each
    rates = np.log10([p["learning_rate"] for p in points]) + 5
    assert list(np.bincount(np.floor(rates).astype(int))) == [4, 4, 4, 4]


def test_a_folder_of_this_study_under_the_earlier_protocol_is_refused_in_one_line(tmp_path):
    """A study folder written when the tuning studies shared their evaluation seeds (study.json
    without a protocol) is not resumed under the new one: its runs would mix both."""
    import json

    from physgrad.comparison.study_folder import PROTOCOL, record_study

    overrides = ["task=toy", "optim=adam,gd"]
    (tmp_path / "study.json").write_text(json.dumps({"overrides": overrides, "config_dir": None}))
    with pytest.raises(UserError, match="run by an earlier physgrad") as error:
        record_study(tmp_path, overrides, None)
    assert "\n" not in str(error.value)
    assert json.loads((tmp_path / "study.json").read_text()).get("protocol") is None  # untouched
    (tmp_path / "new").mkdir()
    record_study(tmp_path / "new", overrides, None)
    assert json.loads((tmp_path / "new" / "study.json").read_text())["protocol"] == PROTOCOL


@pytest.mark.parametrize(
    "stored, said",
    [
        ("[1]", "its study.json is not a study record"),
        ('"x"', "its study.json is not a study record"),
        ('{"overrides": "x"}', "its study.json is not a study record"),
        ('{"overrides": [1, {"a": 2}]}', "1 {'a': 2}"),
        ('{"overrides": ["task=toy\\u001b]0;pwned\\u0007"]}', "task=toy\ufffd]0;pwned\ufffd"),
    ],
)
def test_a_study_json_from_someone_else_is_one_line_whatever_it_holds(tmp_path, stored, said):
    """study.json is data from whoever wrote the folder: a list, a string, overrides that are no
    text, or a terminal escape give one line naming the folder (it was a 25-line traceback), with
    the stored command's control characters replaced, and the file is left as it was."""
    from physgrad.comparison.study_folder import record_study

    (tmp_path / "study.json").write_text(stored)
    with pytest.raises(UserError, match="holds another study") as error:
        record_study(tmp_path, ["task=toy", "optim=adam,gd"], None)
    assert f"({said})" in str(error.value) and "\n" not in str(error.value)
    assert "\x1b" not in str(error.value) and (tmp_path / "study.json").read_text() == stored


@pytest.mark.parametrize(
    "loss, held_out, passed, fragment",
    [
        (0.5, 0.4, True, "loss 0.5, held-out loss 0.4"),
        (0.0, 0.0, True, "loss 0"),  # an exact fit is a loss
        (-0.3, 0.4, False, "negative at initialisation: loss -0.3"),
        (0.3, -2.0, False, "held-out loss -2"),
        (float("nan"), -2.0, False, "not finite at initialisation: loss"),
    ],
)
def test_physgrad_check_refuses_a_negative_loss_in_one_line(loss, held_out, passed, fragment):
    """The scene check's 'finite' row: a signed objective has no loss ratio, so physgrad check
    refuses it before anything trains, in one line that says what to change."""
    import types

    import jax.numpy as jnp

    from physgrad.scene_check import _finite_check

    scene = types.SimpleNamespace(evaluate=lambda params, test_set: {"loss": jnp.array(held_out)})
    seeds = types.SimpleNamespace(test_sets=jnp.zeros((1, 3)))
    check = _finite_check(scene, seeds, None, jnp.zeros(3), jnp.array(loss))
    assert check.passed == passed and fragment in check.detail and "\n" not in check.detail


def test_the_same_command_with_other_defaults_is_another_study(tmp_path):
    """A changed default of the scene or rule (physgrad upgraded: the book's toy replaced the
    3 x 20 one) must not resume the earlier study's tuning: the default folder is another, and an
    explicit folder is refused in one line; a record from before the fingerprint cannot be told."""
    import json

    from omegaconf import OmegaConf

    from physgrad.comparison.study_folder import configuration_of, default_folder, record_study

    def config(hidden):
        return OmegaConf.create({"task": {"hidden": hidden}, "optim": {"name": "adam"}, "seed": 3})

    overrides = ["task=toy", "optim=adam,gd"]
    old, new = configuration_of([config([20, 20, 20])]), configuration_of([config([7])])
    assert old != new and configuration_of([config([7])]) == new
    # the seed (and anything outside task, optim and precision) is not the scene's
    seeded = config([7])
    seeded.seed = 4
    assert configuration_of([seeded]) == new
    assert default_folder(overrides, None, "toy", old) != default_folder(
        overrides, None, "toy", new
    )
    record_study(tmp_path, overrides, None, old)
    record_study(tmp_path, overrides, None, old)  # the same study resumes
    with pytest.raises(UserError, match="other settings of its scene or rules") as error:
        record_study(tmp_path, overrides, None, new)
    assert "\n" not in str(error.value)
    assert json.loads((tmp_path / "study.json").read_text())["configuration"] == old
    # written before the fingerprint was kept: cannot be checked, and now records it
    record = json.loads((tmp_path / "study.json").read_text())
    del record["configuration"]
    (tmp_path / "study.json").write_text(json.dumps(record))
    record_study(tmp_path, overrides, None, new)
    assert json.loads((tmp_path / "study.json").read_text())["configuration"] == new


def test_the_tuning_studies_points_interleave():
    """The studies of one design, on consecutive tuning seeds (tune_seed + k, one compare or one
    each), rotate one shifted Halton set by quarters of its grid cell: at 2 to 32 trials, in the
    rate's coordinate (base 2) and the next (base 3), every two of four studies' point sets lie at
    least a quarter cell apart, for any group of seeds; each study's points keep their spacing."""
    for count in range(2, 33):
        for group in range(12):
            sets = [unit_points(count, 2, 4 * group + k) for k in range(4)]
            for d in (0, 1):
                gap = halton_cell(count, d) / 4
                for i in range(4):
                    for j in range(i + 1, 4):
                        distance = np.abs(sets[i][:, d, None] - sets[j][None, :, d]).min()
                        assert distance >= gap * (1 - 1e-9), (count, group, d, i, j)
    # at 16 trials over Adam's four decades: 1/64 of the range, 0.0625 decade apart
    assert halton_cell(16, 0) / 4 == 1 / 64


def test_independent_shifts_would_let_two_studies_points_coincide():
    """Why the studies interleave: with an independent shift per tuning seed (here seeds of two
    different groups), two studies' 16 points lie within a hundredth of the cell for some seeds."""
    closest = min(
        np.abs(
            unit_points(16, 1, 4 * s)[:, 0, None] - unit_points(16, 1, 4 * s + 4)[None, :, 0]
        ).min()
        for s in range(200)
    )
    assert closest < halton_cell(16, 0) / 100
