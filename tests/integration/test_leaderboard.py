"""The leaderboard (experiments/leaderboard.py) from kept evidence with known answers: a rule ten
times lower than Adam on every seed of every tuning study is better, one at Adam's level within
noise equivalent, one ten times higher worse, one lower in one study and higher in the others
undecided or worse, never better; rules that do not apply are marked, scenes not run are named."""

import json
import math
import os
import re
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import REPO

sys.path.insert(0, str(REPO / "experiments"))
import leaderboard  # noqa: E402
import leaderboard_cells  # noqa: E402
import leaderboard_detail  # noqa: E402
import leaderboard_keep  # noqa: E402
import leaderboard_rerun  # noqa: E402
import leaderboard_scenes  # noqa: E402
import study_runs  # noqa: E402
import tuned_settings  # noqa: E402
from evidence import write_kept  # noqa: E402

from physgrad.verdict import A_BETTER, B_BETTER, EQUIVALENT  # noqa: E402


def kept_scene(folder, name, levels, studies=3, seeds=10, budget=10.0, first_seed=0, planned=None):  # noqa: E501
    """Evidence of one scene: variant -> (loss at the budget per tuning study), times a small
    per-seed noise shared by every variant (paired seeds), of a protocol of `planned` tuning
    studies (by default those it has: a scene whose studies have all run)."""
    planned = planned or studies
    rng = np.random.default_rng(1)
    noise = np.exp(0.05 * rng.normal(size=(studies, seeds)))
    rows = []
    for variant, by_study in levels.items():
        for k in range(studies):
            for seed in range(seeds):
                value = by_study[k] * noise[k, seed] * (1.0 if variant == "adam" else 1.0)
                rows.append(
                    {
                        "study": k,
                        "variant": variant,
                        "seed": first_seed + k * seeds + seed,
                        "column": "loss",
                        "start": 1.0,
                        **{f"at_{f:g}": value for f in (0.125, 0.25, 0.5, 1.0)},
                    }
                )
    about = {
        "study": name,
        "axis": "calibrated_time",
        "budget": budget,
        "trials": 8,
        "studies": studies,
        "planned": planned,
        "knobs": planned == 4,  # the current protocol's: 4 tuning studies, the rules' knobs
        "seeds": seeds,
        "machine": "test machine",
        "iterations": {v: 100.0 * (i + 1) for i, v in enumerate(levels)},
    }
    write_kept(folder, name, rows, about)


def test_cells_verdicts_and_page_from_kept_evidence(tmp_path):
    evidence = tmp_path / "evidence"
    kept_scene(
        evidence,
        "toy",
        {
            "adam": [1.0, 1.0, 1.0],
            "hig": [0.1, 0.1, 0.1],
            "gd": [1.0, 1.0, 1.0],
            "soap": [10.0, 10.0, 10.0],
            "muon": [0.1, 10.0, 10.0],
        },
        planned=3,  # an earlier protocol's: three tuning studies, the learning rate alone
    )
    found = leaderboard.board(evidence)
    assert set(found) == {"toy"}
    cells = found["toy"][0]
    assert set(cells) == {"hig", "gd", "soap", "muon"}
    assert cells["hig"].verdict == A_BETTER and math.isclose(cells["hig"].ratio, 0.1, rel_tol=0.2)
    assert cells["hig"].wins == cells["hig"].pairs == 30
    assert cells["hig"].studies == (A_BETTER,) * 3
    assert cells["gd"].verdict == EQUIVALENT
    assert cells["soap"].verdict == B_BETTER and cells["soap"].wins == 0
    assert cells["muon"].verdict != A_BETTER and cells["muon"].studies[0] == A_BETTER
    assert cells["hig"].iterations == 200.0

    text = leaderboard.write(evidence, tmp_path / "docs")
    table = [line for line in text.splitlines() if line.startswith("| ")]
    rows = {line.split(" | ")[0][2:]: line for line in table[1:]}
    assert "[**better**](leaderboard/toy.md#hig) 0.1" in rows["hig"] and "30/30" in rows["hig"]
    assert "**worse**" in rows["soap"] and "**equivalent**" in rows["gd"]
    assert "not run" in rows["kfac"]  # a rule that applies but has no runs in the evidence
    assert "Not run yet:" in text and "`guidance`" in text
    # with the profile's parts that would run it and their hours
    guidance = next(e for e in leaderboard_scenes.SCENES if e.name == "guidance")
    where = leaderboard_scenes.where_scene_runs(guidance)
    assert f"`guidance`: {where})" in text
    assert where.startswith("leaderboard parts ") and where.endswith(" h on 2 cores"), where
    assert "3 of 3 tuning studies finished" in text and "hig 200" in text
    # the protocol as the evidence records it
    assert "in each of 3 independent tuning studies" in text and "rests on fewer" in text
    assert "Only the learning rate is tuned" in text and "re-run under" not in text
    # the literature's claims beside the cells that answer them (none run here)
    assert "ssbfgs on KS correction (small): not run yet" in text
    # each cell's link: its rule's section of the scene's page, a row per tuning study and the cell
    detail = (tmp_path / "docs" / "leaderboard" / "toy.md").read_text()
    hig = detail.split("## hig\n")[1].split("\n## ")[0]
    studies = [line for line in hig.splitlines() if line.startswith("| ")][1:]
    assert [row.split(" | ")[0] for row in studies] == ["| 1", "| 2", "| 3", "| over the studies"]
    assert all("| better (interval below 1/1.1" in row for row in studies[:3])
    assert "10 of 10" in studies[0] and "hig 200, adam 100" in studies[0]
    assert "**better**" in studies[3] and "30 of 30" in studies[3]
    muon = detail.split("## muon\n")[1].split("\n## ")[0]
    assert "| 1 | better" in muon and "| 2 | worse" in muon and "**undecided**" in muon
    assert (tmp_path / "docs" / "leaderboard.png").stat().st_size > 10_000
    assert (tmp_path / "docs" / "leaderboard.pdf").is_file()


def test_the_literature_s_cells_say_the_iterations_the_budget_gave_the_rule_and_adam(tmp_path):
    """The papers compare at equal iterations, the leaderboard at equal time: beside each cell
    that answers a paper's claim, the rule's iterations in the budget and Adam's."""
    evidence = tmp_path / "evidence"
    kept_scene(evidence, "burgers_inverse", {"adam": [1.0] * 3, "soap": [10.0] * 3})
    text = leaderboard.write(evidence, tmp_path / "docs")
    line = next(x for x in text.splitlines() if x.startswith("- SOAP"))
    assert "soap on Burgers inverse (exponax): **worse** 10" in line
    assert "(200 iterations in the budget, Adam 100)" in line
    assert "soap on KS correction (small): not run yet;" in line


def test_rules_that_do_not_apply_are_marked_with_why(tmp_path):
    evidence = tmp_path / "evidence"
    kept_scene(evidence, "guidance", {"adam": [1.0] * 3, "hig": [0.5] * 3})
    text = leaderboard.write(evidence, tmp_path / "docs")
    kfac = next(line for line in text.splitlines() if line.startswith("| kfac |"))
    assert "n/a: no layer factors" in kfac
    ssbfgs = next(line for line in text.splitlines() if line.startswith("| ssbfgs |"))
    assert "n/a: a dense inverse Hessian of 13,004 parameters" in ssbfgs
    about = json.loads((evidence / "guidance.json").read_text())
    assert about["budget"] == 10.0
    # a scene with one of its four tuning studies run: its verdicts said to be preliminary
    kept_scene(evidence, "oscillator", {"adam": [1.0], "hig": [0.5]}, studies=1, planned=4)
    text = leaderboard.write(evidence, tmp_path / "docs")
    assert "1 of 4 tuning studies finished (preliminary: a verdict needs 3 of the 4" in text


