"""Integration layer of sweeps and resuming: named sweeps' jobs valid, completed jobs skipped and
interrupted ones rerun, init_from continued or refused, seeds in one process, diverged jobs as
outcomes, the sweeper given the validation loss, and profiles stopped by Ctrl-C or timeout."""

import sys

import numpy as np
import pytest
from hydra import compose as hydra_compose

from physgrad.configs import CONF_DIR, check_overrides, initialized
from physgrad.experiment import prepare, run_experiment
from physgrad.job_spec import checked
from physgrad.optim import build_rule
from physgrad.refusals import check_applies
from physgrad.results import read_run
from physgrad.sweeps import sweep_jobs as expand_sweep
from tests.helpers import REPO, load

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))

TINY = [
    "task=poisson",
    "task.grid=4",
    "task.test_size=8",
    "trainer.batch_size=4",
    "trainer.eval_every=5",
]

sys.path.insert(0, str(REPO / "experiments"))

import reproduce  # noqa: E402


def sweep_jobs(experiment: str, extra=()):
    """Every job's config of a named sweep with extra overrides, as Hydra's basic sweeper makes them
    (a key given in extra replaces the sweeper's values for it). Jobs that differ in their seed
    alone are composed once and given each seed: a seed is a value, it selects no config (a
    composition costs about 0.2 s, and most of a sweep's jobs are its seeds)."""
    import copy

    import yaml

    composed = {}
    jobs = []
    with (
        initialized()
    ):  # one Hydra set-up for every job (composing is cheap, setting Hydra up is not)
        base = hydra_compose("config", [f"+experiment={experiment}"], return_hydra_config=True)
        params = [f"{key}={value}" for key, value in base.hydra.sweeper.params.items()]
        for job in expand_sweep([*params, *extra]):
            seeds = [o.split("=", 1)[1] for o in job if o.startswith("seed=")]
            rest = tuple(o for o in job if not o.startswith("seed="))
            if rest not in composed:
                composed[rest] = hydra_compose("config", [f"+experiment={experiment}", *rest])
            cfg = copy.deepcopy(composed[rest])
            for seed in seeds:
                cfg.seed = yaml.safe_load(seed)
            jobs.append(cfg)
        # the shortcut gives what composing gives: the last job composed as it is
        assert jobs[-1] == hydra_compose("config", [f"+experiment={experiment}", *job])
    return jobs


# (task config, unroll, precision, seed) -> the scene: the jobs of a sweep share a few of them
SCENES = {}


def valid(cfg):
    """Raises on anything a run of cfg would refuse: its settings, its rule, its scene and their
    combination."""
    spec = checked(cfg)
    build_rule(spec.optim)
    key = spec.scene_key([spec.seed])
    if key not in SCENES:
        SCENES[key] = prepare(spec, [spec.seed])[0]
    check_applies(SCENES[key], spec)


def test_every_figure_has_its_experiments():
    named = {e for figure in reproduce.FIGURES for e in figure.experiments}
    assert named == set(EXPERIMENTS)
    assert len(reproduce.FIGURES) == 10  # figure 7 is drawn from all of their runs


@pytest.mark.parametrize("experiment", EXPERIMENTS)
@pytest.mark.long
def test_every_job_of_a_named_sweep_is_valid(experiment):
    jobs = list(sweep_jobs(experiment))
    assert len(jobs) >= 6
    for cfg in jobs:
        valid(cfg)
    # every variant sees the same seeds
    seeds = {}
    for cfg in jobs:
        seeds.setdefault(str(cfg.optim.name) + str(cfg.optim.get("backprop")), set()).add(cfg.seed)
    assert len({frozenset(s) for s in seeds.values()}) == 1


@pytest.mark.long
@pytest.mark.parametrize(
    "figure", [f for f in reproduce.FIGURES if f.quick is not None], ids=lambda f: f.name
)
def test_quick_profile_overrides_are_valid(figure):
    for experiment in figure.experiments:
        overrides = figure.quick[experiment]
        check_overrides([f"+experiment={experiment}", *overrides], multirun=True)
        for cfg in sweep_jobs(experiment, [o for o in overrides if not o.startswith("init_from")]):
            valid(cfg)


def test_a_completed_job_is_skipped_unless_overwrite(tmp_path):
    first, path = run_experiment(load(*TINY, "trainer.iterations=3"), tmp_path)
    created = read_run(path).attrs["finished"]
    again, _ = run_experiment(load(*TINY, "trainer.iterations=3"), tmp_path)
    assert first.status == again.status == "completed" and "already completed" in again.reason
    assert again.final_eval["loss"] == first.final_eval["loss"]
    assert read_run(path).attrs["finished"] == created  # untouched
    rerun, _ = run_experiment(load(*TINY, "trainer.iterations=3", "overwrite=true"), tmp_path)
    assert rerun.reason is None
    # another config: run again
    changed, _ = run_experiment(load(*TINY, "trainer.iterations=4"), tmp_path)
    assert changed.reason is None and read_run(path).train["iteration"].size == 4


