"""Unit layer of the toy's figure (experiments/toy_figure.py) on synthetic runs: the kept table
holds the medians over seeds on the clock's grid, the probe seed's path and the medians at the end;
the figure and its summary come out the same from the table as from the runs; a table from
elsewhere is data, refused in one line where it is not the toy's."""

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))

import toy_figure  # noqa: E402

from physgrad.errors import UserError  # noqa: E402
from physgrad.results import Run  # noqa: E402


def run(seed: int, scale: float, level: float, end: float = 8.0, status="completed") -> Run:
    """A toy run whose loss falls as level * (1 + seed) * exp(-t) on the calibrated clock, with
    its share saturated rising linearly to 0.1 * seed and the probe moving on a line."""
    t = np.linspace(0.0, end, 41)
    return Run(
        Path(f"s{seed}"),
        {"task": "toy", "seed": seed, "status": status},
        {},
        {
            "calibrated_time": t,
            "loss": level * (1 + seed) * np.exp(-t),
            "hidden_magnitude": np.full_like(t, 0.5),
            "hidden_saturated": 0.1 * seed * t / end,
            "hidden_spread": np.full_like(t, 0.2 + 0.01 * seed),
            "probe_y1": t / end,
            "probe_y2": -t / end,
        },
    )


@pytest.fixture
def table():
    return {
        1.0: {
            "adam": [run(s, 1.0, 1.0) for s in range(5)],
            "hig": [run(s, 1.0, 0.1) for s in (3, 4, 5)],
        },
        0.01: {"gauss_newton": [run(s, 0.01, 2.0, end=4.0) for s in range(3)]},
    }


def test_the_kept_table_holds_the_medians_the_path_and_the_ends(table):
    frame = toy_figure.panels(table)
    assert set(frame["kind"]) == {"curve", "path", "final"}
    adam = frame[(frame["scale"] == 1.0) & (frame["variant"] == "adam")]
    curve = adam[adam["kind"] == "curve"]
    assert len(curve) == toy_figure.GRID and curve["t"].iloc[-1] == pytest.approx(8.0)
    # the median seed of 0..4 is seed 2: 3 * exp(-t), and saturated 0.2 t / 8 (to interpolation)
    t = curve["t"].to_numpy()
    grid_loss = np.interp(t, np.linspace(0, 8, 41), 3 * np.exp(-np.linspace(0, 8, 41)))
    np.testing.assert_allclose(curve["loss"], grid_loss, rtol=1e-12)
    np.testing.assert_allclose(curve["hidden_saturated"], 0.2 * t / 8, atol=1e-12)
    final = adam[adam["kind"] == "final"].iloc[0]
    assert final["loss"] == pytest.approx(3 * np.exp(-8.0))
    assert final["hidden_spread"] == pytest.approx(0.22) and final["hidden_saturated"] == 0.2
    assert final["seeds"] == 5 and final["diverged"] == 0
    path = frame[(frame["variant"] == "hig") & (frame["kind"] == "path")]
    assert set(path["seed"]) == {3}  # the lowest seed's
    np.testing.assert_allclose(path["y2"], -path["y1"], atol=1e-12)
    assert path["y1"].iloc[0] == 0 and path["y1"].iloc[-1] == pytest.approx(1.0)
    # lambda 0.01's runs end at 4 s: its own grid, not lambda 1's
    gn = frame[(frame["variant"] == "gauss_newton") & (frame["kind"] == "curve")]
    assert gn["t"].max() == pytest.approx(4.0)


def test_the_figure_and_summary_from_the_kept_table_are_those_from_the_runs(table, tmp_path):
    kept = tmp_path / "toy_book.csv"
    (tmp_path / "empty").mkdir()
    images, text = toy_figure.write([tmp_path / "empty"], tmp_path / "out")
    assert images == [] and "no completed runs" in text
    frame = toy_figure.panels(table)
    kept.write_text(frame.to_csv(index=False, float_format="%.6g"))
    again = toy_figure.read_panels(kept)
    assert toy_figure.summary(again) == toy_figure.summary(frame)
    assert "| 1 | adam | 5 | 0 | 0.00101 | 0.22 | 20% |" in toy_figure.summary(again)
    assert toy_figure.main(["--evidence", str(kept), str(tmp_path / "toy.png")]) == 0
    assert (tmp_path / "toy.png").stat().st_size > 10_000


def test_the_committed_table_draws_the_committed_figure(tmp_path):
    frame = toy_figure.read_panels(REPO / "docs" / "evidence" / "toy_book.csv")
    assert set(frame["scale"]) == {1.0, 0.01}
    assert set(frame["variant"]) == {"adam", "gauss_newton", "hig"}
    toy_figure.plot(frame, tmp_path / "toy.png", "")
    assert (tmp_path / "toy.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    "damage, why",
    [
        (lambda text: text.replace("hidden_spread", "spread"), "columns missing"),
        (lambda text: text.replace(",curve,", ",other,", 1), "kinds"),
        (lambda text: text.replace(",curve,", ",curve,zero", 1), "not a number"),
        (lambda text: text.replace("adam", "sgd"), "unknown clock or variant"),
        (lambda text: "", "not a kept toy table"),
    ],
)
def test_a_table_that_is_not_the_toys_is_refused_in_one_line(table, tmp_path, damage, why):
    good = toy_figure.panels(table).to_csv(index=False)
    bad = tmp_path / "toy_book.csv"
    bad.write_text(damage(good))
    with pytest.raises(UserError, match=why) as error:
        toy_figure.read_panels(bad)
    assert "\n" not in str(error.value)
    assert toy_figure.main(["--evidence", str(bad), str(tmp_path / "toy.png")]) == 2
    assert not (tmp_path / "toy.png").exists()


def test_a_kept_table_at_a_link_is_not_followed(table, tmp_path):
    real = tmp_path / "real.csv"
    real.write_text(toy_figure.panels(table).to_csv(index=False))
    os.symlink(real, tmp_path / "toy_book.csv")
    with pytest.raises(UserError, match="not a kept toy table"):
        toy_figure.read_panels(tmp_path / "toy_book.csv")
