"""Unit layer of the tests of: the scenes' kinds on the claims and leaderboard pages
(experiments/scene_kinds.py): the kept table is what building the scenes gives, is read as data,
and renders each scene's loop, batch, parameters and step costs."""

import json
import sys

import pytest

from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))
import scene_kinds  # noqa: E402

from physgrad.errors import UserError  # noqa: E402


@pytest.mark.parametrize(
    "key", ["toy", *(pytest.param(k, marks=pytest.mark.long) for k in ("oscillator", "cart_4"))]
)
def test_the_kept_rows_are_what_building_the_scene_gives(key):
    """Rebuilt (no training), the scene's row is the committed one: nothing in the table is
    typed by hand. (The toy here, two more in make test-long; `--keep` rebuilds all.)"""
    kind = next(k for k in scene_kinds.SCENES if k.key == key)
    kept = scene_kinds.read_kinds(scene_kinds.KINDS)[key]
    measured = {k: str(v) for k, v in scene_kinds.measure(kind).items()}
    assert measured == kept


@pytest.mark.parametrize(
    "text, why",
    [
        ("scene,loop\ntoy,none\n", "columns"),
        ("scene,loop,unroll,batch,train_size,parameters\ntoy,x,,64,,1e9\n", "parameters"),
        ("scene,loop,unroll,batch,train_size,parameters\ntoy,x,,-1,,30\n", "batch"),
    ],
)
def test_a_damaged_kinds_table_is_one_line(tmp_path, text, why):
    path = tmp_path / "scenes.csv"
    path.write_text(text)
    with pytest.raises(UserError, match=why):
        scene_kinds.read_kinds(path)


def test_the_table_gives_step_costs_in_adam_steps_and_says_where_there_are_none(tmp_path):
    clock = tmp_path / "x.calibration.json"
    costs = {"adam": 0.002, "gauss_newton": 0.02, "hig": 0.03}
    clock.write_text(json.dumps({"costs": {r: {"step_seconds": s} for r, s in costs.items()}}))
    kinds = {
        "a": {
            "loop": "closed",
            "unroll": "5",
            "batch": "8",
            "train_size": "256",
            "parameters": "1200",
        },
        "b": {
            "loop": "one solve",
            "unroll": "",
            "batch": "64",
            "train_size": "",
            "parameters": "30",
        },
    }
    table = scene_kinds.kinds_table([("a", "A", clock), ("b", "B", None), ("c", "C", None)], kinds)
    lines = table.splitlines()
    assert lines[2] == "| A | closed (5) | 8 of 256 | 1,200 | 2 | 10-15 |"
    assert lines[3] == "| B | one solve | 64 of fresh samples | 30 | - | - |"
    assert len(lines) == 4  # a scene without a kept row is left out, not invented


def test_a_rule_whose_preset_sets_another_batch_is_said_beside_the_scenes_batch(tmp_path):
    """The HIG paper's quantum dipole trains Adam at a batch of 256 and HIG at 16: the batch cell
    names the rules whose preset on the scene (tuning/<task>_<rule>.yaml) sets another batch, and
    no file of a scene whose name starts with this one's (quantum_control_adam) counts."""
    for folder in ("optim", "tuning"):
        (tmp_path / folder).mkdir()
    for rule in ("adam", "hig", "gauss_newton"):
        (tmp_path / "optim" / f"{rule}.yaml").write_text(f"name: {rule}\n")
    tuning = tmp_path / "tuning"
    (tuning / "wave_hig.yaml").write_text("optim:\n  tau: 1e-5\ntask:\n  batch_size: 16\n")
    (tuning / "wave_gauss_newton.yaml").write_text("task:\n  batch_size: 16\n")
    (tuning / "wave_adam.yaml").write_text("task:\n  batch_size: 256\n")  # the scene's own
    (tuning / "wave_control_adam.yaml").write_text("task:\n  batch_size: 8\n")
    kind = scene_kinds.SceneKind("wave", "wave", ("task=wave",), str(tmp_path))
    assert scene_kinds.rule_batches(kind, 256) == " (gauss_newton, hig: 16)"
    assert scene_kinds.rule_batches(kind, 16) == " (adam: 256)"
    (tuning / "wave_hig.yaml").write_text("task:\n  batch_size: 32\n")
    assert scene_kinds.rule_batches(kind, 256) == " (gauss_newton: 16; hig: 32)"
    other = scene_kinds.SceneKind("calm", "calm", ("task=calm",), str(tmp_path))
    assert scene_kinds.rule_batches(other, 256) == ""
