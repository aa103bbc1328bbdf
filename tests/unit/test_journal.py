"""Unit layer: the tuning journal's one door (physgrad.comparison.journal.OwnJournal): one file
descriptor held for the storage's life, so that a link or another file put at the journal's name
later is neither read nor written through; links, FIFOs, folders and hard links refused when it
opens; a line cut short not read until its newline comes."""

import os

import pytest

from physgrad.comparison.journal import OwnJournal
from tests.helpers import plant


def test_a_link_put_at_the_name_later_is_not_written_through(tmp_path):
    path, elsewhere = tmp_path / "tuning.journal", tmp_path / "elsewhere"
    elsewhere.write_text("untouched\n")
    journal = OwnJournal(path)
    journal.append_logs([{"op_code": 0, "n": 1}])
    moved = tmp_path / "moved.journal"
    os.replace(path, moved)
    path.symlink_to(elsewhere)
    journal.append_logs([{"op_code": 1, "n": 2}, {"op_code": 2, "n": 3}])
    assert elsewhere.read_text() == "untouched\n"
    assert [log["n"] for log in journal.read_logs(0)] == [1, 2, 3]
    assert [log["n"] for log in journal.read_logs(1)] == [2, 3]
    assert moved.read_text().count("\n") == 3


@pytest.mark.parametrize("kind", ["link", "dangling link", "fifo", "folder", "hard link"])
def test_what_is_not_a_file_of_one_name_is_refused_in_one_line(tmp_path, kind):
    path, other = tmp_path / "tuning.journal", tmp_path / "other"
    plant(path, kind, other)
    with pytest.raises(ValueError) as refused:
        OwnJournal(path)  # a FIFO must not block
    assert "\n" not in str(refused.value) and str(path) in str(refused.value)
    assert not other.exists() or other.read_text() == ""


def test_a_line_cut_short_is_read_once_its_newline_comes(tmp_path):
    path = tmp_path / "tuning.journal"
    path.write_bytes(b'{"op_code":0}\n{"op_code":1')
    journal = OwnJournal(path)
    assert list(journal.read_logs(0)) == [{"op_code": 0}]
    with open(path, "ab") as f:
        f.write(b"}\n")
    assert list(journal.read_logs(1)) == [{"op_code": 1}]
    assert list(journal.read_logs(0)) == [{"op_code": 0}, {"op_code": 1}]