def test_figures_false_draws_none_and_does_not_change_which_run_it_is(tmp_path):
    """figures=false: no loss.png; the run is the same run as with figures (a re-run with them is
    skipped, and one stored by a physgrad without the key is the same run too)."""
    first, path = run_experiment(load(*TINY, "trainer.iterations=3", "figures=false"), tmp_path)
    assert first.status == "completed" and not (tmp_path / "loss.png").exists()
    again, _ = run_experiment(load(*TINY, "trainer.iterations=3"), tmp_path)
    assert "already completed" in again.reason
    import h5py

    from physgrad.results import parse_config

    with h5py.File(path, "a") as f:  # as an older physgrad stored it: no figures key
        stored = parse_config(f.attrs["config"])
        stored.pop("figures")
        import yaml

        f.attrs["config"] = yaml.safe_dump(stored)
    older, _ = run_experiment(load(*TINY, "trainer.iterations=3", "figures=false"), tmp_path)
    assert "already completed" in older.reason
    refused, _ = run_experiment(load(*TINY, "figures=maybe"), tmp_path / "bad")
    assert refused.status == "refused" and "figures" in refused.reason


def test_an_interrupted_job_is_run_again(tmp_path):
    run_experiment(load(*TINY, "trainer.iterations=3"), tmp_path)
    from physgrad.results import ResultsWriter

    config = read_run(tmp_path / "results.h5").attrs["config"]
    (tmp_path / "results.h5").unlink()  # (a completed file is never replaced by an interrupted one)
    ResultsWriter(
        tmp_path / "results.h5", {"task": "toy", "optim": "adam", "seed": 0, "config": config}
    ).finish("interrupted", "SIGINT after 1 iterations")
    outcome, path = run_experiment(load(*TINY, "trainer.iterations=3"), tmp_path)
    assert outcome.reason is None and read_run(path).attrs["status"] == "completed"


def test_init_from_continues_from_the_saved_network(tmp_path):
    _, source = run_experiment(load(*TINY, "trainer.iterations=6"), tmp_path / "adam")
    outcome, path = run_experiment(
        load(*TINY, "optim=gd", "trainer.iterations=2", f"init_from={source}"), tmp_path / "gd"
    )
    first, second = read_run(source), read_run(path)
    assert outcome.status == "completed"
    # same seed, same test set: the continued run's first evaluation is the source's last
    assert second.eval["loss"][0] == first.eval["loss"][-1]
    assert second.variant == "gd (from adam)" and second.offset("iteration") == 6
    assert second.offset("wall_time") == pytest.approx(first.final("train", "wall_time"))


# make test-long: a further check of init_from's source (its status), as the wrong runs below; make
# test keeps test_init_from_continues_from_the_saved_network and the refusal of the job's own file
@pytest.mark.long
def test_init_from_a_run_that_did_not_complete_says_so(tmp_path, caplog):
    """A network from an interrupted (or diverged) run may be gone on from, with one warning that
    names its status; a completed one gives none."""
    import h5py

    _, source = run_experiment(load(*TINY, "trainer.iterations=4"), tmp_path / "adam")
    cfg = load(*TINY, "optim=gd", "trainer.iterations=2", f"init_from={source}")
    with caplog.at_level("WARNING", logger="physgrad"):
        run_experiment(cfg, tmp_path / "after_completed")
    assert not [r for r in caplog.records if "init_from" in r.getMessage()]
    with h5py.File(source, "r+") as f:
        f.attrs["status"] = "interrupted"
    with caplog.at_level("WARNING", logger="physgrad"):
        outcome, _ = run_experiment(cfg, tmp_path / "after_interrupted")
    warned = [r.getMessage() for r in caplog.records if "init_from" in r.getMessage()]
    assert outcome.status == "completed" and len(warned) == 1 and "ended interrupted" in warned[0]


@pytest.mark.parametrize(
    "source, fragment",
    [
        ("missing.h5", "no such file"),
        ("other", "that run trained a poisson network with"),
    ],
)
@pytest.mark.long
def test_init_from_a_wrong_run_is_refused(tmp_path, source, fragment):
    if source == "other":
        _, path = run_experiment(
            load(*TINY, "task.grid=3", "trainer.iterations=1"), tmp_path / "other"
        )
        source = str(path)
    outcome, _ = run_experiment(load(*TINY, f"init_from={tmp_path / source}"), tmp_path / "run")
    assert outcome.status == "refused" and fragment in outcome.reason and "\n" not in outcome.reason


