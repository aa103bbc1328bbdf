"""Integration layer of files from somebody else: crafted results files are unreadable with a reason
while the report goes on, read no other file and have their text cleaned, oversized columns and
configs are refused, and every `_target_`, Hydra's own included, passes one allow-list policy."""

import h5py
import numpy as np
import pytest
from omegaconf import OmegaConf

from physgrad.files import clean_text
from physgrad.report import write_report
from physgrad.results import parse_config, read_final, read_run
from physgrad.runs import collect
from physgrad.sweeps import job_folders, read_manifest
from tests.helpers import SECRET
from tests.unit.test_foreign import (
    good_run,
    rewrite,
    set_attr,
)


def replace_column(group, key, data):
    def edit(f):
        del f[group][key]
        f[group].create_dataset(key, data=data)

    return edit


def external_storage(secret):
    def edit(f):
        del f["eval"]["loss"]
        f["eval"].create_dataset("loss", shape=(3,), dtype="f8", external=[(str(secret), 0, 24)])

    return edit


def external_link(secret_h5):
    def edit(f):
        del f["train"]
        f["train"] = h5py.ExternalLink(str(secret_h5), "/train")

    return edit


def virtual_column(secret_h5):
    def edit(f):
        layout = h5py.VirtualLayout(shape=(3,), dtype="f8")
        layout[:] = h5py.VirtualSource(str(secret_h5), "/eval/loss", shape=(3,))
        del f["eval"]["loss"]
        f["eval"].create_virtual_dataset("loss", layout)

    return edit


def soft_link(f):
    f["elsewhere"] = np.ones(3)
    del f["eval"]["loss"]
    f["eval"]["loss"] = h5py.SoftLink("/elsewhere")


CRAFTED = {
    "config is an int": set_attr("config", "42"),
    "config is a list": set_attr("config", "[1, 2]"),
    "config is bad YAML": set_attr("config", "task: [unclosed"),
    "config holds an alias": set_attr("config", "a: &x [1]\nb: *x\n"),
    "seed is text": set_attr("seed", "zero"),
    "seed is an array": set_attr("seed", np.arange(3)),
    "status unknown": set_attr("status", "great"),
    "iterations is text": set_attr("iterations", "many"),
    "train_seconds is text": set_attr("train_seconds", "3 s"),
    "task is a number": set_attr("task", 7),
    "wall_time is text": replace_column("eval", "wall_time", np.array([b"a", b"b", b"c"])),
    "loss is 2-D": replace_column("eval", "loss", np.ones((3, 2))),
    "loss is text": replace_column(
        "train", "loss", np.array(["1", "2", "3"], dtype=h5py.string_dtype())
    ),
    "unequal columns": replace_column("eval", "loss", np.ones(5)),
    "a soft link": soft_link,
}


def no_seed(f):
    del f.attrs["seed"]


def no_wall_time(f):
    del f["eval"]["wall_time"]


CRAFTED["seed missing"] = no_seed
CRAFTED["eval without wall_time"] = no_wall_time


@pytest.mark.parametrize("kind", sorted(CRAFTED))
def test_a_crafted_file_is_unreadable_with_a_reason_and_the_report_goes_on(
    tmp_path, kind, report_figures_skipped
):
    good_run(tmp_path / "good")
    rewrite(good_run(tmp_path / "bad", seed=1), CRAFTED[kind])
    with pytest.raises(ValueError) as caught:
        read_run(tmp_path / "bad" / "results.h5")
    assert "\n" not in str(caught.value) and str(tmp_path / "bad") in str(caught.value)
    with pytest.raises(ValueError):
        read_final(tmp_path / "bad" / "results.h5")
    body = write_report([tmp_path], out_dir=tmp_path / "report")
    assert "unreadable: " in body and "bad/results.h5" in body
    runs, unreadable, _ = collect([tmp_path])
    assert [run.path.parent.name for run in runs] == ["good"] and len(unreadable) == 1
    assert [[run.path.parent.name for run in drawn] for drawn in report_figures_skipped] == [
        ["good"]
    ]


