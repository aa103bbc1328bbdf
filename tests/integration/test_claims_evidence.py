"""The claims' evidence (experiments/evidence.py): a finished study kept as a table decides every
kind of claim part exactly as the study folder does."""

import json
import os
import shutil
import sys

import pytest

from tests.helpers import REPO, plant
from tests.integration.test_compare import small_study  # noqa: F401 - the session's finished study

sys.path.insert(0, str(REPO / "experiments"))
import claim_budget  # noqa: E402
import claims  # noqa: E402
import study_runs  # noqa: E402

PARTS = (
    claims.Lower("small", "adam", "gd"),
    claims.Lower("small", "gd", "adam"),
    claims.Close("small", "adam", "gd", 1.5),
    claims.Stalls("small", "gd"),
    claims.Reaches("small", "adam", 0.5),
    claims.Reaches("small", "gd", 0.3),
    claims.Lower("small", "adam", "gd", "error_second"),
)


def test_kept_evidence_decides_every_part_as_the_study_folder(
    small_study,  # noqa: F811
    tmp_path,
    monkeypatch,
):
    root, kept = tmp_path / "studies", tmp_path / "evidence"
    shutil.copytree(small_study.folder, root / "small", symlinks=True)
    claim = claims.Claim("small", "a paper's claim", PARTS)
    monkeypatch.setattr(claims, "CLAIMS", (claim,))
    assert claims.keep_evidence(root, kept) == ["small"]
    about = json.loads((kept / "small.json").read_text())
    assert (about["trials"], about["studies"], about["seeds"]) == (2, 2, 6)
    assert about["axis"] == "iteration" and about["budget"] == 30
    assert "task=toy" in about["overrides"] and about["kept_by"] and about["commits"]
    # the code that ran the runs, from their results files (the leaderboard keeps it too)
    ran = study_runs.run_commits(study_runs.read_study(root / "small"))
    assert ran and all(c not in ("unknown", "unreadable") for c in ran)
    # 2 tuning studies x 2 variants x 6 seeds x 2 columns, kilobytes
    assert len((kept / "small.csv").read_text().splitlines()) == 1 + 48
    assert (kept / "small.csv").stat().st_size < 10_000
    for fraction in (0.25, 0.5, 1.0):
        from_folder = claims.decide_claim(claim, root, fraction=fraction)
        from_kept = claims.decide_claim(claim, kept, fraction=fraction)
        assert from_kept == from_folder, fraction
    assert claims.study_protocol(kept / "small") == claims.study_protocol(root / "small")
    # each tuning study's tuning is kept: its trials and the setting it chose per variant, the
    # one its compare evaluated (the study's own table), shown with the trials' span in claims.md
    import pandas as pd

    trials = pd.read_csv(root / "small" / "trials.csv")
    for k, record in about["tuning_studies"].items():
        mine = trials[trials["study"] == int(k) - 1]
        assert len(record["trials"]) == len(mine) == 4
        for variant, tuned in record["tuned"].items():
            rows = mine[mine["variant"] == variant]
            best = rows.loc[rows["validation_loss"].idxmin()]
            assert tuned == {"learning_rate": pytest.approx(best["learning_rate"])}
    table = claims.tuned_table(kept)
    assert "| small | adam | study 1: learning_rate=" in table and "study 2:" in table
    # the study folder is not needed to regenerate the markdown
    shutil.rmtree(root)
    assert claims.decide_claim(claim, kept) == from_kept


