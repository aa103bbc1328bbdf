"""End-to-end layer of `physgrad compare` through the console script: a study on a user's own scene
tuned, evaluated and resumed, a study stopped by signals at random instants resuming to the same
trials, continued networks paired with each seed's own start, and --plan training nothing."""

import csv
import math
import re
import shutil
from pathlib import Path

import pytest

import physgrad
from tests.helpers import REPO, console

EXAMPLE = REPO / "examples" / "custom_scene"


@pytest.mark.long
def test_a_study_on_a_users_own_scene_end_to_end_and_resumed(tmp_path):
    """examples/custom_scene (the pendulum) with Adam against HIG through the console script: tuning
    trials on the tuning seed scored by validation loss, 7 paired seeds, verdict tables and CSVs;
    run again it trains nothing new; with one evaluation file lost it runs that job alone."""
    study = tmp_path / "study"
    args = [
        "compare",
        "-cd",
        "conf",
        "task=pendulum",
        "optim=adam,hig",
        "trainer.iterations=24",
        "task.train_size=64",
        "task.test_size=32",
        "compare.trials=3",
        "compare.studies=1",
        "compare.seeds=7",
        f"compare.dir={study}",
    ]
    first = console(*args, cwd=EXAMPLE)
    assert "| adam vs hig |" in first.stdout and (study / "compare.md").read_text() in first.stdout
    trials = list(csv.DictReader(open(study / "trials.csv")))
    assert [t["variant"] for t in trials] == ["adam"] * 3 + ["hig"] * 3
    assert all(t["state"] == "COMPLETE" and float(t["validation_loss"]) > 0 for t in trials)
    tuned = [physgrad.read_run(p) for p in sorted((study / "tune").rglob("results.h5"))]
    assert len(tuned) == 6 and {r.attrs["seed"] for r in tuned} == {1_000_000}
    assert all("validation_loss" in r.eval for r in tuned)
    runs = list(csv.DictReader(open(study / "runs.csv")))
    assert sorted((r["variant"], int(r["seed"])) for r in runs) == [
        (v, s) for v in ("adam", "hig") for s in range(7)
    ]
    rates = {r["variant"]: physgrad.read_run(r["path"]).attrs["config"] for r in runs}
    best = {
        v: min((t for t in trials if t["variant"] == v), key=lambda t: float(t["validation_loss"]))
        for v in ("adam", "hig")
    }
    for variant in ("adam", "hig"):
        assert f"learning_rate: {float(best[variant]['learning_rate'])!r}" in rates[variant]
    comparisons = list(csv.DictReader(open(study / "comparisons.csv")))
    assert [(c["a"], c["b"], float(c["fraction"])) for c in comparisons] == [
        ("adam", "hig", f) for f in (0.25, 0.5, 1.0)
    ]
    assert all(
        c["verdict"] in ("A better", "B better", "equivalent", "undecided") for c in comparisons
    )
    assert int(comparisons[-1]["pairs"]) == 7 and math.isfinite(
        float(comparisons[-1]["median_ratio"])
    )
    assert (study / "sensitivity.png").stat().st_size > 0 and (
        study / "report" / "loss_vs_iteration.png"
    ).exists()

    stamps = {p: p.stat().st_mtime_ns for p in study.rglob("results.h5")}
    again = console(*args, cwd=EXAMPLE)
    assert {
        p: p.stat().st_mtime_ns for p in study.rglob("results.h5")
    } == stamps  # nothing trained again
    assert again.stdout.split("## Verdicts")[1] == first.stdout.split("## Verdicts")[1]

    lost = next(iter(sorted((study / "eval").glob("+compare_job=eval_v1*"))))  # HIG's 7 seeds
    shutil.rmtree(lost)
    console(*args, cwd=EXAMPLE)
    changed = [p for p in study.rglob("results.h5") if stamps.get(p) != p.stat().st_mtime_ns]
    assert len(changed) == 7 and all(lost in p.parents for p in changed)
    other = console(*args[:-1], f"compare.dir={study}", "compare.seeds=8", cwd=EXAMPLE, check=False)
    assert other.returncode == 2 and "holds another study" in other.stderr