# make test-long: the refusal with overwrite=true; make test keeps it without ([False])
@pytest.mark.parametrize("overwrite", [False, pytest.param(True, marks=pytest.mark.long)])
def test_init_from_the_job_s_own_results_file_is_refused_and_leaves_it_intact(tmp_path, overwrite):
    _, source = run_experiment(load(*TINY, "trainer.iterations=3"), tmp_path / "run")
    before = source.read_bytes()
    outcome, _ = run_experiment(
        load(
            *TINY,
            "optim=gd",
            "trainer.iterations=2",
            f"init_from={source}",
            f"overwrite={overwrite}",
        ),
        tmp_path / "run",
    )
    assert outcome.status == "refused" and "is this job's own results file" in outcome.reason
    assert source.read_bytes() == before and read_run(source).attrs["status"] == "completed"


def test_params_are_saved_unless_the_run_diverged(tmp_path):
    from physgrad.results import read_params

    _, path = run_experiment(load(*TINY, "trainer.iterations=2"), tmp_path / "ok")
    assert (
        np.isfinite(read_params(path)).all()
        and read_params(path).size == read_run(path).attrs["n_params"]
    )
    _, diverged = run_experiment(
        load(*TINY, "optim=gd", "optim.learning_rate=1e30", "trainer.iterations=50"),
        tmp_path / "bad",
    )
    assert read_run(diverged).attrs["status"] == "diverged"
    with pytest.raises(ValueError, match="holds no final network"):
        read_params(diverged)
    # a diverged run is a result: a second call skips it, as it skips a completed one
    written = read_run(diverged).attrs["finished"]
    again, _ = run_experiment(
        load(*TINY, "optim=gd", "optim.learning_rate=1e30", "trainer.iterations=50"),
        tmp_path / "bad",
    )
    assert again.status == "diverged" and again.reason.startswith(
        "already diverged (update became inf"
    )
    assert read_run(diverged).attrs["finished"] == written


@pytest.mark.parametrize(
    "task",
    [
        ["task=poisson", "task.grid=4", "task.test_size=8", "trainer.batch_size=4"],
        [
            "task=multicart",
            "task.train_size=16",
            "task.test_size=8",
            "unroll=20",
            "optim=stable_bptt",
        ],
    ],
    ids=["fresh batches", "fixed training set"],
)
@pytest.mark.long
def test_seeds_in_one_process_match_separate_runs(tmp_path, task):
    """seeds=3 trains seeds 0, 1, 2 in one vmapped step; every seed's file has the curves of its own
    run."""
    common = [*task, "precision=64", "trainer.iterations=6", "trainer.eval_every=3"]
    # figures on: each seed of a run trained together gets its own
    outcome, folder = run_experiment(
        load(*common, "seeds=3", "figures=true"), tmp_path / "together"
    )
    assert outcome.status == "completed"
    for seed in range(3):
        together = read_run(folder / f"seed={seed}" / "results.h5")
        _, path = run_experiment(load(*common, f"seed={seed}"), tmp_path / f"alone{seed}")
        alone = read_run(path)
        assert together.attrs["seed"] == seed and together.attrs["wall_time_shared_by"] == 3
        for group in ("train", "eval"):
            for column in ("iteration", "loss"):
                np.testing.assert_allclose(
                    getattr(together, group)[column],
                    getattr(alone, group)[column],
                    rtol=1e-9,
                    atol=1e-12,
                )
    assert (folder / "seed=1" / "loss.png").exists()


def test_a_diverging_seed_leaves_the_others_running(tmp_path):
    # GD at lr 1e-3 on the closed-loop oscillator with batches of 16 blows up from seed 0's initial
    # network only
    outcome, folder = run_experiment(
        load(
            "task=oscillator",
            "task.closed_loop=true",
            "optim=gd",
            "task.train_size=64",
            "task.test_size=8",
            "trainer.batch_size=16",
            "trainer.iterations=4",
            "seeds=3",
        ),
        tmp_path,
    )
    runs = [read_run(folder / f"seed={seed}" / "results.h5") for seed in range(3)]
    assert [run.attrs["status"] for run in runs] == ["diverged", "completed", "completed"]
    assert (
        outcome.status == "diverged"
        and "seed #0: output became nan at iteration 1" in outcome.reason
    )
    assert runs[0].train["iteration"].tolist() == [0, 1] and runs[1].train[
        "iteration"
    ].tolist() == [0, 1, 2, 3]
    assert runs[1].eval["iteration"].tolist() == [0, 4]
    # what stopped the run is recorded for the seeds that ran to the end only
    assert (
        "stopped_by" not in runs[0].attrs
        and runs[1].attrs["stopped_by"] == runs[2].attrs["stopped_by"] == "iterations"
    )


