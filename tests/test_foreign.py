"""Results files, report inputs and sweep folders from somebody else are data: crafted files of
every kind are refused with a one-line reason (or their text cleaned) and the rest of the report
goes on; nothing they name is followed, resolved or expanded. Bombs run under a time and memory cap
in a child process."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from omegaconf import OmegaConf

from physgrad.files import clean_text, read_small_yaml
from physgrad.report import write_report
from physgrad.results import ResultsWriter, parse_config, read_final, read_params, read_run
from physgrad.resume import finished_before
from physgrad.runs import collect
from physgrad.sweeps import job_folders, read_manifest

SECRET = "ssh-rsa AAAA-this-must-never-reach-a-report-0123456789"
CONFIG = {
    "seed": 0,
    "seeds": 1,
    "task": {"name": "toy", "batch_size": 4},
    "optim": {"name": "adam"},
    "trainer": {"iterations": 3},
}


def good_run(folder: Path, seed: int = 0, **attrs) -> Path:
    """A small valid results file, as physgrad writes it."""
    path = folder / "results.h5"
    writer = ResultsWriter(
        path,
        {
            "task": "toy",
            "optim": "adam",
            "variant": "adam",
            "seed": seed,
            "config": OmegaConf.to_yaml(OmegaConf.create({**CONFIG, "seed": seed})),
            **attrs,
        },
    )
    for i in range(3):
        writer.append(
            "train",
            {"iteration": i, "wall_time": 0.1 * (i + 1), "loss": 1.0 / (i + 1), "grad_norm": 1.0},
        )
        writer.append("eval", {"iteration": i, "wall_time": 0.1 * (i + 1), "loss": 1.0 / (i + 1)})
    writer.save_params(np.ones(5))
    writer.finish("completed", stopped_by="iterations", iterations=3, train_seconds=0.3)
    return path


def rewrite(path: Path, edit) -> Path:
    """A crafted copy: edit(h5py.File) applied to a good file in place."""
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def set_attr(key, value):
    def edit(f):
        f.attrs[key] = value

    return edit


def replace_column(group, key, data):
    def edit(f):
        del f[group][key]
        f[group].create_dataset(key, data=data)

    return edit


@pytest.fixture
def secret_file(tmp_path):
    path = tmp_path / "id_rsa"
    path.write_bytes(np.frombuffer(SECRET.encode().ljust(24 * 8, b"x"), dtype=np.uint8).tobytes())
    return path


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
def test_a_crafted_file_is_unreadable_with_a_reason_and_the_report_goes_on(tmp_path, kind):
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
    assert (tmp_path / "report" / "loss_vs_time.png").is_file()


@pytest.mark.parametrize("how", ["external storage", "external link", "virtual dataset"])
def test_a_file_cannot_read_other_files_into_a_report(tmp_path, secret_file, how):
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


def test_params_stored_elsewhere_are_refused(tmp_path, secret_file):
    path = good_run(tmp_path / "run")

    def edit(f):
        del f["params"]
        f.create_dataset("params", shape=(3,), dtype="f8", external=[(str(secret_file), 0, 24)])

    rewrite(path, edit)
    with pytest.raises(ValueError, match="params"):
        read_params(path)


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


def test_escapes_in_the_stored_config_are_cleaned_too(tmp_path):
    path = good_run(tmp_path / "run")
    rewrite(path, set_attr("config", 'task: {name: "toy\\e[31m"}\nseed: 0\n'))
    assert read_run(path).config["task"]["name"] == "toy\ufffd[31m"


def test_a_fifo_named_results_h5_is_refused_without_blocking(tmp_path):
    good_run(tmp_path / "good")
    (tmp_path / "fifo").mkdir()
    os.mkfifo(tmp_path / "fifo" / "results.h5")
    runs, unreadable, _ = collect([tmp_path])  # a blocking open would hang here
    assert len(runs) == 1 and "FIFO" in unreadable[0][1]
    with pytest.raises(ValueError, match="FIFO"):
        read_small_yaml(tmp_path / "fifo" / "results.h5")


def test_resume_compares_the_stored_config_as_data_and_resolves_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSGRAD_TEST_SECRET", SECRET)
    cfg = OmegaConf.create({**CONFIG, "overwrite": False})
    path = good_run(tmp_path / "run")
    assert finished_before(path, cfg) is not None  # its own config: skipped as completed
    rewrite(
        path,
        set_attr(
            "config",
            "seed: ${oc.env:PHYSGRAD_TEST_SECRET}\ntask: ${${oc.env:PHYSGRAD_TEST_SECRET}}\n",
        ),
    )
    assert finished_before(path, cfg) is None  # a different config: runs again
    assert parse_config(read_run(path).attrs["config"])["seed"] == "${oc.env:PHYSGRAD_TEST_SECRET}"
    for text in ("[1, 2]", "7", "{bad", "a: &x [1]\nb: *x"):
        rewrite(path, set_attr("config", text))
        assert finished_before(path, cfg) is None


BOMB_LEVELS = 9  # each level refers to the one below ten times: 10^9 leaves once expanded


def alias_bomb() -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, BOMB_LEVELS + 1)]
    return "\n".join(lines) + "\n"


def interpolation_bomb() -> str:
    text = "x: ${oc.env:HOME}\n"
    for i in range(1, 30):
        text += f"x{i}: ${{x{i - 1 if i > 1 else ''}}}${{x{i - 1 if i > 1 else ''}}}\n"
    return text


def run_capped(code: str, seconds: int = 60, memory: int = 2 << 30) -> subprocess.CompletedProcess:
    """code in a child process that caps its own address space (start-up's 3 GiB plus `memory`)
    first, within `seconds`."""
    cap = memory + (3 << 30)
    preamble = f"import resource\nresource.setrlimit(resource.RLIMIT_AS, ({cap}, {cap}))\n"
    return subprocess.run(
        [sys.executable, "-c", preamble + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=seconds,
    )


@pytest.mark.parametrize("bomb", ["alias", "interpolation"])
def test_config_bombs_are_refused_in_bounded_time_and_memory(tmp_path, bomb):
    good_run(tmp_path / "good", seed=1)
    path = good_run(tmp_path / "job")
    rewrite(path, set_attr("config", alias_bomb() if bomb == "alias" else interpolation_bomb()))
    (tmp_path / "job" / ".hydra").mkdir()
    (tmp_path / "job" / ".hydra" / "overrides.yaml").write_text(alias_bomb())
    (tmp_path / "jobs.yaml").write_text(alias_bomb() + "jobs: *a9\n")
    done = run_capped(f"""
        from pathlib import Path
        from omegaconf import OmegaConf
        from physgrad.report import write_report
        from physgrad.resume import finished_before
        from physgrad.sweeps import job_folders, read_manifest
        folder = Path({str(tmp_path)!r})
        cfg = OmegaConf.create({CONFIG!r})
        assert finished_before(folder / "job" / "results.h5", cfg) is None
        assert read_manifest(folder) is None and job_folders(folder) == {{}}
        body = write_report([folder], out_dir=folder / "report")
        print(body)
    """)
    assert done.returncode == 0, done.stderr[-2000:]
    if bomb == "alias":
        assert "unreadable: " in done.stdout and "aliases" in done.stdout
    else:  # text, never resolved: the run is readable and its config holds the ${...} as written
        assert "unreadable" not in done.stdout


def test_sweep_manifests_of_other_types_are_ignored(tmp_path):
    (tmp_path / "jobs.yaml").write_text("jobs: 7\n")
    assert read_manifest(tmp_path) is None
    (tmp_path / "jobs.yaml").write_text("jobs: [[a=1], [{b: 2}]]\n")
    assert read_manifest(tmp_path) is None
    (tmp_path / "j" / ".hydra").mkdir(parents=True)
    (tmp_path / "j" / ".hydra" / "overrides.yaml").write_text("{a: 1}\n")
    assert job_folders(tmp_path) == {}


def test_physgrad_files_read_back_unchanged(tmp_path):
    path = good_run(tmp_path / "run", unroll=8, contended=0, load_start=0.5, step_seconds_p50=0.01)
    run = read_run(path)
    assert (
        run.attrs["seed"] == 0 and run.attrs["unroll"] == 8 and run.attrs["status"] == "completed"
    )
    assert run.config["trainer"] == {"iterations": 3} and run.eval["loss"].tolist() == [
        1.0,
        0.5,
        1 / 3,
    ]
    assert read_params(path).tolist() == [1.0] * 5 and read_final(path)[1]["loss"] == pytest.approx(
        1 / 3
    )


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
    """A stored config of 100,000 keys (under the byte limit) would make a table of as many
    columns: refused before it is flattened."""
    from physgrad.results import CONFIG_KEYS_LIMIT, parse_config

    text = "\n".join(f"k{i}: 0" for i in range(100_000))  # under the byte limit
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
