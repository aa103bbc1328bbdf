"""Numerics layer of the claims (experiments/claims.py): lower parts by the paired rule, the studies
and variants every claim part names, the studies' commands and parts, decisions at each fraction
of the budget and over tuning studies, and docs/claims.md regenerated from the kept evidence."""

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))

import claims  # noqa: E402
import studies as study_lists  # noqa: E402
from claims import FAILS, HOLDS, OPEN  # noqa: E402

from physgrad.readout import Curve  # noqa: E402
from tests.unit.test_claims import (
    TEN,
    FakeStudy,
    X,
    base,
    claim_of,
    falling,
    three_studies,
)


def test_lower_holds_fails_or_is_open_by_the_paired_rule(tmp_path, studies):
    studies["s"] = FakeStudy(
        "s",
        {
            "a": {s: falling(0.5 * base(s)) for s in TEN},
            "b": {s: falling(base(s)) for s in TEN},
            "c": {s: falling(base(s) * (0.5 if s % 2 else 2.0)) for s in TEN},
        },
    )
    verdict, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert verdict == HOLDS and "a / b = 0.5" in d.measured and "a lower in 10 of 10" in d.measured
    assert claims.decide_claim(claim_of(claims.Lower("s", "b", "a")), tmp_path)[0] == FAILS
    assert claims.decide_claim(claim_of(claims.Lower("s", "c", "b")), tmp_path)[0] == OPEN
    # one failing part makes the claim fail; an open one leaves it open
    assert (
        claims.decide_claim(
            claim_of(claims.Lower("s", "a", "b"), claims.Lower("s", "b", "a")), tmp_path
        )[0]
        == FAILS
    )
    assert (
        claims.decide_claim(
            claim_of(claims.Lower("s", "a", "b"), claims.Lower("s", "c", "b")), tmp_path
        )[0]
        == OPEN
    )


def test_every_claim_part_names_a_study_of_the_profile_and_variants_it_makes():
    """The variant names are the ones physgrad compare gives the study's axes
    (comparison.variant_name)."""
    import itertools

    from physgrad.comparison import variant_name

    studies = {s.name: s for s in study_lists.STUDIES}
    for claim in claims.CLAIMS:
        for part in claim.parts:
            for name in [part.easy, part.hard] if isinstance(part, claims.Grows) else [part.study]:
                study = studies[name]
                axes = [
                    [f"{o.partition('=')[0]}={v}" for v in study_lists._values(o)]
                    for o in study.overrides
                    if len(study_lists._values(o)) > 1
                ]
                names = {variant_name(list(combo)) for combo in itertools.product(*axes)}
                wanted = (
                    [part.variant]
                    if isinstance(part, (claims.Stalls, claims.Reaches))
                    else [part.a, part.b]
                )
                assert set(wanted) <= names, (claim.name, name, wanted, names)


def test_paired_seeds_suffice_for_every_comparison_a_claim_makes():
    from physgrad.verdict import seeds_needed

    studies = {s.name: s for s in study_lists.PROFILES["claims"]}
    for claim in claims.CLAIMS:
        per_study = {}
        for part in claim.parts:
            if isinstance(part, (claims.Lower, claims.Close)):
                per_study[part.study] = per_study.get(part.study, 0) + 1
        for name, count in per_study.items():
            assert studies[name].seeds >= seeds_needed(comparisons=count), (claim.name, name)
    assert all(
        s.seeds >= 5 for s in study_lists.PROFILES["claims"] if s.timed
    )  # equal time: at least 5


