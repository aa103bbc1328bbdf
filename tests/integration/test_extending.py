"""Integration layer of a researcher's own scene and options: options from a user's folder are valid
and misspellings get a suggestion, a scene that cannot be built, has both an output and dynamics,
or a wrong loss or test set is refused in one line, and an unnamed option takes its file's name."""

import pytest

from physgrad.configs import check_overrides
from physgrad.errors import UserError
from physgrad.results import read_run
from physgrad.tasks import Scene, build_scene
from tests.helpers import REPO

EXAMPLE = REPO / "examples" / "custom_scene"


def test_options_from_a_users_folder_are_valid_and_misspellings_suggest(in_example):
    check_overrides(
        ["task=pendulum", "optim=lion", "task.gravity=3.7"], multirun=False, config_dirs=["conf"]
    )
    check_overrides(
        ["task=pendulum,poisson", "optim=lion,hig"], multirun=True, config_dirs=["conf"]
    )
    with pytest.raises(
        UserError, match=r"unknown optim 'lino': did you mean lion\? \(choose one of adam, .*lion"
    ):
        check_overrides(["task=pendulum", "optim=lino"], multirun=False, config_dirs=["conf"])
    with pytest.raises(UserError, match="did you mean task.gravity"):
        check_overrides(["task=pendulum", "task.gravty=3"], multirun=False, config_dirs=["conf"])
    with pytest.raises(UserError, match="unknown task 'pendulum'"):  # without the user's folder
        check_overrides(["task=pendulum"], multirun=False)


def not_a_scene(key: object = None) -> dict:
    """A function of the user's (a test module) that builds no scene."""
    return {}


@pytest.mark.parametrize(
    "node, fragment",
    [
        (
            {"_target_": "pendulum.build"},
            "pendulum.build needs task.gravity, task.length, task.damping, task.dt, task.unroll",
        ),
        (
            {
                "_target_": "pendulum.build",
                "gravity": 9.8,
                "length": 1,
                "damping": 0,
                "dt": 0.1,
                "unroll": 4,
                "hidden": [4],
                "train_size": 4,
                "test_size": 4,
                "mass": 1,
            },
            "task.mass is not a setting of pendulum.build",
        ),
        ({"_target_": "pendulum.biuld"}, "task._target_=pendulum.biuld cannot be imported"),
        (
            {"_target_": "nomodule.build"},
            "task._target_=nomodule.build cannot be imported (ModuleNotFoundError",
        ),
        (
            {"_target_": "tests.integration.test_extending.not_a_scene"},
            "returned dict, not a physgrad.tasks.Scene",
        ),
        ({"_target_": "builtins.dict"}, "task._target_=builtins.dict is not allowed"),
        # a function of the standard library is no scene of the user's: refused by name
        ({"_target_": "collections.OrderedDict"}, "collections.OrderedDict is not allowed"),
        ({}, "the task config has no _target_"),
    ],
)
def test_a_scene_that_cannot_be_built_is_one_line(in_example, node, fragment):
    import jax

    with pytest.raises(UserError) as error:
        build_scene({"name": "x", **node}, jax.random.PRNGKey(0))
    assert fragment in str(error.value) and "\n" not in str(error.value), str(error.value)


def test_a_scene_has_an_output_or_dynamics_but_not_both():
    with pytest.raises(UserError, match="exactly one of them"):
        Scene(init_params=lambda k: None, sample_loss=lambda y, s: 0.0, test_set={})
    with pytest.raises(UserError, match="needs draw_batch"):
        Scene(
            init_params=lambda k: None,
            sample_loss=lambda y, s: 0.0,
            test_set={},
            sample_output=lambda p, s: 0.0,
        )


def broken_toy(kind):
    """The toy scene with one thing a scene author might get wrong."""
    import dataclasses

    import jax.numpy as jnp

    from physgrad.tasks.toy import build

    def scene(key, **kwargs):
        good = build(key, **kwargs)
        if kind == "integer loss":
            return dataclasses.replace(
                good, sample_loss=lambda y, s: jnp.sum(y > 0).astype(jnp.int32)
            )
        if kind == "vector loss":
            return dataclasses.replace(good, sample_loss=lambda y, s: (y - s["target"]) ** 2)
        test_set = dict(good.test_set, target=good.test_set["target"].at[3, 0].set(jnp.nan))
        return dataclasses.replace(good, test_set=test_set)

    return scene


@pytest.mark.parametrize(
    "kind, fragment",
    [
        ("integer loss", "returns int32; it must be a real float"),
        ("vector loss", "returns (2,) per sample; it must return one number"),
        ("NaN test set", "its test_set holds 1 values that are NaN"),
    ],
)
def test_a_scene_with_a_wrong_loss_or_test_set_is_refused_in_one_line(
    tmp_path, monkeypatch, kind, fragment
):
    import physgrad.tasks.toy as toy
    from physgrad.experiment import run_experiment
    from tests.helpers import load

    monkeypatch.setattr(toy, "build", broken_toy(kind))
    outcome, path = run_experiment(load("task=toy", "trainer.iterations=2"), tmp_path)
    assert outcome.status == "refused" and fragment in outcome.reason, outcome.reason


def test_an_option_without_a_name_is_named_after_its_file(tmp_path):
    from physgrad.configs import compose
    from physgrad.experiment import run_experiment

    (tmp_path / "task").mkdir()
    (tmp_path / "task" / "heat.yaml").write_text(
        "_target_: physgrad.tasks.toy.build\nbatch_size: 4\nscale: 0.01\n"
        "hidden: [8]\ntest_size: 8\n"
    )
    cfg = compose(["task=heat", "trainer.iterations=2"], config_dirs=[tmp_path])
    assert cfg.task.name == "heat" and cfg.optim.name == "adam"
    outcome, path = run_experiment(cfg, tmp_path / "run")
    assert outcome.status == "completed" and read_run(path).attrs["task"] == "heat"


@pytest.mark.parametrize(
    "overrides",
    [
        ["task=pendulum", "optim=lion", "task.gravity=3.7"],  # the user's folder's options
        ["task=toy", "optim=hig", "seed=3"],  # physgrad's own
        ["task=heat"],  # an option without a name, named after its file
    ],
)
def test_a_checked_config_is_the_config_compose_gives(in_example, tmp_path, overrides):
    """checked_config composes once for its checks and the run: the same config, hydra section
    and names included, as compose(return_hydra_config=True) after check_overrides, and the
    memo of group choices shared by several runs does not change it."""
    from omegaconf import OmegaConf

    from physgrad.configs import checked_config, compose

    (tmp_path / "task").mkdir()
    (tmp_path / "task" / "heat.yaml").write_text(
        "_target_: physgrad.tasks.toy.build\nbatch_size: 4\nscale: 0.01\nhidden: [8]\n"
        "test_size: 8\n"
    )
    folders = ["conf", tmp_path]
    memo: dict = {}
    for _ in range(2):
        got = checked_config(overrides, folders, memo)
        want = compose(overrides, folders, return_hydra_config=True)
        assert OmegaConf.to_container(got) == OmegaConf.to_container(want)
    assert memo and all(len(by_choice) == 1 for by_choice in memo.values())