def _replace(path, old, new):
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize(
    "damage, why",
    [
        (lambda csv, about: csv.write_text("study,variant\n0,adam\n"), "columns"),
        (
            lambda csv, about: csv.write_text(
                csv.read_text().replace("\n0,adam,0,", "\n0,adam,zero,", 1)
            ),
            "not a number",
        ),
        (lambda csv, about: about.unlink(), "FileNotFoundError"),
        (lambda csv, about: about.write_text('{"axis": "iteration"}'), "KeyError"),
        (lambda csv, about: csv.write_bytes(b"\x00\xff" * 50), "not an evidence table"),
        # a study number far past any study (it allocated a list of 1e9), a negative one (it
        # wrapped to the last study), a NaN seed, a name with a terminal escape, an unknown axis
        # (make test checks the negative one; make test-long the others)
        pytest.param(
            lambda csv, about: _replace(csv, "\n0,adam,", "\n1000000000,adam,"),
            "study: 1e\\+09",
            marks=pytest.mark.long,
        ),
        (lambda csv, about: _replace(csv, "\n0,adam,", "\n-3,adam,"), "study: -3 is not"),
        pytest.param(
            lambda csv, about: _replace(csv, "\n0,adam,0,", "\n0,adam,,"),
            "seed: nan is not",
            marks=pytest.mark.long,
        ),
        pytest.param(
            lambda csv, about: _replace(csv, "\n0,adam,", "\n0,ad\x1b]0;x\x07am,"),
            "variant: ",
            marks=pytest.mark.long,
        ),
        pytest.param(
            lambda csv, about: _replace(about, '"iteration"', '"hours"'),
            "axis: 'hours'",
            marks=pytest.mark.long,
        ),
        # a FIFO is refused, never read as a study that did not run; a record's protocol in range
        (lambda csv, about: (csv.unlink(), os.mkfifo(csv)), "a FIFO, not a file"),
        (
            lambda csv, about: _replace(about, '"seeds": ', '"seeds": -'),
            r"small.json: .*seeds=-\d+ is not a whole number",
        ),
    ],
)
def test_a_damaged_evidence_table_is_one_line(
    small_study,  # noqa: F811
    tmp_path,
    monkeypatch,
    damage,
    why,
):
    from physgrad.errors import UserError

    root, kept = tmp_path / "studies", tmp_path / "evidence"
    shutil.copytree(small_study.folder, root / "small", symlinks=True)
    monkeypatch.setattr(claims, "CLAIMS", (claims.Claim("small", "-", PARTS[:1]),))
    claims.keep_evidence(root, kept)
    damage(kept / "small.csv", kept / "small.json")
    with pytest.raises(UserError, match=why) as refused:
        claims.read_study(kept / "small")
    assert "small" in str(refused.value) and "\n" not in str(refused.value)


# a second study run and kept beside the shared one (7 s): make test-long
@pytest.mark.long
def test_tuning_studies_run_as_compares_of_their_own_are_kept_and_decided_as_one(
    small_study,  # noqa: F811
    tmp_path,
    monkeypatch,
):
    """Each tuning study of a claims study run as a compare of its own (<name>/study-k), on two
    machines, kept one after the other (the later first): one table, the same as the one compare
    that ran both keeps, deciding every part as it does, from the folders and from the table;
    keeping a study again replaces its rows."""
    import pandas as pd

    whole = tmp_path / "whole"
    shutil.copytree(small_study.folder, whole / "small", symlinks=True)
    runs = pd.read_csv(whole / "small" / "runs.csv", dtype=str)
    machines, both = {}, tmp_path / "both" / "small"
    for k in (1, 2):
        machines[k] = tmp_path / f"machine-{k}"
        folder = machines[k] / "small" / f"study-{k}"
        shutil.copytree(small_study.folder, folder, symlinks=True)
        runs[runs["study"] == str(k - 1)].to_csv(folder / "runs.csv", index=False)
        shutil.copytree(folder, both / f"study-{k}", symlinks=True)
    claim = claims.Claim("small", "a paper's claim", PARTS)
    monkeypatch.setattr(claims, "CLAIMS", (claim,))
    kept, kept_whole = tmp_path / "evidence", tmp_path / "evidence-whole"
    assert claims.keep_evidence(machines[2], kept) == ["small/study-2"]
    assert json.loads((kept / "small.json").read_text())["studies"] == 1
    assert claims.keep_evidence(machines[1], kept) == ["small/study-1"]
    assert claims.keep_evidence(whole, kept_whole) == ["small"]
    assert (kept / "small.csv").read_text() == (kept_whole / "small.csv").read_text()
    about = json.loads((kept / "small.json").read_text())
    assert about["studies"] == 2 and sorted(about["tuning_studies"]) == ["1", "2"]
    # every kind of part, from the folders and from the table (each fraction reads the same runs:
    # test_kept_evidence_decides_every_part_as_the_study_folder)
    expected = claims.decide_claim(claim, whole)
    assert claims.decide_claim(claim, both.parent) == expected
    assert claims.decide_claim(claim, kept) == expected
    claims.keep_evidence(machines[2], kept)
    assert (kept / "small.csv").read_text() == (kept_whole / "small.csv").read_text()
    # a study of the profiles is to have more: kept with its plan, decided by a majority of it
    monkeypatch.setattr(study_runs, "_planned", lambda name: 4)
    lower = claims.Claim("small", "-", PARTS[:1])
    monkeypatch.setattr(claims, "CLAIMS", (lower,))
    claims.keep_evidence(machines[1], kept)
    for root in (both.parent, kept):
        runs = claims.read_study(root / "small")
        assert runs.planned == 4 and claim_budget.of_planned(runs) == " of 4"
        _, ((_, decision),) = claims.decide_claim(lower, root)
        assert "(2 of 4 tuning studies run)" in decision.why
    # a kept clock measured on a busy machine: the first study kept again replaces every tuning
    # study kept on it (their budget bought fewer steps than it says), which then run again
    busy = {"costs": {"adam": {"step_seconds": 0.01}}, "load_start": 5.4, "load_end": 5.4}
    (kept / "small.calibration.json").write_text(json.dumps({**busy, "machine": {"cpu_count": 2}}))
    claims.keep_evidence(machines[2], kept)  # a later study: kept beside the others
    assert sorted(json.loads((kept / "small.json").read_text())["tuning_studies"]) == ["1", "2"]
    assert claims.keep_evidence(machines[1], kept) == ["small/study-1"]
    assert sorted(json.loads((kept / "small.json").read_text())["tuning_studies"]) == ["1"]
    assert claims.read_study(kept / "small").planned == 4