@pytest.mark.parametrize("how", ["external storage", "external link", "virtual dataset"])
def test_a_file_cannot_read_other_files_into_a_report(
    tmp_path, secret_file, how, report_figures_skipped
):
    source = good_run(tmp_path / "source")  # an HDF5 file a link could point at
    rewrite(source, set_attr("note", SECRET))
    edit = {
        "external storage": external_storage(secret_file),
        "external link": external_link(source),
        "virtual dataset": virtual_column(source),
    }[how]
    crafted = rewrite(good_run(tmp_path / "crafted", seed=1), edit)
    with pytest.raises(ValueError, match="external|virtual|link"):
        read_run(crafted)
    with pytest.raises(ValueError):
        read_final(crafted)
    write_report([crafted, source], out_dir=tmp_path / "report")
    curves = (tmp_path / "report" / "curves.csv").read_text()
    assert "crafted" not in curves and SECRET[:20] not in curves
    assert SECRET[:20] not in (tmp_path / "report" / "report.md").read_text()


def test_text_is_cleaned_of_terminal_escapes_and_cut(tmp_path):
    path = good_run(tmp_path / "run", variant="adam\x1b[31m$x^2$")
    rewrite(path, set_attr("hostname", "h" * 10_000))
    rewrite(path, set_attr("reason", "\x1b]0;owned\x07\x1b[2Jcleared"))
    run = read_run(path)
    assert "\x1b" not in run.attrs["reason"] and "\x07" not in run.attrs["reason"]
    assert "\x1b" not in run.variant and run.variant.endswith("$x^2$")
    assert len(run.attrs["hostname"]) < 2100
    # a `$` label is drawn as text, not mathtext
    body = write_report([path], out_dir=tmp_path / "report")
    assert "\x1b" not in body and (tmp_path / "report" / "loss_vs_time.png").is_file()
    assert clean_text("a\u202eb\nc") == "a\ufffdb c" and clean_text("a\nb", lines=True) == "a\nb"


def test_sweep_manifests_of_other_types_are_ignored(tmp_path):
    (tmp_path / "jobs.yaml").write_text("jobs: 7\n")
    assert read_manifest(tmp_path) is None
    (tmp_path / "jobs.yaml").write_text("jobs: [[a=1], [{b: 2}]]\n")
    assert read_manifest(tmp_path) is None
    (tmp_path / "j" / ".hydra").mkdir(parents=True)
    (tmp_path / "j" / ".hydra" / "overrides.yaml").write_text("{a: 1}\n")
    assert job_folders(tmp_path) == {}


def test_columns_that_unpack_far_beyond_the_file_are_refused(tmp_path):
    """A few MB of gzip-compressed zeros that would unpack into 448 MiB: refused in one line before
    anything is read (physgrad writes its columns uncompressed, so its own files hold
    about as many bytes as their columns)."""
    path = good_run(tmp_path / "run")
    assert read_run(path).train["loss"].size == 3

    def bomb(f):
        for group in ("train", "eval"):
            for key in list(f[group]):
                del f[group][key]
                f[group].create_dataset(key, data=np.zeros(1 << 23), compression="gzip")

    rewrite(path, bomb)
    assert path.stat().st_size < (8 << 20)
    with pytest.raises(ValueError, match="unpack to") as refused:
        read_run(path)
    assert "\n" not in str(refused.value)