def test_a_study_command_names_its_folder_seeds_trials_and_the_presets_clock(tmp_path, monkeypatch):
    """Tuning study k of a study is a compare of its own in <name>/study-k with the tuning seed and
    evaluation seeds study k has in one compare of all of them; the later studies and the presets'
    twin run on the first study's clock, the kept one first."""
    from physgrad.comparison import split_overrides, study_settings

    monkeypatch.setattr(study_lists, "EVIDENCE", tmp_path / "evidence")
    study = next(s for s in study_lists.STUDIES if s.name == "oscillator")
    # on the calibrated clock a variant's seeds train together: one job each, seeds x the budget
    assert study.variants() == 3 and study.timed and study.eval_jobs() == 3
    assert study.eval_job_seconds() == pytest.approx(
        3 * study.eval_seconds + 3 * (study.seeds - 1) * study.time_budget
    )
    measured = replace(study, overrides=(*study.overrides, "compare.clock=measured"))
    assert measured.eval_jobs() == 3 * study.seeds
    assert measured.eval_job_seconds() == pytest.approx(3 * study.seeds * study.eval_seconds)
    whole = study_settings(split_overrides(study.command(tmp_path))[0])
    assert f"compare.dir={tmp_path / 'oscillator'}" in study.command(tmp_path)
    first, second, *_ = study_lists.slices(study)
    clock = tmp_path / "oscillator" / "study-1" / "calibration.json"
    for k, piece in enumerate(study_lists.slices(study)):
        command = piece.command(tmp_path)
        assert f"compare.dir={tmp_path / 'oscillator' / f'study-{k + 1}'}" in command
        assert "compare.tune=false" not in command and "compare.studies=1" in command
        settings = study_settings(split_overrides(command)[0])
        assert settings.evaluation_seeds == whole.study_seeds(k)
        assert settings.tune_seed == whole.tune_seed + k
        assert not any(o.startswith("compare.calibration=") for o in command)  # no clock yet
    preset = first.command(tmp_path, preset=True)
    assert f"compare.dir={tmp_path / 'oscillator-preset'}" in preset
    assert "compare.tune=false" in preset
    assert study_settings(split_overrides(preset)[0]).evaluation_seeds == whole.study_seeds(0)
    clock.parent.mkdir(parents=True)
    clock.write_text("{}")
    assert f"compare.calibration={clock}" in second.command(tmp_path)
    assert f"compare.calibration={clock}" in first.command(tmp_path, preset=True)
    assert not any(o.startswith("compare.calibration=") for o in first.command(tmp_path))
    kept = tmp_path / "evidence" / "oscillator.calibration.json"
    kept.parent.mkdir()
    kept.write_text("{}")
    assert f"compare.calibration={kept}" in second.command(tmp_path)
    cart = next(s for s in study_lists.STUDIES if s.name == "cart_4")
    # seeds trained together, one job per variant
    assert cart.variants() == 6 and cart.eval_jobs() == 6
    unroll = next(s for s in study_lists.STUDIES if s.name == "ks_unroll")
    assert unroll.eval_jobs() == 3 * unroll.seeds  # init_from: one network per job
    assert any(
        f"init_from='{tmp_path}/ks_start/seed=${{seed}}/results.h5'" == o
        for o in unroll.command(tmp_path)
    )


def test_parts_stay_under_the_limit_and_keep_the_order():
    """Every study in order, one with repeated tuning studies cut into them (1, 2, ..., each a
    compare of its own in <name>/study-k), costing what the whole does, the presets with the
    first (on its seeds, start networks and clock)."""
    for profile in study_lists.PROFILES.values():
        parts = study_lists.chunks(profile)
        pieces = iter(s for part in parts for s in part)
        for study in profile:
            piece = next(pieces)
            if study.studies == 1:
                assert piece == study
                continue
            cut = [piece] + [next(pieces) for _ in range(study.studies - 1)]
            assert [(s.name, s.studies, s.tuning_study, s.folder) for s in cut] == [
                (study.name, study.studies, k, f"{study.name}/study-{k}")
                for k in range(1, study.studies + 1)
            ]
            assert sum(s.seconds() for s in cut) == pytest.approx(study.seconds())
            assert [s.preset for s in cut] == [study.preset] + [False] * (study.studies - 1)
        assert next(pieces, None) is None
        assert all(sum(s.seconds() for s in part) <= 80 * 60 or len(part) == 1 for part in parts)