def test_diverged_and_refused_jobs_are_outcomes_not_failures(tmp_path):
    from physgrad.cli import main

    assert (
        main(
            [
                "run",
                "-m",
                "optim=gd,bptt",
                "optim.learning_rate=1e30",
                "trainer.iterations=30",
                *TINY[1:],
                f"hydra.sweep.dir={tmp_path}",
            ]
        )
        == 0
    )
    assert sorted(read_run(p).attrs["status"] for p in tmp_path.rglob("results.h5")) == [
        "diverged",
        "refused",
    ]


def test_the_job_returns_its_validation_loss_to_the_sweeper_never_the_test_loss():
    from physgrad.app import objective
    from physgrad.runner import Outcome

    assert (
        objective(Outcome("completed", None, 10, 1.0, {"loss": 0.25, "validation_loss": 0.5}))
        == 0.5
    )
    # no validation data
    assert objective(Outcome("completed", None, 10, 1.0, {"loss": 0.25})) == float("inf")
    for status in ("diverged", "refused", "failed"):
        assert objective(
            Outcome(status, "why", 10, 1.0, {"loss": 0.25, "validation_loss": 0.5})
        ) == float("inf")


def test_every_seed_of_a_job_is_logged(tmp_path):
    from physgrad.app import seed_lines

    run_experiment(load(*TINY, "trainer.iterations=2", "seeds=3"), tmp_path)
    lines = seed_lines(tmp_path)
    assert [line.split(":")[0].strip() for line in lines] == ["seed 0", "seed 1", "seed 2"]
    assert all("completed, test loss " in line for line in lines)


def _profile_and_child(tmp_path) -> str:
    """A profile's code (run_child, then the one line) around a child that takes 0.8 s to leave
    its files resumable after SIGINT: the parent's Python source."""
    child = tmp_path / "child.py"
    child.write_text(
        "import pathlib, signal, sys, time\n"
        "def leave(*_):\n"
        "    time.sleep(0.8)  # writing its resumable state\n"
        f"    pathlib.Path({str(tmp_path / 'left')!r}).write_text('resumable')\n"
        "    sys.exit(130)\n"
        "signal.signal(signal.SIGINT, leave)\n"
        f"pathlib.Path({str(tmp_path / 'started')!r}).touch()\n"
        "time.sleep(60)\n"
    )
    return (
        f"import sys; sys.path.insert(0, {str(REPO / 'experiments')!r})\n"
        "from study_profiles import INTERRUPTED, run_child\n"
        f"code = run_child([sys.executable, {str(child)!r}])\n"
        "if code == 130: print(INTERRUPTED, file=sys.stderr)\n"
        "sys.exit(code)\n"
    )


INTERRUPTED_LINE = ["reproduce: interrupted; the same command resumes where it stopped"]


# one instant in make test, the others with the faults at many instants in make test-long
@pytest.mark.parametrize(
    "instant",
    [pytest.param(0.3, marks=pytest.mark.long), 0.6, pytest.param(1.2, marks=pytest.mark.long)],
)
def test_ctrl_c_lets_a_profile_s_child_leave_its_files_then_ends_in_one_line(tmp_path, instant):
    """Ctrl-C reaches the profile's process group: the child (a study, a sweep) takes a while to
    leave its files resumable, and the profile waits for it (subprocess.run would kill it after a
    quarter of a second), then says in one line how to resume, exit 130."""
    import os
    import signal
    import subprocess
    import sys
    import time

    parent = _profile_and_child(tmp_path)
    profile = subprocess.Popen(
        [sys.executable, "-c", parent], start_new_session=True, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 30
    while not (tmp_path / "started").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(instant)
    os.killpg(profile.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole group
    _, stderr = profile.communicate(timeout=30)
    assert profile.returncode == 130 and (tmp_path / "left").read_text() == "resumable"
    assert stderr.strip().splitlines() == INTERRUPTED_LINE


@pytest.mark.long
def test_a_time_box_of_coreutils_timeout_stops_a_profile_as_ctrl_c_does(tmp_path):
    """`timeout -s INT <limit> <profile>` (docs/evidence/leaderboard/README.md: a part in slices
    on a machine lent for minutes) signals its whole process group, as Ctrl-C does: the child
    leaves its files resumable and the profile ends in its one line; timeout says 124."""
    import subprocess
    import sys

    limit = 3  # the child has its handler well before: it starts in about 0.1 s
    ended = subprocess.run(
        ["timeout", "-s", "INT", str(limit), sys.executable, "-c", _profile_and_child(tmp_path)],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert ended.returncode == 124 and (tmp_path / "left").read_text() == "resumable"
    assert ended.stderr.strip().splitlines() == INTERRUPTED_LINE