def test_every_scene_is_a_compare_with_adam_as_baseline_and_parts_stay_near_80_minutes():
    sys.path.insert(0, str(REPO / "experiments"))
    from studies import TUNE_SEED, chunks

    for entry in leaderboard_scenes.SCENES:
        for k in range(1, leaderboard_scenes.LEADERBOARD_STUDIES + 1):
            overrides = entry.study(k).overrides
            assert "compare.baseline=adam" in overrides
            optims = next(o for o in overrides if o.startswith("optim=")).split("=")[1].split(",")
            assert optims[0] == "adam" and set(optims[1:]) | set(entry.refused) == set(
                leaderboard_scenes.RULES
            )
            assert any(o.startswith("trainer.time_budget=") for o in overrides)
            # tuning study k of one compare of three: its tuning seed and evaluation seeds
            assert f"compare.tune_seed={TUNE_SEED + k - 1}" in overrides
            assert f"compare.seed={(k - 1) * leaderboard_scenes.LEADERBOARD_SEEDS}" in overrides
            assert "compare.studies=1" in entry.study(k).command(REPO)
    ks = next(e for e in leaderboard_scenes.SCENES if e.name == "ks").study(2)
    # on the calibrated clock a rule's seeds train in one job, but for the three that search a line
    assert ks.searching() == 3 and ks.eval_jobs() == 8 + 3 * ks.seeds
    parts = leaderboard_scenes.leaderboard_parts()
    # every part is one study of one scene, each in a folder of its own, even where studies
    # would fit in one part's time (a longer study of 22 min), and a longer study k comes after
    # tuning study k, whose settings it reads
    assert sum(len(p) for p in chunks(leaderboard_scenes.LEADERBOARD)) == len(parts)
    longer = [p[0] for p in parts if "/longer-" in p[0].name]
    assert len(parts) - len(longer) == (
        len(leaderboard_scenes.SCENES) * leaderboard_scenes.LEADERBOARD_STUDIES
    )
    assert all(len(part) == 1 for part in parts)
    names = [part[0].name for part in parts]
    assert len(set(names)) == len(parts)
    for study in longer:
        tuning = study.name.replace("/longer-", "/study-")
        assert names.index(tuning) < names.index(study.name), study.name


def test_a_study_run_elsewhere_is_added_to_the_kept_evidence(tmp_path, monkeypatch):
    """Tuning study 2 of a scene, run on another machine than study 1 (whose evidence is kept in the
    old one-study format), is added beside it: both decide the cells, the calibration is kept for
    the studies still to run, keeping it again replaces its rows, and a study at another budget is
    refused in one line."""
    from physgrad.errors import UserError

    levels = {"adam": [1.0], "hig": [0.1]}
    evidence, root = tmp_path / "evidence", tmp_path / "studies"
    kept_scene(evidence, "toy", levels, studies=1, planned=4)  # study 1, kept before
    about = json.loads((evidence / "toy.json").read_text())
    assert "tuning_studies" not in about
    kept_scene(tmp_path / "elsewhere", "toy", levels, studies=1, first_seed=10, planned=4)
    study_2 = study_runs.read_study(tmp_path / "elsewhere" / "toy")
    folder = root / "toy" / "study-2"
    folder.mkdir(parents=True)
    (folder / "runs.csv").write_text("variant,iterations\nadam,300\nhig,100\nhig,140\n")
    (folder / "study.json").write_text(
        json.dumps({"overrides": ["task=toy", "compare.knobs=True", "compare.seed=10"]})
    )
    rules = ("adam", *leaderboard_scenes.SCENES[0].rules)
    ends = leaderboard_scenes.knob_ends(rules)  # the cost-shaping knobs' ends: soap@..., lbfgs@...
    clock = {"costs": {rule: {} for rule in (*rules, *sorted(ends))}}
    (folder / "calibration.json").write_text(json.dumps(clock))
    (folder / "trials.csv").write_text(
        "variant,study,trial,learning_rate,validation_loss,state\n"
        "adam,0,0,0.001,0.5,COMPLETE\nadam,0,1,0.01,0.2,COMPLETE\nadam,0,2,0.1,0.3,COMPLETE\n"
        "hig,0,0,0.1,0.4,COMPLETE\nhig,0,1,1.0,0.6,COMPLETE\nhig,0,2,10.0,0.1,COMPLETE\n"
    )
    read_study = leaderboard_keep.read_study

    def keep(study):  # keep root's one study folder, read as `study`
        monkeypatch.setattr(
            leaderboard_keep, "read_study", lambda path: study if path == folder else None
        )
        try:
            return leaderboard.keep(root, evidence)
        finally:
            monkeypatch.setattr(leaderboard_keep, "read_study", read_study)

    assert keep(study_2) == ["toy/study-2"]
    table = (evidence / "toy.csv").read_text().splitlines()
    assert len(table) == 1 + 2 * 2 * 10  # 2 studies x 2 variants x 10 seeds
    about = json.loads((evidence / "toy.json").read_text())
    assert about["studies"] == 2 and list(about["tuning_studies"]) == ["1", "2"]
    assert about["tuning_studies"]["2"]["iterations"] == {"adam": 300.0, "hig": 120.0}
    assert about["tuning_studies"]["1"]["iterations"] == {"adam": 100.0, "hig": 200.0}
    assert about["iterations"] == {"adam": 200.0, "hig": 160.0}  # medians of the studies'
    # what the study's tuning chose, and the trials it chose from, shown on the page
    assert about["tuning_studies"]["2"]["tuned"] == {
        "adam": {"learning_rate": 0.01},
        "hig": {"learning_rate": 10.0},
    }
    assert len(about["tuning_studies"]["2"]["trials"]) == 6
    shown = tuned_settings.tuned_table(evidence)
    from physgrad.readout import fmt

    tried = [
        t["learning_rate"] for t in about["tuning_studies"]["2"]["trials"] if t["variant"] == "hig"
    ]
    span = f"of [{fmt(min(tried))}, {fmt(max(tried))}]"
    assert f"| toy | hig | study 2: learning_rate=10 {span} *edge* |" in shown, shown
    toy = leaderboard_scenes.SCENES[0]
    assert json.loads((evidence / "toy.calibration.json").read_text()) == clock
    assert leaderboard_scenes.kept_clock(toy, evidence) == evidence / "toy.calibration.json"
    assert (
        f"compare.calibration={evidence / 'toy.calibration.json'}"
        in toy.study(3, leaderboard_scenes.kept_clock(toy, evidence)).overrides
    )
    # a clock without a rule the scene runs now is not used (the study calibrates again)
    for name in ("soap", "lbfgs@memory_size=100"):  # a rule, or a cost-shaping knob's end
        without = {"costs": {k: v for k, v in clock["costs"].items() if k != name}}
        (evidence / "toy.calibration.json").write_text(json.dumps(without))
        assert leaderboard_scenes.kept_clock(toy, evidence) is None, name
    cells = leaderboard.board(evidence)["toy"][0]
    assert cells["hig"].studies == (A_BETTER, A_BETTER) and cells["hig"].pairs == 20

    # kept again: its rows replaced, not added
    assert keep(study_2) == ["toy/study-2"]
    assert (evidence / "toy.csv").read_text().splitlines() == table
    # and the clock replaced by one with every rule
    assert leaderboard_scenes.kept_clock(toy, evidence) == evidence / "toy.calibration.json"

    with pytest.raises(UserError, match="a budget of 20, where .* keeps 10; keep it in another"):
        keep(replace(study_2, budget=20.0))