@pytest.mark.long
def test_every_study_composes_and_its_variants_apply():
    """Each study's variants as physgrad compare builds them (composed, checked, the scene and rule
    built on the tuning seed); a study that continues networks is checked without its start file."""
    from physgrad.comparison import (
        build_variants,
        check_variants_build,
        split_overrides,
        study_settings,
    )

    built = {}  # each distinct scene built once over all the studies (the same tuning seed)
    for study in (s for profile in study_lists.PROFILES.values() for s in profile):
        overrides = [o for o in study.command(Path("/nowhere")) if not o.startswith("init_from")]
        given, axes, common, _ = split_overrides(overrides)
        s = study_settings(given)
        variants = build_variants(axes, common, s, [])
        assert len(variants) == study.variants()
        check_variants_build(variants, s["tune_seed"], built)


def test_the_ks_study_table_says_when_a_claim_has_nothing_to_compare():
    import importlib.util

    spec = importlib.util.spec_from_file_location("ks_study", REPO / "experiments" / "ks_study.py")
    ks_study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ks_study)
    text = ks_study.claims({("correct", "WIG", 2): {0: (0.1, 0.0)}})  # no prediction runs
    assert "nothing to compare" in text and "nan" not in text


def crossing(final_a: float, s: int) -> Curve:
    """A loss that falls fast and then stops at final_a x base (b's falls steadily to base): A is
    far ahead early and behind at the budget when final_a > 1."""
    loss = base(s) * np.maximum(final_a, 40.0 * np.exp(-X / 60.0))
    return Curve(X, loss, X[-1])


def test_a_claim_is_decided_at_each_fraction_of_its_budget_and_a_reversal_heads_its_row(
    tmp_path, studies
):
    """A ahead at X/4 and behind at X (a claim that turns with the budget): the claim holds at X/4,
    does not at X, and the headline says it reverses; the longer profile's verdicts count for the
    reversal too."""
    slow = {s: Curve(X, base(s) * 100.0 ** (1 - X / X[-1]), X[-1]) for s in TEN}
    studies["oscillator"] = FakeStudy(
        "oscillator",
        {"hig": {s: crossing(3.0, s) for s in TEN}, "adam": slow, "gauss_newton": slow},
    )
    studies["oscillator"].folder = tmp_path / "oscillator"
    claim = next(c for c in claims.CLAIMS if c.name.startswith("oscillators"))
    verdicts = claims.claim_verdicts(claim, tmp_path)
    assert verdicts[0.25] == HOLDS and verdicts[1.0] == FAILS, verdicts
    _, rows = claims.decide_claim(claim, tmp_path, fraction=1.0)
    assert "at X/4" in rows[0][1].measured and "(A better)" in rows[0][1].measured
    table = claims.headline_table(tmp_path, study_lists.PROFILES["claims"])
    row = next(line for line in table.splitlines() if "oscillators" in line)
    assert row.startswith("| **reverses with the budget**: oscillators")
    assert "| holds |" in row and "**does not hold**" in row
    # the paper's hour is no share of iterations
    assert "1000 iterations; the paper's: 3,600 s per method (its run scripts: 60 x 60 s)" in row
    assert "| not run yet |" in row  # the presets' twin has no finished study
    # every variant trained, but the verdict turned between X/2 and X: no evidence against the claim
    assert (
        "| **not tested at the paper's budget** (does not hold at X, but did not fail at X/2" in row
    )
    # a claim that holds at every fraction does not reverse, unless a longer profile's verdict does
    studies["oscillator"] = FakeStudy(
        "oscillator",
        {"hig": {s: falling(0.01 * base(s)) for s in TEN}, "adam": slow, "gauss_newton": slow},
    )
    row = next(
        line
        for line in claims.headline_table(tmp_path, study_lists.PROFILES["claims"]).splitlines()
        if "oscillators" in line
    )
    assert "reverses" not in row and "| holds | holds | **holds** |" in row
    assert (
        "| **supported** (holds at X, every variant having left its start) |" in row
        and "| hig 426x, adam 100x, gauss_newton 100x |" in row
    )
    # ... unless a longer profile's verdict does: read from its own folder, with what it ran
    longer = tmp_path / "claims-long"
    studies[str(longer / "oscillator")] = FakeStudy(
        "oscillator",
        {"hig": {s: crossing(3.0, s) for s in TEN}, "adam": slow, "gauss_newton": slow},
    )
    further = ((longer, study_lists.LONG), (tmp_path / "claims-gpu", study_lists.GPU))
    table = claims.headline_table(tmp_path, study_lists.PROFILES["claims"], further)
    row = next(line for line in table.splitlines() if "oscillators" in line)
    assert row.startswith("| **reverses with the budget**: oscillators"), row
    assert "claims-long, 1000 iterations (8 x 3, 10): holds" in row and "**does not hold**" in row
    # a claim the longer profiles do not run says so; one they run but have not finished too
    studies["quantum"] = FakeStudy("quantum", {"hig": slow, "adam": slow})
    studies["ks_training"] = FakeStudy("ks_training", {})
    studies[str(tmp_path / "claims-gpu" / "ks_training")] = None  # not finished there
    table = claims.headline_table(tmp_path, study_lists.PROFILES["claims"], further)
    row = next(line for line in table.splitlines() if line.startswith("| quantum dipole"))
    assert "not in a longer profile" in row
    row = next(line for line in table.splitlines() if "WIG best" in line)
    assert "| not run yet: needs a GPU: claims-gpu parts 5, 6, 7, 8, about " in row