@pytest.mark.parametrize("kind", ["link", "fifo"])
@pytest.mark.parametrize("name", ["runs.csv", "study.json", "trials.csv"])
def test_a_planted_file_in_a_study_folder_is_refused_or_left_out_never_followed_or_waited_on(
    small_study,  # noqa: F811
    tmp_path,
    monkeypatch,
    kind,
    name,
):
    """A study folder from someone else with a link (to a file elsewhere) or a FIFO where runs.csv,
    study.json or trials.csv should be: reading and keeping it refuses in one line or leaves the
    file out; nothing waits on the FIFO and nothing is read through the link."""
    import signal

    from physgrad.errors import UserError

    root, kept = tmp_path / "studies", tmp_path / "evidence"
    shutil.copytree(small_study.folder, root / "small", symlinks=True)
    secret = tmp_path / "elsewhere.csv"
    shutil.copy(root / "small" / "runs.csv", secret)  # a table that would read as the study's
    (root / "small" / name).unlink(missing_ok=True)
    plant(root / "small" / name, kind, secret)
    monkeypatch.setattr(claims, "CLAIMS", (claims.Claim("small", "-", PARTS[:1]),))
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("waited on a FIFO"))
    signal.alarm(60)
    try:
        try:
            runs = claims.read_study(root / "small")
            claims.keep_evidence(root, kept)
        except UserError as refused:
            assert "\n" not in str(refused) and name in str(refused)
            assert kind == "link" or name == "study.json", refused
        else:
            assert name == "trials.csv" or (name == "runs.csv" and runs is None)
    finally:
        signal.alarm(0)


def test_kept_evidence_is_written_by_replacing_never_through_a_planted_link(
    small_study,  # noqa: F811
    tmp_path,
    monkeypatch,
):
    """An evidence folder whose table is a link to a file elsewhere: keeping replaces the link with
    the table and leaves the file it pointed to as it was; a linked table is refused when read."""
    from physgrad.errors import UserError

    root, kept = tmp_path / "studies", tmp_path / "evidence"
    shutil.copytree(small_study.folder, root / "small", symlinks=True)
    monkeypatch.setattr(claims, "CLAIMS", (claims.Claim("small", "-", PARTS[:1]),))
    kept.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("untouched")
    (kept / "small.csv").symlink_to(victim)
    (kept / "small.json").symlink_to(victim)
    with pytest.raises(UserError, match="a link") as refused:
        claims.read_study(kept / "small")
    assert "\n" not in str(refused.value)
    (kept / "small.csv").unlink(), (kept / "small.json").unlink()
    claims.keep_evidence(root, kept)
    (kept / "small.json").rename(kept / "kept.json")
    (kept / "small.json").symlink_to(victim)
    claims.keep_evidence(root, kept)
    assert victim.read_text() == "untouched" and not (kept / "small.json").is_symlink()