def test_a_rule_added_after_a_scenes_first_studies_is_decided_over_the_studies_that_ran_it(
    tmp_path,
):
    """A rule in the last of three tuning studies only (added to the leaderboard later): its cell
    is that study's verdict, said to rest on 1 of 3 studies; the rules of every study keep theirs
    over all three."""
    import pandas as pd

    evidence = tmp_path / "evidence"
    levels = {"adam": [1.0] * 3, "hig": [0.1] * 3, "psgd_kron": [0.5] * 3}
    kept_scene(evidence, "toy", levels)
    table = pd.read_csv(evidence / "toy.csv")
    table[~((table.variant == "psgd_kron") & (table.study < 2))].to_csv(
        evidence / "toy.csv", index=False
    )
    cells = leaderboard.board(evidence)["toy"][0]
    assert cells["psgd_kron"].studies == (A_BETTER,) and cells["psgd_kron"].pairs == 10
    assert cells["hig"].studies == (A_BETTER,) * 3 and cells["hig"].pairs == 30
    text = leaderboard.write(evidence, tmp_path / "docs")
    row = next(line for line in text.splitlines() if line.startswith("| psgd_kron |"))
    assert "(1 of 3 studies ran it)" in row and "**](leaderboard/toy.md#psgd_kron) 0.5x" in row
    psgd = (tmp_path / "docs" / "leaderboard" / "toy.md").read_text().split("## psgd_kron\n")[1]
    assert "| 3 | better" in psgd and "| 1 |" not in psgd  # the study that ran it, by number
    hig = next(line for line in text.splitlines() if line.startswith("| hig |"))
    assert "studies ran it" not in hig


@pytest.mark.parametrize(
    ("hig", "verdict", "why"),
    [
        ([0.1, 0.1], "undecided", "2 of 2 tuning studies decided, 3 needed"),
        ([0.1, 0.1, 0.1], A_BETTER, "3 of 3 tuning studies"),
        ([0.1, 0.1, 1.0], "undecided", "the tuning studies disagree"),
    ],
)
def test_a_scene_with_studies_still_to_run_needs_a_majority_of_those_planned(
    tmp_path, hig, verdict, why
):
    """A re-run in progress (4 tuning studies planned): a rule ten times lower than Adam in 2 of
    the 2 kept is not yet better (3 of 4 needed, as for a claim); in 3 of 3 it is; a study at
    Adam's level (equivalent) leaves it undecided; each says how many studies have run."""
    evidence = tmp_path / "evidence"
    kept_scene(evidence, "toy", {"adam": [1.0] * len(hig), "hig": hig}, studies=len(hig), planned=4)
    cell = leaderboard.board(evidence)["toy"][0]["hig"]
    assert cell.verdict == verdict
    assert why in cell.why and f"({len(hig)} of 4 tuning studies run)" in cell.why
    text = leaderboard_cells.cell_text(cell, len(hig), planned=4)
    assert f"({len(hig)} of 4 studies run: " in text


def test_the_committed_page_is_what_the_committed_evidence_gives(tmp_path):
    """docs/leaderboard.md regenerated from docs/evidence/leaderboard, unchanged: nothing in it is
    copied by hand."""
    evidence = REPO / "docs" / "evidence" / "leaderboard"
    assert sorted(p.stem for p in evidence.glob("*.csv")), "no kept evidence"
    text = leaderboard.write(evidence, tmp_path)
    assert text == (REPO / "docs" / "leaderboard.md").read_text()
    pages = sorted(
        str(p.relative_to(REPO / "docs")) for p in (REPO / "docs").glob("leaderboard/**/*.md")
    )
    assert pages == sorted(
        str(p.relative_to(tmp_path)) for p in tmp_path.glob("leaderboard/**/*.md")
    )
    assert "leaderboard/rerun/toy.md" in pages  # the re-run's scene pages too
    for name in pages:
        assert (tmp_path / name).read_text() == (REPO / "docs" / name).read_text()
    for image in ("leaderboard.png", "leaderboard_rerun.png"):
        assert (tmp_path / image).stat().st_size > 10_000
        assert (REPO / "docs" / image).is_file()


def test_studies_on_different_clocks_are_said_to_be(tmp_path):
    """Tuning studies whose rules got other iterations for the budget (each calibrated itself, or
    the clock was replaced when a rule was added) are grouped by clock and the page says so; a
    rule one study ran alone, a 1% difference or one rule's divergences split nothing."""
    same = {"adam": 100.0, "hig": 50.0}
    checked = {"undecided_by_the_clock": {}}  # kept with its clock check: no note for that
    by_study = {
        "1": {"iterations": same},
        "2": {"iterations": {"adam": 100.5, "hig": 50.0, "psgd_kron": 7.0}},
        "3": {"iterations": {"adam": 130.0, "hig": 50.0}},
    }
    assert leaderboard_detail.clock_groups(by_study) == [["1", "2"], ["3"]]
    assert leaderboard_detail.clock_groups({"1": by_study["1"], "2": by_study["2"]}) == [["1", "2"]]
    # a rule that diverged in most seeds of one study (its median stops early) moves no clock
    diverged = {
        "1": {"iterations": {**same, "gd": 70.0}},
        "2": {"iterations": {**same, "gd": 20.0}},
    }
    assert leaderboard_detail.clock_groups(diverged) == [["1", "2"]]
    assert (
        leaderboard_detail.scene_notes({"tuning_studies": {"1": {**by_study["1"], **checked}}})
        == []
    )

    evidence = tmp_path / "evidence"
    kept_scene(evidence, "toy", {"adam": [1.0] * 3, "hig": [0.1] * 3})
    about = json.loads((evidence / "toy.json").read_text())
    (evidence / "toy.json").write_text(json.dumps({**about, "tuning_studies": by_study}))
    text = leaderboard.write(evidence, tmp_path / "docs")
    assert (
        "Its tuning studies ran on 2 clocks (studies 1 and 2; study 3): adam's iterations in the "
        "budget are 100 (study 1), 100 (study 2), 130 (study 3)."
    ) in text
    by_study["3"]["iterations"]["adam"] = 100.0
    (evidence / "toy.json").write_text(json.dumps({**about, "tuning_studies": by_study}))
    assert "iterations in the budget are" not in leaderboard.write(evidence, tmp_path / "docs")


def test_a_better_its_compare_found_undecided_by_the_clock_stays_undecided(tmp_path):
    """A study's "better" that its compare made undecided by the clock (the check reads losses at
    shifted times, which kept evidence does not hold) is kept as such from comparisons.csv and
    stays undecided in the leaderboard's cell; in two of three studies the cell is undecided."""
    from evidence import undecided_by_the_clock

    from physgrad.errors import UserError
    from physgrad.verdict import UNDECIDED

    folder = tmp_path / "study"
    folder.mkdir()
    assert undecided_by_the_clock(folder) == {}  # no comparisons.csv: nothing kept
    (folder / "comparisons.csv").write_text(
        "study,a,b,fraction,verdict,why\n"
        '0,hig,adam,1.0,undecided,"undecided by the clock: A better (p = 0.02), but undecided"\n'
        '0,hig,adam,0.5,A better,"interval below 1/1.1, p = 0.02"\n'
        '0,gd,adam,1.0,B better,"interval above 1.1, p = 0.04"\n'
    )
    assert undecided_by_the_clock(folder) == {"hig vs adam": [1.0]}

    evidence = tmp_path / "evidence"
    kept_scene(evidence, "toy", {"adam": [1.0] * 3, "hig": [0.1] * 3})
    about = json.loads((evidence / "toy.json").read_text())
    flagged = {"undecided_by_the_clock": undecided_by_the_clock(folder)}
    records = {"1": {}, "2": flagged, "3": {}}
    (evidence / "toy.json").write_text(json.dumps({**about, "tuning_studies": records}))
    hig = leaderboard.board(evidence)["toy"][0]["hig"]
    assert hig.studies == (A_BETTER, UNDECIDED, A_BETTER) and hig.verdict == A_BETTER
    records["3"] = flagged
    (evidence / "toy.json").write_text(json.dumps({**about, "tuning_studies": records}))
    hig = leaderboard.board(evidence)["toy"][0]["hig"]
    assert hig.studies == (A_BETTER, UNDECIDED, UNDECIDED) and hig.verdict == UNDECIDED
    # the cell says why over the studies, and the scene page shows it
    assert hig.why.startswith("1 of 3 tuning studies decided, 2 needed: "), hig.why
    records["3"] = {"undecided_by_the_clock": {"hig vs adam": "1.0"}}  # not fractions
    (evidence / "toy.json").write_text(json.dumps({**about, "tuning_studies": records}))
    with pytest.raises(UserError, match="undecided_by_the_clock: not pairs and fractions"):
        leaderboard.board(evidence)