def test_the_presets_verdict_reads_the_profile_that_ran_the_study(tmp_path, studies):
    """A study name shared by two profiles (oscillator in claims and claims-long) is read with the
    profile that ran it: the claims profile's oscillator has a presets' twin, claims-long's not."""
    claim = next(c for c in claims.CLAIMS if c.name.startswith("oscillators"))
    verdict, rows = claims.decide_claim(claim, tmp_path, "-preset")
    assert verdict == OPEN and "has no finished study" in rows[0][1].why
    verdict, rows = claims.decide_claim(claim, tmp_path, "-preset", profile=study_lists.LONG)
    assert verdict == claims.NOT_RUN and "no presets' twin" in rows[0][1].why


def test_a_trend_over_settings_with_different_numbers_of_tuning_studies_waits(tmp_path, studies):
    """A profile cut into slices can have finished three tuning studies of the easy setting and one
    of the hard: the trend is not decided from the one pair."""
    spread = np.linspace(-0.05, 0.05, 10)

    def runs(ratio):
        return {
            "C": {s: falling(ratio * base(s) * math.exp(spread[(3 * s) % 10])) for s in TEN},
            "R": {s: falling(base(s)) for s in TEN},
        }

    studies["easy"] = three_studies("easy", [runs(0.9)] * 3)
    studies["hard"] = FakeStudy("hard", runs(0.3))
    found, ((_, d),) = claims.decide_claim(
        claim_of(claims.Grows("easy", "hard", "C", "R")), tmp_path
    )
    assert found == OPEN and "3 tuning studies and hard 1" in d.why, d