def test_a_config_with_more_settings_than_any_physgrad_run_is_refused_in_one_line():
    """A stored config of one key more than the limit (10,000, under the byte limit) would make a
    table of as many columns: refused before it is flattened."""
    from physgrad.results import CONFIG_KEYS_LIMIT

    text = "\n".join(f"k{i}: 0" for i in range(CONFIG_KEYS_LIMIT + 1))
    assert parse_config(text.rsplit("\n", 1)[0])  # the limit itself is read
    with pytest.raises(ValueError, match=f"more than {CONFIG_KEYS_LIMIT} settings") as caught:
        parse_config(text)
    assert "\n" not in str(caught.value)
    nested = "a:\n" + "\n".join(f"  k{i}: [1, 2]" for i in range(CONFIG_KEYS_LIMIT))
    with pytest.raises(ValueError, match="settings"):
        parse_config(nested)
    assert parse_config("a: 1\nb: {c: [1, 2]}") == {"a": 1, "b": {"c": [1, 2]}}


@pytest.mark.parametrize(
    "override",
    [
        "task._target_=os.system",
        "optim._target_=subprocess.run",
        "+optim.learning_rate={_target_:os.system,command:'touch MARK'}",
        "task._target_=builtins.exec",
    ],
)
def test_every_target_physgrad_calls_passes_one_policy(tmp_path, override, monkeypatch):
    """A `_target_` naming a system function (a shell command, code, a subprocess) is refused in one
    line wherever it stands (the task, the rule, a nested schedule, a tracker) and nothing runs."""
    from physgrad.errors import UserError
    from physgrad.experiment import run_experiment
    from physgrad.trackers import build_trackers
    from tests.helpers import load

    monkeypatch.chdir(tmp_path)
    outcome, _ = run_experiment(load("task=toy", "trainer.iterations=2", override), tmp_path / "r")
    assert outcome.status == "refused" and "not allowed" in outcome.reason
    assert "\n" not in outcome.reason and not (tmp_path / "MARK").exists()
    evil = {"evil": {"_target_": "os.system", "command": "touch MARK"}}
    with pytest.raises(UserError, match="logger.evil._target_=os.system is not allowed"):
        build_trackers(OmegaConf.create(evil))
    assert not (tmp_path / "MARK").exists()


HOSTILE_TARGETS = [
    # each ran a command, read a pickle or wrote a file under the deny list it replaces
    "glob.os.system",
    "pathlib.os.system",
    "tempfile._os.system",
    "pydoc.pipepager",
    "timeit.timeit",
    "cProfile.run",
    "asyncio.run",
    "asyncio.create_subprocess_shell",
    "numpy.load",
    "pandas.read_pickle",
    "yaml.unsafe_load",
    "io.open",
    "pathlib.Path.write_text",
    "os.system",
    "builtins.exec",
    "hydra.utils.get_object",
    "physgrad.files.replace_file",  # physgrad's own, but no scene, rule or tracker
    "antigravity.fly",  # importing it opens a browser: refused before any import
]