def test_the_iterations_in_the_budget_are_those_of_the_runs_that_reached_it():
    """A diverged run stops early: its iterations say when, not what the budget gives. Seven of
    SSBroyden's ten runs diverged after 110 to 585 iterations, three reached the budget at 1688:
    1688, not the median of all ten (530). A rule none of whose runs reached the budget has no
    figure; a table without statuses counts every run."""
    import pandas as pd

    table = pd.DataFrame(
        {
            "variant": ["ssbroyden"] * 10 + ["adam"] * 2 + ["gd"] * 2,
            "status": ["completed"] * 3 + ["diverged"] * 7 + ["completed"] * 2 + ["diverged"] * 2,
            "iterations": [1688] * 3 + [110, 300, 438, 482, 500, 560, 585] + [4270, 4270, 12, 40],
        }
    )
    assert leaderboard_keep.iterations_in_budget(table) == {"ssbroyden": 1688.0, "adam": 4270.0}
    assert leaderboard_keep.iterations_in_budget(table.drop(columns="status"))["gd"] == 26.0


@pytest.mark.parametrize("scene", ["oscillator", "ks"])
def test_the_per_rule_presets_said_are_those_a_run_of_the_scene_composes(scene):
    """The scene notes name each rule's per-scene preset (conf/tuning); every setting named is the
    one Hydra composes for a run of that scene and rule (a schedule by its optax function and
    arguments), and a rule not named composes the scene's and its optim's own values."""
    from omegaconf import OmegaConf

    from physgrad.configs import compose

    entry = next(e for e in leaderboard_scenes.SCENES if e.name == scene)
    presets = leaderboard_detail.preset_settings(entry)
    assert presets and set(presets) <= {"adam", *entry.rules}
    plain = compose(entry.overrides)
    for rule, settings in presets.items():
        cfg = compose([*entry.overrides, f"optim={rule}"])
        for setting in settings:
            key, said = setting.split("=", 1)
            value = OmegaConf.select(cfg, key)
            if OmegaConf.is_dict(value):
                target = value._target_.rsplit(".", 1)[-1]
                assert said.startswith(f"{target}(") and "init_value" not in said
                for arg in said[len(target) + 1 : -1].split(", "):
                    name, text = arg.split("=")
                    assert str(value[name]).lower() == text.lower(), (rule, setting)
            else:
                assert str(value).lower() == said.lower(), (rule, setting)
    unnamed = next(r for r in entry.rules if r not in presets)
    cfg = compose([*entry.overrides, f"optim={unnamed}"])
    assert cfg.task.batch_size == plain.task.batch_size
    line = leaderboard_detail.preset_line(entry)
    assert all(rule in line for rule in presets) and f"{unnamed} " not in line


def test_the_wall_clock_ratios_are_within_a_study_then_the_median_over_studies():
    """Known answers: a rule's wall-clock seconds over Adam's in the same study (a loaded study
    slows both), the median over the studies that recorded both; only the rules beyond 1.5x
    either way are named; a study kept before wall seconds were recorded does not count."""
    import pandas as pd

    table = pd.DataFrame(
        {
            "variant": ["adam", "adam", "ssbroyden", "ssbroyden", "ssbroyden"],
            "status": ["completed", "completed", "completed", "completed", "diverged"],
            "train_seconds": [20.0, 24.0, 100.0, 120.0, 3.0],
        }
    )
    assert leaderboard_detail.wall_seconds_in_budget(table) == {"adam": 22.0, "ssbroyden": 110.0}
    # Adam's seeds trained together, 10 to a job: the job's time is not one run's, so none
    together = table.assign(wall_time_shared_by=[10, 10, 1, 1, 1])
    assert leaderboard_detail.wall_seconds_in_budget(together) == {"ssbroyden": 110.0}
    studies = {
        "1": {"wall_seconds": {"adam": 20.0, "lbfgs": 60.0, "psgd_kron": 10.0, "soap": 21.0}},
        "2": {"wall_seconds": {"adam": 40.0, "lbfgs": 80.0, "psgd_kron": 28.0, "soap": 40.0}},
        "3": {"wall_seconds": {"adam": 10.0, "lbfgs": 40.0, "psgd_kron": 6.0, "soap": 9.0}},
        "4": {"iterations": {"adam": 100.0}},
    }
    ratios = leaderboard_detail.wall_ratios({"tuning_studies": studies})
    assert ratios == pytest.approx({"lbfgs": 3.0, "psgd_kron": 0.6, "soap": 1.0})
    line = leaderboard_detail.wall_line({"tuning_studies": studies})
    assert "median over 3 tuning studies)" in line and "lbfgs 3x, soap 1x, psgd_kron 0.6x" in line
    assert "beyond 1.5x either way: lbfgs, psgd_kron." in line
    even = {"1": {"wall_seconds": {"adam": 20.0, "soap": 21.0}}}
    assert "soap 1.1x; every one within 1.5x" in leaderboard_detail.wall_line(
        {"tuning_studies": even}
    )
    assert leaderboard_detail.wall_line({"tuning_studies": {"1": {}}}) is None
    # Adam's seeds trained together (not timed one run at a time): the budget stands for a run of
    # Adam's, whose steps cost what the calibration timed; the rules not timed alone are named
    together = {
        "budget": 20.0,
        "iterations": {"adam": 9.0, "lbfgs": 3.0, "soap": 8.0},
        "tuning_studies": {
            "1": {"wall_seconds": {"lbfgs": 30.0}},
            "2": {"wall_seconds": {"lbfgs": 50.0}},
            "3": {"wall_seconds": {"adam": 25.0, "lbfgs": 50.0}},
        },
    }
    assert leaderboard_detail.wall_ratios(together) == pytest.approx({"lbfgs": 2.0})
    line = leaderboard_detail.wall_line(together)
    assert "for adam, whose seeds trained in one job, its run's time is taken as the budget" in line
    assert "not timed one run at a time (their seeds trained in one job): soap)" in line
    assert "lbfgs 2x; beyond 1.5x either way: lbfgs." in line
    assert leaderboard_detail.wall_ratios({**together, "budget": None}) == pytest.approx(
        {"lbfgs": 2.0}  # no budget recorded: the one study that timed Adam
    )
    assert leaderboard_detail.wall_seconds_in_budget(table.drop(columns="train_seconds")) == {}
    # seeds trained together: a seed's share of its job (the job's time over its N seeds), read
    # against Adam's share of its own job of seeds, never against the budget or a run alone
    jobs = pd.DataFrame(
        {
            "variant": ["adam"] * 3 + ["hig"] * 3 + ["lbfgs", "soap", "soap"],
            "status": ["completed"] * 5 + ["diverged", "completed", "completed", "completed"],
            "train_seconds": [150.0] * 3 + [1020.0] * 2 + [7.0, 16.0, 180.0, 180.0],
            "wall_time_shared_by": [10] * 6 + [1, 10, 10],
        }
    )
    shares = leaderboard_detail.wall_seconds_together(jobs)
    assert shares == pytest.approx({"adam": 15.0, "hig": 102.0, "soap": 18.0})
    assert leaderboard_detail.wall_seconds_together(jobs.drop(columns="wall_time_shared_by")) == {}
    vectorised = {
        "budget": 15.0,
        "iterations": {"adam": 9.0, "hig": 3.0, "lbfgs": 5.0, "soap": 8.0, "gd": 9.0},
        "tuning_studies": {
            "1": {
                "wall_seconds": leaderboard_detail.wall_seconds_in_budget(jobs),
                "wall_seconds_together": shares,
            },
            "2": {"wall_seconds_together": {"hig": 30.0, "soap": 20.0}},  # no Adam: not read
        },
    }
    assert leaderboard_detail.wall_ratios(vectorised, "wall_seconds_together") == pytest.approx(
        {"hig": 6.8, "soap": 1.2}
    )
    line = leaderboard_detail.wall_line(vectorised)
    assert "lbfgs 1.1x; seeds trained in one job, its job's time per seed over adam's" in line
    assert "hig 6.8x, soap 1.2x; beyond 1.5x either way: hig." in line
    assert "not timed one run at a time (their seeds trained in one job): gd)" in line
    only = {"1": {"wall_seconds_together": {"adam": 15.0, "hig": 30.0}}}
    assert "(median over 1 tuning study" in leaderboard_detail.wall_line({"tuning_studies": only})
    for order in ([np.nan, 50.0, 300.0], [300.0, np.nan, 50.0]):  # NaN: not a share
        nan = pd.DataFrame(
            {"variant": ["hig"] * 3, "train_seconds": order, "wall_time_shared_by": [10] * 3}
        )
        assert leaderboard_detail.wall_seconds_together(nan) == {"hig": 17.5}
    # a cell whose rule's runs took 1.5x Adam's wall-clock time or more (or 1/1.5 or less) says so
    from leaderboard_cells import Cell, cell_text

    def cell(ratio):
        return Cell("undecided", 1.0, 0.5, 2.0, 5, 10, ("undecided",), 100.0, wall_ratio=ratio)

    for ratio, said in (
        (3.0, ", its runs 3x"),
        (0.6, ", its runs 0.6x"),
        (1.2, ""),
        (math.nan, ""),
    ):
        text = cell_text(cell(ratio))
        assert ("Adam's wall-clock time" in text) == bool(said) and said in text, text