def test_studies_whose_verdicts_all_support_a_part_agree(tmp_path, studies):
    """Over tuning studies a part is decided by what each study's verdict says of it: for "A close
    to B" both A better and equivalent support it, for "A lower than B" both B better and
    equivalent go against it; for a stall both still falling and rising say "not stalled"."""
    spread = np.linspace(-0.01, 0.01, 10)

    def pair(ratio):
        return {
            "a": {s: falling(ratio * base(s) * math.exp(spread[(3 * s) % 10])) for s in TEN},
            "b": {s: falling(base(s)) for s in TEN},
        }

    # A better (0.5), equivalent (1.0), equivalent
    studies["s"] = three_studies("s", [pair(0.5), pair(1.0), pair(1.0)])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Close("s", "a", "b", 1.25)), tmp_path)
    assert found == HOLDS and "3 of 3" in d.why and "A better, equivalent" in d.why, d
    # for "a lower than b" the same studies are 1 for, 2 against: not settled
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == OPEN and "disagree" in d.why, d
    # B better (2.0), equivalent, B better: A is not lower in any study
    studies["s"] = three_studies("s", [pair(2.0), pair(1.0), pair(2.0)])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Lower("s", "a", "b")), tmp_path)
    assert found == FAILS and "3 of 3" in d.why, d
    noise = lambda s: math.exp(spread[(7 * s) % 10])  # noqa: E731
    shapes = {"slow": (0.1, 0.3), "rising": (3.0, 0.9)}

    def adam(kind):
        final, half = shapes[kind]
        curves = {s: falling(final * base(s) * noise(s), base(s), half * base(s)) for s in TEN}
        return {"adam": curves}

    studies["toy"] = three_studies("toy", [adam("slow"), adam("rising"), adam("slow")])
    found, ((_, d),) = claims.decide_claim(claim_of(claims.Stalls("toy", "adam")), tmp_path)
    assert found == FAILS and "still falling, rising, not stalled, still falling" in d.why, d


def test_the_command_line_checks_its_folder_before_it_writes(tmp_path, capsys):
    """--help prints the usage and a missing study folder is a one-line error: neither writes a
    file or a folder (a mistyped path used to get a claims.md of its own)."""
    with pytest.raises(SystemExit) as help_exit:
        claims.main(["--help"])
    assert help_exit.value.code == 0
    assert "STUDIES" in capsys.readouterr().out
    missing = tmp_path / "claimz"
    assert claims.main([str(missing), str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("claims: error: no study folder") and "\n" not in error
    assert list(tmp_path.iterdir()) == []


def test_a_doc_that_is_missing_a_fifo_a_link_or_not_text_is_one_line(tmp_path, capsys):
    """--doc reads the page through the reading door: a missing file, a FIFO (never waited on), a
    link and bytes that are not text are each one line, and nothing is written."""
    import os

    os.mkfifo(tmp_path / "fifo.md")
    (tmp_path / "binary.md").write_bytes(b"\xff\xfe\x00")
    (tmp_path / "target.md").write_text("x")
    (tmp_path / "link.md").symlink_to(tmp_path / "target.md")
    for name in ("missing.md", "fifo.md", "binary.md", "link.md"):
        assert claims.main([str(tmp_path), "--doc", str(tmp_path / name)]) == 2, name
        error = capsys.readouterr().err.strip()
        assert error.startswith(f"claims: error: --doc {tmp_path / name}: cannot be read")
        assert "\n" not in error
    assert (tmp_path / "target.md").read_text() == "x"


def test_kept_evidence_with_a_variant_its_study_does_not_run_is_one_line(tmp_path, capsys):
    """A row of the kept evidence renamed to a variant the study does not run (it was dropped
    silently, changing a claim's seed counts) ends the page in one line naming it."""
    import shutil

    evidence = tmp_path / "claims"
    shutil.copytree(REPO / "docs" / "evidence" / "claims", evidence)
    table = evidence / "toy_1.csv"
    text = table.read_text()
    assert "\n0,adam,0," in text
    table.write_text(text.replace("\n0,adam,0,", "\n0,nosuchrule,0,", 1))
    assert claims.main([str(evidence), str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert "variant 'nosuchrule' is none of the study's (adam, gauss_newton, hig)" in error
    assert "\n" not in error and not (tmp_path / "out").exists()


def test_docs_claims_says_what_the_kept_evidence_says(monkeypatch):
    """docs/claims.md's verdicts are the ones its committed evidence gives, regenerated now."""
    monkeypatch.chdir(REPO)
    text = (REPO / "docs" / "claims.md").read_text()
    start, end = (text.index(marker) for marker in claims.GENERATED)
    written = text[start + len(claims.GENERATED[0]) : end].strip()
    assert written == claims.evidence_block(Path("docs/evidence/claims")).strip()
