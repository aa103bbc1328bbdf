"""Unit layer: the tuning journal's one door (physgrad.comparison.journal.OwnJournal): one file
descriptor held for the storage's life, so that a link or another file put at the journal's name
later is neither read nor written through; links, FIFOs, folders and hard links refused when it
opens; a line cut short not read until its newline comes."""

import json
import os

import pytest

from physgrad.comparison.journal import FIELDS, OwnJournal
from tests.helpers import plant


def record(op_code, **more):
    """A record of Optuna's journal with the fields its operation needs (each 0) and more."""
    return {"op_code": op_code, **dict.fromkeys(FIELDS[op_code], 0), **more}


def test_a_link_put_at_the_name_later_is_not_written_through(tmp_path):
    path, elsewhere = tmp_path / "tuning.journal", tmp_path / "elsewhere"
    elsewhere.write_text("untouched\n")
    journal = OwnJournal(path)
    journal.append_logs([record(0, n=1)])
    moved = tmp_path / "moved.journal"
    os.replace(path, moved)
    path.symlink_to(elsewhere)
    journal.append_logs([record(1, n=2), record(2, n=3)])
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
    first, second = json.dumps(record(0)).encode(), json.dumps(record(1)).encode()
    path.write_bytes(first + b"\n" + second[:-1])
    journal = OwnJournal(path)
    assert list(journal.read_logs(0)) == [record(0)]
    with open(path, "ab") as f:
        f.write(b"}\n")
    assert list(journal.read_logs(1)) == [record(1)]
    assert list(journal.read_logs(0)) == [record(0), record(1)]


@pytest.mark.parametrize(
    "line, why",
    [
        ({"op_code": 99}, "no known op_code"),
        ({"op_code": 4, "worker_id": "w"}, "op_code 4 without study_id, datetime_start"),
        ([1, 2], "no known op_code"),
    ],
)
def test_a_record_optuna_cannot_replay_is_one_line(tmp_path, line, why):
    """A whole JSON line that is not a record Optuna's replay can read (an unknown op code, a field
    its operation needs missing) is refused with the line's number, before Optuna reads it (its
    replay failed with a 42-line KeyError or AssertionError)."""
    path = tmp_path / "tuning.journal"
    path.write_text(json.dumps(record(0)) + "\n" + json.dumps(line) + "\n")
    with pytest.raises(ValueError, match=f"line 2 is not a record of Optuna's journal \\({why}\\)"):
        list(OwnJournal(path).read_logs(0))


def test_trials_beyond_the_study_s_and_records_optuna_cannot_replay_are_one_line(tmp_path):
    """A journal padded with trials still to run beyond the study's compare.trials (each would have
    become a job: a thousand ran for minutes) is refused before anything is asked; a record whose
    fields are there but of the wrong kind (a start that is no date) fails inside Optuna's replay,
    which journal_replay turns into one line naming the journal; an error raised outside the
    replay passes unchanged."""
    import optuna

    from physgrad.comparison.journal import journal_replay, journal_storage
    from physgrad.comparison.tuning import _refuse_unasked
    from physgrad.errors import UserError

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    path = tmp_path / "tuning.journal"
    search = optuna.create_study(study_name="adam", storage=journal_storage(path))
    for rate in (1e-3, 1e-2):
        search.enqueue_trial({"learning_rate": rate})
    _refuse_unasked(tmp_path, search, 2)  # the study's own points
    for _ in range(40):
        search.enqueue_trial({"learning_rate": 0.1})
    with pytest.raises(UserError, match="40 trials of adam to run beyond the 2 the study asks"):
        _refuse_unasked(tmp_path, search, 2)

    bad = tmp_path / "bad" / "tuning.journal"
    bad.parent.mkdir()
    good = path.read_text().splitlines(keepends=True)[0]  # the study's creation
    bad.write_text(good + json.dumps(record(4, study_id=0, datetime_start="not a date")) + "\n")
    with pytest.raises(UserError, match="a record Optuna cannot replay") as refused:
        with journal_replay(bad):
            optuna.load_study(study_name="adam", storage=journal_storage(bad)).get_trials()
    assert str(bad) in str(refused.value) and "\n" not in str(refused.value)
    with pytest.raises(KeyError), journal_replay(bad):
        raise KeyError("physgrad's own")
