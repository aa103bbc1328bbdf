"""Unit layer: the one door for reading a folder someone else may have written
(physgrad.files.open_foreign, read_own_file, walk_files and the readers built on them): no link
followed, no FIFO waited on, bounded, parsed inside the one-line error boundary, and walked
without recursion or leaving the folder."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from physgrad.errors import UserError
from physgrad.files import open_foreign, read_own_file, read_small_yaml, walk_files
from physgrad.results import find_results, member_order, read_final, read_run
from tests.helpers import plant
from tests.unit.test_foreign import good_run

KINDS = ["link", "dangling link", "fifo", "folder"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "read",
    [
        lambda path: read_own_file(path, 1 << 10),
        lambda path: read_small_yaml(path),
        lambda path: read_run(path),
        lambda path: os.close(open_foreign(path, write=True)),
    ],
    ids=["bytes", "yaml", "results", "append"],
)
def test_every_reader_refuses_what_is_not_a_plain_file_in_one_line(tmp_path, kind, read):
    """A link (to a readable file of the right kind, or to nothing), a FIFO or a folder where a
    file is expected: one line naming the path and what it is, without blocking on a FIFO and
    without reading or creating what a link points at."""
    other = tmp_path / "elsewhere.yaml"
    if kind != "dangling link":
        other.write_text("jobs: []\n")
    path = tmp_path / "folder" / "file"
    path.parent.mkdir()
    plant(path, kind, other if kind != "dangling link" else tmp_path / "nothing")
    with pytest.raises(ValueError) as refused:
        read(path)
    message = str(refused.value)
    assert str(path) in message and "\n" not in message and "refused" in message
    assert not (tmp_path / "nothing").exists()


def test_a_results_file_behind_a_link_is_read_only_where_the_user_gave_the_link(tmp_path):
    """A results.h5 that is a link to a valid run: refused when found in a folder (read_run), read
    when it is the path the user gave (follow=True)."""
    real = good_run(tmp_path / "real")
    link = tmp_path / "job" / "results.h5"
    link.parent.mkdir()
    link.symlink_to(real)
    with pytest.raises(ValueError, match="a link: refused"):
        read_final(link)
    assert read_final(link, follow=True)[0]["status"] == "completed"


def test_a_file_longer_than_its_bound_is_refused_not_cut(tmp_path):
    """Cutting a table or a journal at its bound would parse a part as if it were the whole."""
    path = tmp_path / "runs.csv"
    path.write_bytes(b"a,b\n" + b"1,2\n" * 100)
    with pytest.raises(ValueError, match="longer than 64 bytes"):
        read_own_file(path, 64)
    assert read_own_file(path, len(path.read_bytes())) == path.read_bytes()
    assert read_own_file(path, 8, tail=True) == b"1,2\n1,2\n"  # a log's tail: its last bytes


@pytest.mark.parametrize(
    "line",
    [b"[" * 200_000 + b"\n", b"not json\n", b"[1, 2]\n", b"\xff\xfe\n"],
    ids=["deep", "text", "not-a-record", "binary"],
)
def test_a_journal_line_that_is_not_a_record_is_one_line(tmp_path, line):
    """A crafted tuning.journal: a UserError naming the file and the line, whoever opens it (the
    tuning, or the tables of a study run with compare.tune=false)."""
    from physgrad.comparison.journal import journal_storage

    path = tmp_path / "tuning.journal"
    path.write_bytes(line)
    with pytest.raises(UserError, match=r"tuning.journal: line 1 is not a record") as refused:
        journal_storage(path)
    assert "\n" not in str(refused.value)


def test_a_journal_over_its_bound_is_refused(tmp_path, monkeypatch):
    from physgrad.comparison import journal
    from physgrad.comparison.journal import journal_storage

    monkeypatch.setattr(journal, "JOURNAL_LIMIT", 1000)
    path = tmp_path / "tuning.journal"
    path.write_bytes(b'{"op_code": 0}\n' * 100)
    with pytest.raises(UserError, match="longer than 1000 bytes"):
        journal_storage(path)


@contextmanager
def deep_folders(top: Path, depth: int) -> Iterator[Path]:
    """depth nested folders under top, taken down again afterwards one level at a time (pathlib's
    mkdir(parents=True) and shutil.rmtree, which pytest cleans up with, recurse)."""
    levels = [top / "deep"]
    for _ in range(depth):
        levels.append(levels[-1] / "d")
    try:
        for level in levels:
            level.mkdir()
        yield levels[-1]
    finally:
        for level in reversed(levels):
            if level.is_dir():
                level.rmdir()


def test_a_sweep_folder_of_any_depth_is_walked_without_recursion(tmp_path):
    """physgrad report's look for unfinished jobs (sweeps.unfinished_jobs, job_folders) on 1,500
    nested folders: no RecursionError."""
    from physgrad.sweeps import job_folders, unfinished_jobs

    with deep_folders(tmp_path, 1500):
        assert job_folders(tmp_path) == {}
        assert unfinished_jobs(tmp_path) == []
        assert list(walk_files(tmp_path, "results.h5")) == []


def test_a_walk_follows_no_linked_folder(tmp_path):
    outside = tmp_path / "outside"
    good_run(outside / "run")
    (outside / "run" / ".hydra").mkdir()
    (outside / "run" / ".hydra" / "overrides.yaml").write_text("- optim=adam\n")
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "job").symlink_to(outside / "run")
    (sweep / "loop").symlink_to(sweep)
    from physgrad.sweeps import job_folders

    assert find_results([sweep]) == [] and job_folders(sweep) == {}


def test_a_job_record_pointing_outside_its_sweep_is_not_walked(tmp_path):
    """A job's record (.physgrad-jobs/*.yaml) is data from the sweep folder: a record saying its job
    folder is /usr, or another sweep's folder with results in it, does not make physgrad walk it
    or count the job as finished."""
    import yaml

    from physgrad.sweeps import JOB_STATES, unfinished_jobs, write_manifest

    elsewhere = tmp_path / "elsewhere"
    good_run(elsewhere / "job")
    sweep = tmp_path / "sweep"
    write_manifest(sweep, [["optim=adam"]])
    (sweep / JOB_STATES).mkdir()
    record = {"folder": str(elsewhere), "overrides": ["optim=adam"], "state": "started"}
    record |= {"reason": None, "owner": "pid 1 on elsewhere", "scheduler": None}
    (sweep / JOB_STATES / "crafted.yaml").write_text(yaml.safe_dump(record))
    [(job, why)] = unfinished_jobs(sweep)
    assert job == "optim=adam" and "no results yet" in why


def test_a_results_link_that_points_at_itself_is_listed_not_fatal(tmp_path):
    """physgrad report on a folder holding a results.h5 that links to itself: the file is listed
    as unreadable (no 'Symlink loop' traceback)."""
    from physgrad.runs import collect

    good_run(tmp_path / "good")
    loop = tmp_path / "bad" / "results.h5"
    loop.parent.mkdir()
    loop.symlink_to(loop)
    runs, unreadable, _ = collect([tmp_path])
    assert len(runs) == 1 and [path for path, _ in unreadable] == [loop]


def test_members_of_any_folder_name_sort_without_error(tmp_path):
    """seed=2 before seed=10; a planted seed=x or seed=² folder last, not a ValueError."""
    from physgrad.app import seed_lines

    for name in ("seed=10", "seed=2", "seed=x", "seed=²"):
        good_run(tmp_path / name, seed=0)
    paths = sorted(tmp_path.glob("seed=*/results.h5"), key=member_order)
    assert [p.parent.name for p in paths][:2] == ["seed=2", "seed=10"]
    assert len(seed_lines(tmp_path)) >= 2


def test_a_config_nested_past_the_bound_is_one_line_not_a_recursion_error():
    """A stored config nested 500 deep (a crafted results file's) is refused where it is read, in
    one line; every later reader (OmegaConf, report, read_runs, resume) failed with a RecursionError
    thousands of lines long. A physgrad config's depth passes."""
    from physgrad.files import MAX_DEPTH, load_yaml

    deep = "a: " + "{b: " * 500 + "1" + "}" * 500
    with pytest.raises(ValueError, match=f"nested deeper than {MAX_DEPTH} levels") as caught:
        load_yaml(deep)
    assert "\n" not in str(caught.value)
    shallow = "a: " + "{b: " * (MAX_DEPTH - 2) + "1" + "}" * (MAX_DEPTH - 2)
    assert load_yaml(shallow)["a"]["b"]["b"]