def test_psgd_krons_time_is_said_per_scene_beside_the_fixed_cost_rules():
    """Known answers: PSGD Kron's wall-clock ratio to Adam per scene that recorded it, beside the
    range of gd's, Muon's and SOAP's there; a scene without it is left out; no scene, no line."""
    one = {"1": {"wall_seconds": {"adam": 20.0, "psgd_kron": 13.0, "gd": 19.0, "soap": 21.0}}}
    two = {
        "1": {"wall_seconds": {"adam": 10.0, "psgd_kron": 7.0, "muon": 10.0}},
        "2": {"wall_seconds": {"adam": 10.0, "psgd_kron": 9.0, "muon": 12.0}},
    }
    without = {"1": {"wall_seconds": {"adam": 10.0, "soap": 10.0}}}
    line = leaderboard.scheduled_cost_line(
        {
            "a": {"tuning_studies": one},
            "b": {"tuning_studies": two},
            "c": {"tuning_studies": without},
        },
        {"a": "Scene A"},
    )
    assert "Scene A: 0.65x (gd, Muon, SOAP: 0.95-1.1x); b: 0.8x (gd, Muon, SOAP: 1.1x)" in line
    assert "c:" not in line and "\n" not in line
    assert leaderboard.scheduled_cost_line({"c": {"tuning_studies": without}}, {}) is None
    # a study whose clock charged PSGD Kron its expected cost is not counted: scene b's second
    # study alone is left (0.9x), and a scene with only such studies says nothing
    charged = {**two["1"], "charged_by_schedule": ["psgd_kron"]}
    line = leaderboard.scheduled_cost_line(
        {"b": {"tuning_studies": {"1": charged, "2": two["2"]}}}, {}
    )
    assert "b: 0.9x (gd, Muon, SOAP: 1.2x)" in line
    assert leaderboard.scheduled_cost_line({"b": {"tuning_studies": {"1": charged}}}, {}) is None


def test_the_rules_a_studys_calibration_charged_by_their_schedule_are_read_from_it(tmp_path):
    """charged_by_schedule: the variants with update_seconds in a calibration.json; none from one
    without, from a broken one or from none."""
    import json

    from tests.helpers import scheduled_calibration

    calibration = scheduled_calibration()
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(calibration))
    assert leaderboard_detail.charged_by_schedule(path) == ["psgd_kron"]
    calibration["costs"]["psgd_kron"] = calibration["costs"]["adam"]
    path.write_text(json.dumps(calibration))
    assert leaderboard_detail.charged_by_schedule(path) == []
    path.write_text("{")
    assert leaderboard_detail.charged_by_schedule(path) == []
    assert leaderboard_detail.charged_by_schedule(tmp_path / "none.json") == []


def test_the_rules_a_studys_clock_charged_their_evaluations_are_read_and_said(tmp_path):
    """charged_by_clock: with the rules charged by schedule, those whose calibration timed a line
    search's evaluations (evaluation_seconds); the scene's wall-clock sentence says whether its
    line-search rules were charged the evaluations they made or each step its calibrated cost."""
    import json

    from tests.helpers import scheduled_calibration

    calibration = scheduled_calibration()
    searching = {"evaluation_seconds": 5e-4, "step_evaluations": 2.0}
    calibration["costs"]["lbfgs"] = {**calibration["costs"]["adam"], **searching}
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(calibration))
    charged = leaderboard_detail.charged_by_clock(path)
    assert charged == {"charged_by_schedule": ["psgd_kron"], "charged_by_evaluations": ["lbfgs"]}
    about = {
        "tuning_studies": {
            "1": {"wall_seconds": {"adam": 10.0, "lbfgs": 30.0}, **charged},
        }
    }
    assert "each run was charged those it made" in leaderboard_detail.wall_line(about)
    about["tuning_studies"]["1"]["charged_by_evaluations"] = []
    assert "charged each step at its calibrated cost" in leaderboard_detail.wall_line(about)


@pytest.mark.parametrize(
    "damage, why",
    [
        (
            lambda d: _swap(d / "toy.csv", "\n0,adam,0,", "\n0,nosuchrule,0,"),
            "'nosuchrule' is none",
        ),
        (lambda d: _swap(d / "toy.json", '"adam": 75312.0', '"adam": "many"'), "toy.json: iter"),
        (lambda d: ((d / "toy.csv").unlink(), os.mkfifo(d / "toy.csv")), "a FIFO, not a file"),
    ],
)
def test_crafted_leaderboard_evidence_is_one_line_and_writes_nothing(tmp_path, capsys, damage, why):
    """The page's script reads its evidence as data: a variant that is none of the scene's rules,
    iterations that are not numbers and a FIFO at a table's name each end it with one line (exit
    2) before a file is written."""
    evidence, out = tmp_path / "evidence", tmp_path / "out"
    shutil.copytree(REPO / "docs" / "evidence" / "leaderboard", evidence)
    damage(evidence)
    assert leaderboard.main([str(evidence), str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("leaderboard: error: ") and why in error and "\n" not in error
    assert not out.exists()


def _swap(path, old, new):
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))


