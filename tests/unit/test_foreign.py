"""Unit layer of files from somebody else: params stored elsewhere, configs past their bound, FIFOs
and YAML aliases are refused, stored text is cleaned and compared as data, physgrad's own files read
back unchanged, and its writes never go through a planted link."""

import os
from pathlib import Path

import h5py
import numpy as np
import pytest
from omegaconf import OmegaConf

from physgrad.files import read_small_yaml
from physgrad.members import comparable_config
from physgrad.results import ResultsWriter, parse_config, read_final, read_params, read_run
from physgrad.resume import finished_before
from physgrad.runs import collect
from tests.helpers import SECRET

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


def test_params_stored_elsewhere_are_refused(tmp_path, secret_file):
    path = good_run(tmp_path / "run")

    def edit(f):
        del f["params"]
        f.create_dataset("params", shape=(3,), dtype="f8", external=[(str(secret_file), 0, 24)])

    rewrite(path, edit)
    with pytest.raises(ValueError, match="params"):
        read_params(path)


def test_a_config_longer_than_its_bound_is_refused_in_one_line(tmp_path):
    """The stored config is bounded where it is read (CONFIG_LIMIT characters): one more is
    refused before it is parsed; the bound itself is read."""
    from physgrad.files import CONFIG_LIMIT

    path = good_run(tmp_path / "run")
    padded = "seed: 0\n#" + "x" * (CONFIG_LIMIT - 9)
    rewrite(path, set_attr("config", padded))
    assert len(padded) == CONFIG_LIMIT and read_run(path).config == {"seed": 0}
    rewrite(path, set_attr("config", padded + "x"))
    with pytest.raises(ValueError, match=f"'config' is longer than {CONFIG_LIMIT}") as caught:
        read_run(path)
    assert "\n" not in str(caught.value)


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
    assert (
        finished_before(path, comparable_config(cfg)) is not None
    )  # its own config: skipped as completed
    rewrite(
        path,
        set_attr(
            "config",
            "seed: ${oc.env:PHYSGRAD_TEST_SECRET}\ntask: ${${oc.env:PHYSGRAD_TEST_SECRET}}\n",
        ),
    )
    assert finished_before(path, comparable_config(cfg)) is None  # a different config: runs again
    assert parse_config(read_run(path).attrs["config"])["seed"] == "${oc.env:PHYSGRAD_TEST_SECRET}"
    for text in ("[1, 2]", "7", "{bad", "a: &x [1]\nb: *x"):
        rewrite(path, set_attr("config", text))
        assert finished_before(path, comparable_config(cfg)) is None


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


@pytest.mark.parametrize("planted", ["destination", "temporary"])
def test_a_file_written_into_a_folder_never_writes_through_a_planted_link(tmp_path, planted):
    """physgrad's one way of writing a file into a folder (physgrad.files.replace_file, which
    error.txt, the tables and the journal's set-aside part go through): a link planted at the file's
    name, or at the name of the temporary file it writes first, is replaced or removed, and the file
    it pointed at is left as it was."""
    from physgrad.app import save_traceback
    from physgrad.files import replace_file, replaced

    outside = tmp_path / "outside.txt"
    outside.write_text("theirs\n")
    folder = tmp_path / "job"
    folder.mkdir()
    name = "error.txt" if planted == "destination" else f".error.txt.{os.getpid()}.tmp"
    (folder / name).symlink_to(outside)
    try:
        raise ValueError("the scene failed")
    except ValueError:
        written = save_traceback(folder)
    assert written == folder / "error.txt" and not written.is_symlink()
    assert "the scene failed" in written.read_text() and outside.read_text() == "theirs\n"
    assert not (folder / f".error.txt.{os.getpid()}.tmp").exists()
    replace_file(folder / "table.csv", b"a,b\n")
    assert (folder / "table.csv").read_bytes() == b"a,b\n"
    # a table written as text, through the same door
    (folder / "runs.csv").symlink_to(outside)
    with replaced(folder / "runs.csv", text=True) as table:
        table.write("variant\r\nadam\n")  # as written: no newline translation
    assert (folder / "runs.csv").read_bytes() == b"variant\r\nadam\n"
    assert outside.read_text() == "theirs\n"


def test_the_last_resort_mark_of_a_failed_run_never_writes_through_a_link(tmp_path):
    """ResultsWriter.mark_failed_in_place (a full disk's last resort) sets the status on the file
    itself; with a link put at the file's name it writes nothing and says so."""
    path = good_run(tmp_path / "run")
    writer = ResultsWriter(path, {"task": "toy", "optim": "adam", "seed": 0}, write=False)
    writer.live = path
    assert writer.mark_failed_in_place("disk full") and read_final(path)[0]["status"] == "failed"
    outside = good_run(tmp_path / "outside")
    before = outside.read_bytes()
    path.unlink()
    path.symlink_to(outside)
    assert not writer.mark_failed_in_place("disk full") and outside.read_bytes() == before


@pytest.mark.parametrize("parser", ["libyaml", "pure Python"])
def test_yaml_with_an_alias_anywhere_is_refused_by_either_parser(parser, monkeypatch):
    """load_yaml refuses every alias (of a mapping, a list, a scalar, nested a billion times) with
    libyaml's parser and with PyYAML's own (where PyYAML was built without libyaml), and reads
    plain YAML alike with both."""
    import yaml

    import physgrad.files as files

    if parser == "pure Python":  # (where PyYAML has no libyaml, both cases are this one)
        monkeypatch.setattr(files, "_Loader", yaml.SafeLoader)
    laughs = "a0: &a0 [x, x]\n" + "".join(
        f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}]\n" for i in range(1, 40)
    )
    for text in ("a: &x {b: 1}\nc: *x\n", "a: &x [1]\nb: *x\n", "a: &x 1\nb: *x\n", laughs):
        with pytest.raises(
            ValueError, match=r"^not plain YAML \(aliases \(\*name\) are not allowed\)$"
        ):
            files.load_yaml(text)
    plain = "optim:\n  name: hig\n  learning_rate: 0.64\nseeds: [0, 1]\nnote: '&x *y'\n"
    assert files.load_yaml(plain) == {
        "optim": {"name": "hig", "learning_rate": 0.64},
        "seeds": [0, 1],
        "note": "&x *y",
    }
    assert files.load_yaml("") is None
    with pytest.raises(ValueError, match="not plain YAML"):
        files.load_yaml("a: !!python/object:os.system x\n")