@pytest.mark.long
def test_a_study_stopped_at_random_instants_resumes_to_the_same_trials(tmp_path):
    """SIGTERM to `physgrad compare` while its tuning or evaluation multirun trains (its own
    session: the signal is passed on once), at random instants, PHYSGRAD_FAULT_REPEATS times: it
    exits 130, leaves no process behind, and the same command then finishes with exactly
    compare.trials trials per variant, none asked twice."""
    import os
    import random
    import signal
    import subprocess
    import time

    from tests.helpers import PHYSGRAD

    # a study per kill: 5 at make test-faults
    repeats = max(1, int(os.environ.get("PHYSGRAD_FAULT_REPEATS", "1")) // 4)
    rng = random.Random(0)
    stopped = 0
    for attempt in range(repeats):
        study = tmp_path / f"study{attempt}"
        args = [
            PHYSGRAD,
            "compare",
            "task=toy",
            "optim=adam,gd",
            "trainer.iterations=400",
            "compare.trials=3",
            "compare.studies=1",
            "compare.seeds=6",
            f"compare.dir={study}",
            "figures=false",  # the tables only: what is checked
        ]
        process = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        # a tuning job's first file (trials trained together write one per member, a level down)
        deadline = time.time() + 120
        while not any((study / "tune").rglob("results.h5")) and time.time() < deadline:
            time.sleep(0.1)
        assert time.time() < deadline, "no tuning job wrote a results file in 120 s"
        time.sleep(rng.uniform(0.0, 3.0))
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=120)
        if process.returncode == 0:  # finished before the signal: nothing to resume
            continue
        stopped += 1
        assert process.returncode == 130 and "run the same command again to resume" in output, (
            output
        )
        leftover = subprocess.run(
            ["pgrep", "-f", f"compare.dir={study}|hydra.sweep.dir={study}"],
            capture_output=True,
            text=True,
        ).stdout.split()
        assert not leftover, leftover
        finished = subprocess.run(args, capture_output=True, text=True, timeout=300)
        assert finished.returncode == 0, finished.stdout[-2000:] + finished.stderr[-2000:]
        trials = list(csv.DictReader(open(study / "trials.csv")))
        assert [t["variant"] for t in trials] == ["adam"] * 3 + ["gd"] * 3
        assert all(t["state"] == "COMPLETE" for t in trials)
        assert len(list(csv.DictReader(open(study / "runs.csv")))) == 12
    assert stopped, "every study finished before its signal: nothing was resumed"


@pytest.mark.long
def test_a_study_that_continues_networks_pairs_each_seed_with_its_own_start(tmp_path):
    """init_from='<start>/seed=${seed}/results.h5': every tuning and evaluation job (one per seed)
    starts from the network of its own seed; the runs say which, and are read after their own
    training."""
    from physgrad.readout import loss_at
    from physgrad.results import read_run

    start = tmp_path / "start"
    console(
        "run",
        "-m",
        "task=toy",
        "trainer.iterations=20",
        "figures=false",
        "seed=0,1,1000000",
        f"hydra.sweep.dir={start}",
        "hydra.sweep.subdir='seed=${seed}'",
    )
    study = physgrad.compare(
        "task=toy",
        "optim=adam,gd",
        "trainer.iterations=20",
        "compare.trials=1",
        "compare.studies=1",
        "compare.seeds=2",
        f"init_from='{start}/seed=${{seed}}/results.h5'",
        f"compare.dir={tmp_path / 'study'}",
        "figures=false",
    )
    assert len(study.runs) == 4
    for path in [*study.runs.path, *(tmp_path / "study" / "tune").glob("*/results.h5")]:
        run = read_run(Path(path))
        assert run.attrs["init_from"] == str(start / f"seed={run.attrs['seed']}" / "results.h5")
    # each run is read after its own 20 iterations, not at the network it started from
    started_at = {s: loss_at(read_run(start / f"seed={s}" / "results.h5")) for s in (0, 1)}
    assert all(row.test_loss_at_1 != started_at[row.seed] for row in study.runs.itertuples())
    assert study.trials.validation_loss.nunique() == 2  # adam's and gd's trial


# two jobs run to cost the phases (10 s): make test-long; the plan's costs are checked in-process in
# tests/integration/test_compare.py
@pytest.mark.long
def test_plan_prints_the_estimate_and_trains_nothing(tmp_path):
    out = console(
        "compare",
        "--plan",
        "task=toy",
        "optim=adam,gd",
        "trainer.iterations=50",
        f"compare.dir={tmp_path / 'study'}",
    )
    assert "| adam |" in out.stdout and "| gd |" in out.stdout and "Total: about" in out.stdout
    composed = r"composing and checking the variants \(\d+ s, measured here\) included"
    assert re.search(composed, out.stdout)
    # the phases' own costs, from two jobs run as a phase runs them (its launch lines read: a
    # phase that could not be read costs nothing to start)
    phases = re.search(
        r"Each of its 2 phases' start \((\d+\.\d) s here.*own \((\d+\.\d) s\)", out.stdout
    )
    assert phases and float(phases[1]) > 0
    assert not (tmp_path / "study").exists()
    # what it is doing, as it goes: on stderr, a line per variant compiled and timed
    assert "plan: compiling and timing adam (1 of 2)" in out.stderr
    assert "plan: compiling and timing gd (2 of 2)" in out.stderr