@pytest.mark.parametrize("target", HOSTILE_TARGETS)
def test_the_target_policy_is_an_allow_list(target, tmp_path, monkeypatch):
    """Every target that is not one of physgrad's scenes, rules or trackers, an optax function or
    the user's own module is refused in one line, at the top and nested (a schedule), before it is
    called; a module of the user's that hands on a system function is refused by what it resolves
    to; a package the user names in PHYSGRAD_TARGET_MODULES is allowed."""
    import sys

    from physgrad.errors import UserError
    from physgrad.validate import TARGET_MODULES_ENV, allowed_target, call_target

    monkeypatch.chdir(tmp_path)
    before = set(sys.modules)
    with pytest.raises(UserError, match="is not allowed") as caught:
        call_target("task", {"_target_": target, "path": str(tmp_path / "MARK")})
    assert "\n" not in str(caught.value) and f"task._target_={target}" in str(caught.value)
    nested = {"_target_": "optax.sgd", "learning_rate": {"_target_": target}}
    with pytest.raises(UserError, match="learning_rate._target_=.* is not allowed"):
        call_target("optim", nested)
    assert not (tmp_path / "MARK").exists()
    assert "antigravity" not in set(sys.modules) - before
    # the user's own module: allowed; one that hands on os.system: refused by what it resolves to
    (tmp_path / "mylab.py").write_text("import os\n\ndef build(**kw):\n    return kw\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    allowed_target("task", "mylab.build")
    with pytest.raises(UserError, match="mylab.os.system is not allowed"):
        call_target("task", {"_target_": "mylab.os.system", "command": "touch MARK"})
    assert not (tmp_path / "MARK").exists()
    monkeypatch.setenv(TARGET_MODULES_ENV, "pandas")
    allowed_target("task", "pandas.DataFrame")


@pytest.mark.parametrize(
    "planted",
    [
        "callbacks: {{planted: {{_target_: os.makedirs, name: {mark}}}}}",
        # make test checks the callback; make test-long the logging handler and formatter
        pytest.param(
            "job_logging: {{handlers: {{planted: {{class: os.makedirs, name: {mark}}}}}}}",
            marks=pytest.mark.long,
        ),
        pytest.param(
            "hydra_logging: {{formatters: {{planted: {{(): os.makedirs, name: {mark}}}}}}}",
            marks=pytest.mark.long,
        ),
    ],
)
def test_hydra_s_own_targets_from_a_config_folder_pass_the_same_policy(tmp_path, planted):
    """A user's config folder whose experiment plants a Hydra callback, a logging handler class or
    a formatter factory naming os.makedirs: refused in one line at the door, before Hydra
    instantiates anything, and the folder it names is not made; from the command line too.
    physgrad's own callback and job log, and Hydra's defaults, pass."""
    from physgrad.configs import check_overrides
    from physgrad.errors import UserError

    mark = tmp_path / "MARK"
    (tmp_path / "conf" / "experiment").mkdir(parents=True)
    text = "# @package _global_\nhydra:\n  " + planted.format(mark=mark) + "\n"
    (tmp_path / "conf" / "experiment" / "planted.yaml").write_text(text)
    with pytest.raises(UserError, match="hydra.* is not allowed") as caught:
        check_overrides(["task=toy", "+experiment=planted"], False, [tmp_path / "conf"])
    assert "\n" not in str(caught.value) and not mark.exists()
    line = [
        "+hydra.callbacks.planted._target_=os.makedirs",
        f"+hydra.callbacks.planted.name={mark}",
    ]
    with pytest.raises(UserError, match="hydra.callbacks.planted._target_=os.makedirs"):
        check_overrides(["task=toy", *line], False)
    assert not mark.exists()
    check_overrides(["task=toy", "hydra/launcher=basic"], False)  # physgrad's and Hydra's own


@pytest.mark.parametrize(
    "planted",
    [
        ["hydra.launcher._target_=os.makedirs", "+hydra.launcher.name={mark}"],
        ["hydra.sweeper._target_=os.makedirs", "+hydra.sweeper.name={mark}"],
    ],
)
def test_a_sweep_s_launcher_and_sweeper_targets_pass_the_policy_too(tmp_path, planted):
    """A launcher or sweeper target naming os.makedirs on the command line of a sweep (seed=0,1, a
    range, a list of options: the hydra section is composed for the sweep's first job) is refused
    in one line by physgrad's policy, not left to Hydra's own traceback; physgrad's SLURM
    launcher and Hydra's basic sweeper pass."""
    from physgrad.configs import check_overrides
    from physgrad.errors import UserError

    mark = tmp_path / "MARK"
    line = [override.format(mark=mark) for override in planted]
    for sweep in (["seed=0,1"], ["seed=range(0,3)", "optim=adam,gd"]):
        with pytest.raises(UserError, match=r"hydra\.(launcher|sweeper)\._target_=os.makedirs"):
            check_overrides(["task=toy", *sweep, *line], True)
    assert not mark.exists()
    check_overrides(["task=toy", "seed=0,1", "hydra/launcher=slurm"], True)