def test_the_current_protocols_studies_are_kept_apart_and_shown_as_a_re_run(tmp_path, monkeypatch):
    """Studies of the current protocol (4 tuning studies, compare.knobs=true) are refused in one
    line where a scene's kept evidence is of another (3 studies, the learning rate alone), kept in
    rerun/ instead; the page then keeps its table from the published evidence and adds the re-run's
    progress and preliminary cells; a study folder mixing knobs and none is refused too."""
    from physgrad.errors import UserError

    evidence, root = tmp_path / "evidence", tmp_path / "studies"
    kept_scene(evidence, "toy", {"adam": [1.0] * 3, "hig": [0.1] * 3}, planned=3)
    folder = root / "toy" / "study-1"
    folder.mkdir(parents=True)
    (folder / "runs.csv").write_text("variant,iterations\nadam,300\nhig,100\n")
    (folder / "study.json").write_text(
        json.dumps({"overrides": ["task=toy", "compare.knobs=true", "compare.seed=0"]})
    )
    kept_scene(tmp_path / "elsewhere", "toy", {"adam": [1.0], "hig": [10.0]}, studies=1)
    study = study_runs.read_study(tmp_path / "elsewhere" / "toy")
    monkeypatch.setattr(
        leaderboard_keep, "read_study", lambda path: study if path == folder else None
    )
    with pytest.raises(
        UserError,
        match="keeps studies of another protocol .3 tuning studies, "
        "the learning rate alone tuned.: keep toy.s in another folder",
    ) as error:
        leaderboard.keep(root, evidence)
    assert "\n" not in str(error.value)
    assert leaderboard.keep(root, evidence / "rerun") == ["toy/study-1"]
    about = json.loads((evidence / "rerun" / "toy.json").read_text())
    assert about["knobs"] is True and about["planned"] == 4
    text = leaderboard.write(evidence, tmp_path / "docs")
    assert "Only the learning rate is tuned" in text  # the published table's protocol
    rerun = text[text.index("## The re-run under the current protocol") :]
    assert "toy, lambda 0.01: 1 of 4" in rerun and "oscillators: 0 of 4" in rerun
    hig = next(line for line in rerun.splitlines() if line.startswith("| hig |"))
    # one study of the four planned decides nothing yet; its verdict is said beside the cell
    assert "[**undecided**](leaderboard/rerun/toy.md#hig) 10x" in hig
    assert "(1 of 4 studies run: worse)" in hig
    # its own heat map, beside the earlier protocol's
    assert "![the re-run, preliminary](leaderboard_rerun.png)" in rerun
    assert (tmp_path / "docs" / "leaderboard_rerun.png").stat().st_size > 10_000
    main = text[: text.index("## The re-run")]
    assert "[**better**](leaderboard/toy.md#hig) 0.1" in main  # the published cell, unchanged
    # the page says at its head that its table is the earlier protocol's, and how far the re-run is
    head = text[: text.index("![leaderboard]")]
    assert "**The table and figure below are from an earlier protocol**" in head
    assert "has kept 1 of 32 studies so far" in head
    without = tmp_path / "without"
    shutil.copytree(evidence, without, ignore=shutil.ignore_patterns("rerun"))
    assert "earlier protocol" not in leaderboard.write(without, tmp_path / "docs2")
    # a scene's kept clock for the profile's studies is the re-run's
    assert leaderboard_scenes.kept_clock.__defaults__[0] == leaderboard_scenes.RERUN
    (root / "toy" / "study-2").mkdir()
    shutil.copy(folder / "runs.csv", root / "toy" / "study-2" / "runs.csv")
    (root / "toy" / "study-2" / "study.json").write_text(json.dumps({"overrides": ["task=toy"]}))
    monkeypatch.setattr(
        leaderboard_keep, "read_study", lambda path: study if path.parent.name == "toy" else None
    )
    with pytest.raises(UserError, match="a study run without compare.knobs=true"):
        leaderboard.keep(root, tmp_path / "fresh")
    # a scene the published evidence never ran is not kept beside its other protocol's scenes
    shutil.rmtree(root / "toy" / "study-2")
    (root / "oscillator" / "study-1").mkdir(parents=True)
    shutil.copy(folder / "runs.csv", root / "oscillator" / "study-1" / "runs.csv")
    shutil.copy(folder / "study.json", root / "oscillator" / "study-1" / "study.json")
    shutil.rmtree(root / "toy")
    monkeypatch.setattr(
        leaderboard_keep,
        "read_study",
        lambda path: study if path.parent.name == "oscillator" else None,
    )
    with pytest.raises(UserError, match="toy.json keeps studies of another protocol"):
        leaderboard.keep(root, evidence)
    assert not (evidence / "oscillator.json").exists()


def test_the_re_runs_cells_link_to_its_scene_pages_with_what_each_study_tuned(tmp_path):
    """The re-run's preliminary cells link to its own scene pages (docs/leaderboard/rerun), which
    give each study's tuned values with the span its trials tried, *edge* in the outer tenth of it
    (known answers); its section gives each scene's budget line, where a preset the studies tuned
    is not said as a preset; the published pages stay where they were."""
    evidence = tmp_path / "evidence"
    kept_scene(evidence, "toy", {"adam": [1.0] * 3, "hig": [0.1] * 3}, planned=3)
    rerun = evidence / "rerun"
    levels = {"adam": [1.0] * 2, "hig": [0.1] * 2, "gauss_newton": [1.0] * 2}
    kept_scene(rerun, "toy", levels, studies=2, planned=4)
    about = json.loads((rerun / "toy.json").read_text())
    tried = [1e-9, 1e-7, 1e-5, 1e-3]

    def trials(rule, k, tied=False):  # the tau of each trial; the learning rate the same
        return [
            {"variant": rule, "learning_rate": 0.1 * k, "tau": t, "validation_loss": 1.0 + i}
            | ({"validation_loss": 1.0} if tied else {})
            for i, t in enumerate(tried)
        ]

    about["tuning_studies"] = {
        str(k): {
            "iterations": about["iterations"],
            "undecided_by_the_clock": {},
            # study 1 chose a tau in the middle of its trials' span, study 2 one at its top
            "tuned": {
                "gauss_newton": {"learning_rate": 0.1 * k, "tau": [1e-6, 1e-3][k - 1]},
                **({"hig": {"learning_rate": 0.1, "tau": 1e-9}} if k == 1 else {}),
            },
            # study 1's HIG: every trial the same loss (no step in the budget), so none was chosen
            "trials": trials("gauss_newton", k) + (trials("hig", k, tied=True) if k == 1 else []),
        }
        for k in (1, 2)
    }
    (rerun / "toy.json").write_text(json.dumps(about))
    # a scene only the re-run has run is said so under the earlier table, not "not run yet"
    kept_scene(rerun, "ode_control_full", {"adam": [1.0], "hig": [0.1]}, studies=1, planned=4)
    text = leaderboard.write(evidence, tmp_path / "docs")
    earlier = text[: text.index("## The re-run")]
    assert "Run under the current protocol only (the re-run's section below): " in earlier
    assert "full batch (`ode_control_full`)." in earlier
    not_run = next(line for line in earlier.splitlines() if line.startswith("Not run yet: "))
    assert "`burgers_inverse_full`" in not_run and "`ode_control_full`" not in not_run
    section = text[text.index("## The re-run under the current protocol") :]
    row = next(line for line in section.splitlines() if line.startswith("| gauss_newton |"))
    assert "[**undecided**](leaderboard/rerun/toy.md#gauss_newton)" in row
    assert "- **toy, lambda 0.01** (`task=toy task.scale=0.01`)" in section
    assert "2 of 4 tuning studies finished (preliminary: a verdict needs 3 of the 4" in section
    # the toy's preset of Gauss-Newton's tau (conf/tuning/toy_gauss_newton.yaml) is tuned here
    assert "optim.tau" not in section
    assert "optim.tau=" in text[: text.index("## The re-run")]  # the published studies': a preset
    page = (tmp_path / "docs" / "leaderboard" / "rerun" / "toy.md").read_text()
    assert "(the re-run under the current protocol)" in page.splitlines()[0]
    assert "[leaderboard](../../leaderboard.md#the-re-run-under-the-current-protocol-in-" in page
    gauss = page.split("## gauss_newton\n")[1].split("\n## ")[0]
    rows = [line for line in gauss.splitlines() if line.startswith("| ")]
    assert rows[0].endswith("| iterations | tuned |")
    assert rows[1].endswith("| learning_rate=0.1 of [0.1, 0.1], tau=1e-06 of [1e-09, 0.001] |")
    assert rows[2].startswith("| 2 |") and rows[2].endswith("tau=0.001 of [1e-09, 0.001] *edge* |")
    assert rows[3].startswith("| over the studies |") and rows[3].count("|") == rows[0].count("|")
    hig = page.split("## hig\n")[1].split("\n## ")[0]
    assert "| untuned: its 4 trials tied (the first one's settings ran) |" in hig
    assert "| - |" in hig  # a rule whose tuning the record does not give
    # the baseline's own losses per study, which every ratio is over
    adam = page.split("## adam (the baseline)\n")[1].split("\n## ")[0]
    assert [line.split(" | ")[0] for line in adam.splitlines() if line[:3] in ("| 1", "| 2")] == [
        "| 1",
        "| 2",
    ]
    assert "Detectable:" in gauss
    assert (tmp_path / "docs" / "leaderboard" / "toy.md").is_file()  # the published scene's
    one = (tmp_path / "docs" / "leaderboard" / "rerun" / "ode_control_full.md").read_text()
    assert "Detectable: not stated from one tuning study" in one


