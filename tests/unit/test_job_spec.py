"""Unit layer of the door (physgrad.job_spec.check): a composed config becomes typed, frozen
settings or a refusal with the files that say so; and below the door no function takes a
DictConfig. Nothing is built or trained."""

import ast
import dataclasses
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from physgrad.errors import UserError
from physgrad.job_spec import JobSpec, Refusal, calibration_of, check, checked
from physgrad.members import comparable_config
from tests.helpers import load

PACKAGE = Path(__file__).resolve().parents[2] / "physgrad"


def test_a_config_becomes_typed_frozen_settings():
    spec = check(load("task=toy", "optim=adam", "seed=5", "seeds=3", "precision=64"))
    assert isinstance(spec, JobSpec)
    assert (spec.task_name, spec.rule_name, spec.seed, spec.precision) == ("toy", "adam", 5, 64)
    assert isinstance(spec.task, dict) and isinstance(spec.optim, dict)  # plain data, resolved
    assert [(m.seed, str(m.path)) for m in spec.members] == [
        (5, "seed=5/results.h5"),
        (6, "seed=6/results.h5"),
        (7, "seed=7/results.h5"),
    ]
    assert [m.attributes["seed"] for m in spec.members] == [5, 6, 7]
    assert spec.label == "toy/adam seed 5 (+2)"
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.seed = 0


def test_trial_members_record_their_own_values_and_compare_as_a_job_of_one_trial():
    spec = check(load("task=toy", "optim=adam", "+trial_values={learning_rate: [0.1, 0.01]}"))
    assert spec.trial_values == {"learning_rate": (0.1, 0.01)}
    assert [str(m.path) for m in spec.members] == ["trial=0/results.h5", "trial=1/results.h5"]
    assert [m.config["optim"]["learning_rate"] for m in spec.members] == [0.1, 0.01]
    alone = check(load("task=toy", "optim=adam", "optim.learning_rate=0.01"))
    assert spec.members[1].config == alone.members[0].config  # resumes as that job would


@pytest.mark.parametrize(
    ("override", "named", "files"),
    [
        ("precision=16", "precision", 1),
        ("seed=-1", "seed", 1),
        ("trainer.time_budget=1e-300", "trainer.time_budget", 1),
        ("seeds=2000", "seeds=2000", 0),  # refused before one file per seed is named
        ("+trial_values={learning_rate: [-1]}", "trial_values", 0),
    ],
)
def test_a_refusal_says_what_to_change_and_which_files_record_it(override, named, files):
    refusal = check(load("task=toy", override))
    assert isinstance(refusal, Refusal)
    assert named in refusal.reason and "\n" not in refusal.reason
    assert len(refusal.members) == files
    with pytest.raises(Exception, match=named.replace("+", r"\+").split("=")[0]):
        checked(load("task=toy", override))


def test_the_members_config_is_the_config_a_re_run_compares():
    cfg = load("task=toy", "overwrite=true")
    (member,) = checked(cfg).members
    assert member.config == comparable_config(cfg) and "overwrite" not in member.config


def test_trackers_and_a_calibration_are_checked_at_the_door_into_plain_data():
    """logger=... reaches the trackers as plain settings (a refused job keeps them, its outcome is
    still tracked); a logger or calibrate that is not a mapping is one line."""
    spec = check(load("task=toy", "logger=tensorboard"))
    assert isinstance(spec.trackers["tensorboard"], dict)
    assert spec.trackers["tensorboard"]["_target_"] == "physgrad.trackers.TensorBoard"
    refused = check(load("task=toy", "logger=tensorboard", "trainer.iterations=-1"))
    assert isinstance(refused, Refusal) and "tensorboard" in refused.trackers
    assert check(load("task=toy")).trackers == {}
    cfg = load("task=toy")
    OmegaConf.update(cfg, "logger", 7, force_add=True)
    bad = check(cfg)
    assert isinstance(bad, Refusal) and bad.reason.startswith("logger=7: give a mapping")
    assert calibration_of(load("task=toy")) is None
    cfg = load("task=toy", "seed=3")
    OmegaConf.update(cfg, "calibrate", {}, force_add=True)
    cfg.calibrate = {"adam": load("task=toy"), "gd": load("task=toy", "optim=gd")}
    request = calibration_of(cfg)
    assert request.seed == 3 and request.configs["gd"]["optim"]["name"] == "gd"
    assert isinstance(request.configs["adam"], dict)
    cfg.calibrate = {"adam": 1}
    with pytest.raises(UserError, match="calibrate: give a mapping of variant"):
        calibration_of(cfg)


# the modules below the door: they take a JobSpec, never the composed config
BELOW_THE_DOOR = [
    "experiment",
    "refusals",
    "resume",
    "runner",
    "training",
    "run_figures",
    "trackers",
]
# the one convenience that takes a config: it hands it to the door first
DOOR_ENTRIES = {("experiment", "run_experiment")}


@pytest.mark.parametrize("module", BELOW_THE_DOOR)
def test_below_the_door_no_function_takes_a_dict_config(module):
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    taking = [
        node.name
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and (module, node.name) not in DOOR_ENTRIES
        and any(
            arg.annotation is not None and "DictConfig" in ast.unparse(arg.annotation)
            for arg in [*node.args.args, *node.args.kwonlyargs, *node.args.posonlyargs]
        )
    ]
    assert not taking, f"{module}.py: {taking} take a DictConfig; pass the JobSpec"


@pytest.mark.parametrize(
    "override, named",
    [
        ("task._target_=os.system", "task._target_=os.system"),
        ("optim._target_=subprocess.run", "optim._target_=subprocess.run"),
        ("+optim.learning_rate={_target_:os.system}", "optim.learning_rate._target_=os.system"),
    ],
)
def test_a_target_outside_the_allow_list_is_refused_at_the_door_before_anything_is_imported(
    override, named, monkeypatch
):
    import importlib

    cfg = load("task=toy", override)
    imported = []
    real = importlib.import_module
    monkeypatch.setattr(
        importlib, "import_module", lambda name, *a: imported.append(name) or real(name, *a)
    )
    spec = check(cfg)
    assert isinstance(spec, Refusal) and named in spec.reason and "is not allowed" in spec.reason
    assert spec.members  # each member's results file says why
    assert imported == []  # refused by name: neither the module nor the function was imported
