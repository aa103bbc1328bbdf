"""Unit layer of the write door: every file physgrad or experiments/ writes goes through
physgrad.files (replaced, replace_file, write_text, write_figure, open_append, make_folder), which
follow no link; this test walks the code for the ways Python writes a file and fails on one that
bypasses the door. And make_folder itself, on planted links and files."""

import re

import pytest

from physgrad.files import LinkedFolder, make_folder
from tests.helpers import REPO

WRITES = re.compile(
    r"\.write_text\(|\.write_bytes\(|\bopen\([^)]*['\"][wax]b?\+?['\"]|\.open\(['\"][wax]|"
    r"\.savefig\(|h5py\.File\([^)]*['\"](w|a|r\+|x)['\"]|O_CREAT"
)
# writes that cannot go through a folder someone else made, each with why
ALLOWED = {
    # the GPU claim file: opened without following a link, in physgrad's own cache folder
    ("physgrad/gpus.py", "O_NOFOLLOW"),
    # the jobs' config files, written into a private folder of tempfile.mkdtemp, then copied
    ("physgrad/comparison/jobs.py", '(private / "compare_job"'),
    ("physgrad/comparison/plan.py", '(folder / "files" / "compare_job"'),
    # results.h5 built in memory (no file), then written through replace_file
    ("physgrad/results.py", "backing_store=False"),
    # the last resort on a full disk: the file's own descriptor, opened with O_NOFOLLOW just before
    ("physgrad/results.py", "h5py.File(stream, "),
}


def test_every_file_write_goes_through_the_door():
    found = []
    for root in ("physgrad", "experiments", "hydra_plugins"):
        for path in sorted((REPO / root).rglob("*.py")):
            name = path.relative_to(REPO).as_posix()
            if name == "physgrad/files.py":
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if WRITES.search(line) and not any(
                    name == where and mark in line for where, mark in ALLOWED
                ):
                    found.append(f"{name}:{number}: {line.strip()}")
    assert not found, "writes that bypass physgrad.files:\n" + "\n".join(found)


def test_make_folder_refuses_a_link_or_a_file_at_the_names_it_creates(tmp_path):
    """A folder made anew, or one that exists, passes; a link planted at its name (to a folder
    elsewhere), or at a parent within `levels`, or a file there, is refused in one line and
    nothing is written into the link's target."""
    target = tmp_path / "elsewhere"
    target.mkdir()
    assert make_folder(tmp_path / "study" / "report").is_dir()
    assert make_folder(tmp_path / "study" / "report") == tmp_path / "study" / "report"
    (tmp_path / "study" / "seed=0").symlink_to(target)
    with pytest.raises(LinkedFolder, match="seed=0 is a link, not a folder") as caught:
        make_folder(tmp_path / "study" / "seed=0")
    assert "\n" not in str(caught.value)
    (tmp_path / "study" / "configs").symlink_to(target)
    with pytest.raises(LinkedFolder, match="configs is a link"):
        make_folder(tmp_path / "study" / "configs" / "compare_job", levels=2)
    (tmp_path / "study" / ".hydra").write_text("planted")
    with pytest.raises(LinkedFolder, match=".hydra is a file, not a folder"):
        make_folder(tmp_path / "study" / ".hydra")
    assert list(target.iterdir()) == []


def test_a_run_a_job_record_and_the_pages_refuse_a_planted_link(tmp_path):
    """Links planted at the names a run (seed=0/) and a job (.hydra/) create: each refused in one
    line, nothing written into the link's target (the results file was written into it, and the
    run then run again on every resume)."""
    from omegaconf import OmegaConf

    from physgrad.app import write_provenance
    from physgrad.results import ResultsWriter

    target = tmp_path / "elsewhere"
    target.mkdir()
    job = tmp_path / "job"
    job.mkdir()
    for name in ("seed=0", ".hydra"):
        (job / name).symlink_to(target)
    with pytest.raises(LinkedFolder, match="seed=0 is a link"):
        ResultsWriter(job / "seed=0" / "results.h5", {"task": "toy"})
    with pytest.raises(LinkedFolder, match=".hydra is a link"):
        write_provenance(job, OmegaConf.create({"seed": 0}), OmegaConf.create({}))
    assert list(target.iterdir()) == []


def test_hydra_s_sweep_record_is_never_written_through_a_planted_name(tmp_path):
    """Hydra's sweeper writes multirun.yaml itself, with a plain open: a link (dangling too), a
    second name of another file or a FIFO planted there is removed before the sweep, so Hydra
    makes a file of its own and theirs is untouched; a file of the sweep's own stays; a folder
    there ends the sweep in one line."""
    import os

    from physgrad.sweep_hooks import _clear_hydra_record

    theirs = tmp_path / "theirs.yaml"
    record = tmp_path / "sweep" / "multirun.yaml"
    record.parent.mkdir()
    for plant in (
        lambda: record.symlink_to(theirs),
        lambda: record.symlink_to(tmp_path / "nowhere"),
        lambda: os.link(theirs, record),
        lambda: os.mkfifo(record),
    ):
        theirs.write_text("theirs\n")
        plant()
        _clear_hydra_record(record)
        assert not os.path.lexists(record) and theirs.read_text() == "theirs\n"
    record.write_text("hydra: own\n")
    _clear_hydra_record(record)
    assert record.read_text() == "hydra: own\n"
    record.unlink()
    record.mkdir()
    with pytest.raises(SystemExit) as refused:
        _clear_hydra_record(record)
    assert refused.value.code == 2