def test_the_expensive_rules_are_read_again_at_four_times_the_budget(tmp_path, monkeypatch):
    """A rule whose calibrated step costs more than 10 of Adam's gets a study of its own at 4x the
    budget per tuning study: Adam and those rules at the settings tuning study k chose
    (compare.tuned_in=<root>/<scene>/study-k), on study k's seeds and the scene's kept clock; none
    for a scene whose rules all cost less. Its runs are kept as <scene>_longer and the page reads
    each expensive rule's cell there beside the budget's."""
    clock = tmp_path / "toy.calibration.json"
    costs = {rule: {"step_seconds": 1e-3} for rule in ("adam", *leaderboard_scenes.RULES)}
    costs["hig"]["step_seconds"] = 2e-2  # 20 of Adam's steps
    costs["gauss_newton"]["step_seconds"] = 9e-3  # 9: not expensive
    clock.write_text(json.dumps({"costs": costs}))
    toy = leaderboard_scenes.SCENES[0]
    assert toy.expensive(clock) == ("hig",) and toy.expensive(None) == ()
    # the points a clock must have, Gauss-Newton's too (its file names hig's kernel as a default)
    needed = leaderboard_scenes.knob_ends(("hig", "gauss_newton", "adam"))
    assert needed == {f"{r}@tau={t}" for r in ("hig", "gauss_newton") for t in (1e-9, 1e-6, 1e-3)}
    older = tmp_path / "older.json"  # an older clock, without a rule added since: not expensive
    older.write_text(json.dumps({"costs": {k: v for k, v in costs.items() if k != "soap"}}))
    assert toy.expensive(older) == ("hig",)
    # a knob's value the tuning may choose counts: Gauss-Newton's SVD below tau 1e-6 at 11 of
    # Adam's steps makes it expensive, SOAP's dearest frequency at 9 does not
    knobs = tmp_path / "knobs.json"
    timed = {"gauss_newton@tau=1e-09": 1.1e-2, "soap@precondition_frequency=1": 9e-3}
    knobs.write_text(
        json.dumps({"costs": {**costs, **{k: {"step_seconds": v} for k, v in timed.items()}}})
    )
    assert toy.expensive(knobs) == ("gauss_newton", "hig")
    # a rule with fewer than 100 steps even at 4x the budget at its cheapest timed step is not read
    # again (3 steps in 40 s would decide its step's cost again), and the page says what 100 steps
    # take: Levenberg-Marquardt at 0.5 s a step; HIG too at its preset, but 0.3 s at a tau (133)
    slow = {"levenberg_marquardt": 0.5, "hig": 0.5, "hig@tau=1e-09": 0.3}
    (tmp_path / "far").mkdir()
    far = tmp_path / "far" / "toy.calibration.json"
    far.write_text(
        json.dumps({"costs": {**costs, **{k: {"step_seconds": v} for k, v in slow.items()}}})
    )
    assert toy.expensive(far) == ("hig", "levenberg_marquardt")
    assert toy.beyond_reach(far) == {"levenberg_marquardt": pytest.approx(50.0)}
    assert toy.beyond_reach(clock) == {} and toy.beyond_reach(None) == {}
    assert "optim=adam,hig" in toy.longer(1, far).command(tmp_path / "root")
    said = leaderboard_rerun.rerun_text(tmp_path / "far", {})
    assert (
        "section 7): provisional, from clocks each scene's first study measures again: toy, "
        "lambda 0.01: hig. On toy, lambda 0.01, levenberg_marquardt is not read again: even at 4x "
        "the budget (40 s) it gets fewer than 100 steps (100 of levenberg_marquardt's take 50 s), "
        "so its cell measures a step's cost, not the rule."
    ) in said
    longer = toy.longer(2, clock)
    command = longer.command(tmp_path / "root")
    assert longer.name == "toy/longer-2" and "optim=adam,hig" in command
    from study_profiles import _study_plan

    assert "not tuned here" in _study_plan(longer) and "tuning jobs" not in _study_plan(longer)
    assert "tuning jobs" in _study_plan(toy.study(2))
    assert f"trainer.time_budget={4 * toy.budget:g}" in command
    # the toy's study 2 is kept in the re-run: its kept trials, until its folder holds its own
    assert f"compare.tuned_in={tmp_path / 'root'}/toy/study-2.kept" in command
    (tmp_path / "root" / "toy" / "study-2").mkdir()
    (tmp_path / "root" / "toy" / "study-2" / "trials.csv").write_text("variant,study\n")
    assert f"compare.tuned_in={tmp_path / 'root'}/toy/study-2" in longer.command(tmp_path / "root")
    assert f"compare.calibration={clock}" in command and "compare.seed=10" in command
    assert f"compare.dir={tmp_path / 'root'}/toy/longer-2" in command
    # a scene without a complete kept clock (one from before a knob's points): which rules get few
    # steps from its presets' costs, and the clock study k calibrated for itself, from its folder
    command = toy.longer(2, None, clock).command(tmp_path / "root")
    assert "optim=adam,hig" in command
    assert f"compare.calibration={tmp_path / 'root'}/toy/study-2/calibration.json" in command
    assert toy.longer(2, None) is None
    costs["hig"]["step_seconds"] = 5e-3
    clock.write_text(json.dumps({"costs": costs}))
    assert toy.longer(2, clock) is None

    root, evidence = tmp_path / "studies", tmp_path / "evidence"
    kept_scene(evidence, "toy", {"adam": [1.0] * 4, "hig": [2.0] * 4}, studies=4)
    folder = root / "toy" / "longer-1"
    folder.mkdir(parents=True)
    (folder / "runs.csv").write_text("variant,iterations\nadam,3000\nhig,150\n")
    (folder / "study.json").write_text(
        json.dumps({"overrides": ["task=toy", "compare.knobs=true"]})
    )
    kept_scene(
        tmp_path / "elsewhere",
        "toy",
        {"adam": [1.0], "hig": [0.1]},
        studies=1,
        budget=40.0,
        planned=4,
    )
    study = study_runs.read_study(tmp_path / "elsewhere" / "toy")
    monkeypatch.setattr(leaderboard_keep, "read_study", lambda p: study if p == folder else None)
    assert leaderboard.keep(root, evidence) == ["toy/longer-1"]
    assert json.loads((evidence / "toy_longer.json").read_text())["budget"] == 40.0
    text = leaderboard.write(evidence, tmp_path / "docs")
    line = next(line for line in text.splitlines() if line.startswith("  At 4x the budget (40 s"))
    # one of the four longer studies: not yet decided (3 of 4 needed)
    assert "1 of 4 studies" in line and "hig **undecided** 0.1x" in line and "150 steps" in line
    hig = next(line for line in text.splitlines() if line.startswith("| hig |"))
    assert "worse" in hig  # at the budget, from the scene's own studies
    # the scene's page: hig's studies at the budget, then its longer study's row and cell
    page = (tmp_path / "docs" / "leaderboard" / "toy.md").read_text()
    section = page.split("## hig\n")[1]
    at_budget, at_longer = section.split("At 4x the budget (40 s)")
    assert [row[:5] for row in at_budget.splitlines() if row.startswith("| ")][1:] == [
        "| 1 |",
        "| 2 |",
        "| 3 |",
        "| 4 |",
        "| ove",
    ]
    rows = [row for row in at_longer.splitlines() if row.startswith("| ")][1:]
    assert rows[0].startswith("| 1 | better") and "0.1 [" in rows[0] and "hig 150" in rows[0]
    assert rows[1].startswith("| over the studies | **undecided**") and len(rows) == 2
    assert "At 4x" not in page.split("## hig\n")[0]  # adam is not read again against itself


def test_a_longer_study_reads_the_kept_trials_where_its_tuning_studys_folder_has_gone(tmp_path):
    """compare.tuned_in=<root>/<scene>/study-k, whose folder went with the machine that ran it,
    becomes <root>/<scene>/study-k.kept: the trials tuning study k kept in the scene's record, from
    which compare's own rule picks what the study tuned (the lowest finite validation loss, the
    first of a tie; NaN and infinity never); a folder with its trials.csv, a record without study k
    and any other override are left as they are. On every study kept in the re-run, compare's pick
    from the kept trials is the tuned setting the record states."""
    from studies import kept_tuned_in

    from physgrad.comparison.spec import Variant
    from physgrad.comparison.tuned_in import tuned_in

    nan, inf = float("nan"), float("inf")
    trials = [
        {"variant": "adam", "learning_rate": 1e-3, "validation_loss": 0.5},
        {"variant": "adam", "learning_rate": 1e-2, "validation_loss": 0.2},
        {"variant": "adam", "learning_rate": 2e-2, "validation_loss": 0.2},  # a tie: not chosen
        {"variant": "adam", "learning_rate": 5e-2, "validation_loss": nan},
        {
            "variant": "soap",
            "learning_rate": 1e-3,
            "precondition_frequency": 6.0,
            "validation_loss": inf,
        },  # fmt: skip
        {
            "variant": "soap",
            "learning_rate": 2e-3,
            "precondition_frequency": 40.0,
            "validation_loss": 0.1,
        },  # fmt: skip
    ]
    record = tmp_path / "toy.json"
    record.write_text(json.dumps({"tuning_studies": {"2": {"trials": trials}}}))
    folder = tmp_path / "root" / "toy" / "study-2"
    said = kept_tuned_in(f"compare.tuned_in={folder}", record, 2)
    assert said == f"compare.tuned_in={folder}.kept"
    adam = Variant("adam", [], None, {"learning_rate": (1e-5, 0.1)})
    soap = Variant(
        "soap", [], None, {"learning_rate": (1e-5, 0.1), "precondition_frequency": (1, 100)}
    )
    assert tuned_in(Path(f"{folder}.kept"), [adam, soap], 1) == [
        {
            "adam": {"learning_rate": 1e-2},
            "soap": {"learning_rate": 2e-3, "precondition_frequency": 40},
        }  # noqa: E501
    ]
    assert kept_tuned_in(f"compare.tuned_in={folder}", record, 3).endswith("study-2")
    assert kept_tuned_in("compare.seed=10", record, 2) == "compare.seed=10"
    folder.mkdir(parents=True)  # the study runs again here, unfinished: compare reads it (or says)
    assert kept_tuned_in(f"compare.tuned_in={folder}", record, 2).endswith("study-2")

    checked = 0
    for path in sorted(leaderboard_scenes.RERUN.glob("*.json")):
        if path.name.endswith("calibration.json"):
            continue
        for k, study in json.loads(path.read_text())["tuning_studies"].items():
            if "trials" not in study:
                continue
            spaces = {}
            for t in study["trials"]:
                for key, value in t.items():
                    if key not in ("variant", "validation_loss") and math.isfinite(value):
                        low, high = spaces.setdefault(t["variant"], {}).get(key, (value, value))
                        spaces[t["variant"]][key] = (min(low, value), max(high, value))
            variants = [Variant(name, [], None, space) for name, space in spaces.items()]
            where = tmp_path / "kept" / path.stem / "study-9"
            override = kept_tuned_in(f"compare.tuned_in={where}", path, int(k))
            (picked,) = tuned_in(Path(override.partition("=")[2]), variants, 1)
            assert picked == {v.name: study["tuned"].get(v.name, {}) for v in variants}
            checked += 1
    assert checked >= 2  # the toy's four and the oscillators' first at least


def test_a_study_whose_baseline_trained_far_worse_is_said_on_the_scene_page(tmp_path):
    """Known answer: Adam at 1 in studies 1-3 and 100 in study 4 (100x the studies' median) is
    named on the scene page with its factor; with study 4 at 5 (5x) nothing is said."""
    for worst, said in ((100.0, True), (5.0, False)):
        evidence = tmp_path / str(worst)
        kept_scene(evidence, "toy", {"adam": [1.0, 1.0, 1.0, worst], "hig": [0.1] * 4}, 4)
        leaderboard.write(evidence, tmp_path / str(worst) / "docs")
        page = (tmp_path / str(worst) / "docs" / "leaderboard" / "toy.md").read_text()
        factor = re.search(r"study 4's [0-9.]+, ([0-9.]+)x the studies' median", page)
        assert (factor is not None and 90 < float(factor[1]) < 110) is said
        assert ("far above the other studies'" in page) is said
    # a study whose Adam diverged on every seed keeps its row, said so
    evidence = tmp_path / "diverged"
    kept_scene(evidence, "toy", {"adam": [1.0, 1.0, 1.0, math.nan], "hig": [0.1] * 4}, 4)
    leaderboard.write(evidence, evidence / "docs")
    page = (evidence / "docs" / "leaderboard" / "toy.md").read_text()
    assert "| 4 | - (diverged on 10 of 10 seeds) | - | - |" in page


def test_a_cell_on_few_steps_says_the_steps_within_its_budget():
    """A run's last step crosses the budget and is not read (docs/protocol.md, section 6): 79
    steps taken are 78 within the budget; 1 taken is none, Adam against the untrained network;
    100 or more say nothing."""
    assert leaderboard_cells.few_steps(79).startswith(", 78 steps within the budget: decided")
    assert leaderboard_cells.few_steps(2).startswith(", 1 step within the budget")
    assert "Adam against the untrained network" in leaderboard_cells.few_steps(1)
    assert leaderboard_cells.few_steps(100) == leaderboard_cells.few_steps(float("nan")) == ""
    # a median over the runs can be a half: 99.5 taken are 98 within; 1.5 are none
    assert leaderboard_cells.few_steps(99.5).startswith(", 98 steps within the budget")
    assert "Adam against the untrained network" in leaderboard_cells.few_steps(1.5)


def test_a_cell_tuned_at_its_trials_edge_in_most_studies_says_so():
    """Known answers: an edge in 3 of 4 studies is said, in 2 of 4 not (one edge among 8 random
    points is common), in 1 of 1 not (one study says nothing of most); a longer cell of 2 studies
    says the edge of its settings' tuning at the budget, 4 of 4, never of its own 2."""
    from leaderboard_cells import Cell, cell_text, longer_lines

    def cell(edge, studies):
        return Cell("undecided", 1.0, 0.5, 2.0, 5, 10, ("undecided",) * studies, 500.0, edge=edge)

    said = "tuned at the edge of what its trials tried in {} of {} studies"
    assert said.format(3, 4) in cell_text(cell(3, 4), 4)
    assert "edge" not in cell_text(cell(2, 4), 4)
    assert "edge" not in cell_text(cell(1, 1), 1)
    runs = study_runs.StudyRuns(Path("x"), "calibrated_time", 10.0, {}, planned=4)
    runs = replace(runs, tuning=(runs, runs))
    line = longer_lines(None, ({"hig": cell(0, 2)}, runs, {}), 10.0, {"hig": cell(4, 4)})[0]
    assert said.format(4, 4) in line and said.format(4, 2) not in line


def test_a_clock_measured_on_another_kind_of_machine_is_said(tmp_path):
    """A scene whose kept clock names AMD EPYC while its runs ran on a Xeon says so; the same kind,
    a clock without a machine, or no clock says nothing."""
    clock = tmp_path / "toy.calibration.json"
    clock.write_text(json.dumps({"machine": {"cpu_model": "AMD EPYC", "cpu_count": 2}}))
    xeon = "Intel(R) Xeon(R) Processor (2 cores)"
    said = leaderboard_detail.clock_machine_note(clock, xeon)
    assert said == (
        "; its clock was calibrated on AMD EPYC (2 cores), so each rule's iterations in the "
        "budget follow that machine's step costs"
    )
    assert leaderboard_detail.clock_machine_note(clock, "AMD EPYC (2 cores)") == ""
    assert leaderboard_detail.clock_machine_note(tmp_path / "none.json", xeon) == ""
    clock.write_text(json.dumps({"costs": {}}))
    assert leaderboard_detail.clock_machine_note(clock, xeon) == ""
