"""Unit layer of `physgrad compare`: bad studies refused in one line, a job file composing to its
variant and trial, validation defaults, tuning journals cut short, planted or scored by another
read-out, planted stop marks and logs, the phases' progress and time left, and --help."""

import pytest

from physgrad.comparison import (
    build_variants,
    evaluation_jobs,
    job_yaml,
    split_overrides,
    study_settings,
)
from physgrad.configs import compose
from physgrad.errors import UserError
from tests.helpers import plant


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["task=toy", "optim=adam"], "list two or more variants"),
        (["task=toy", "optim=adam,hig", "compare.trails=3"], "unknown setting compare.trails"),
        (["task=toy", "optim=adam,hig", "compare.tune_seed=3"], "must differ"),
        (["task=toy", "optim.learning_rate=interval(0.1,1)"], "list the variants"),
        (["task=toy", "optim=adam,hig", "compare.search.tau=[1,0.1]"], "0 < low < high"),
        # an infinite end had been accepted, then every tuning job refused, for ever
        (["task=toy", "optim=adam,hig", "compare.search.learning_rate=[1e-3,inf]"], "finite"),
        (["task=toy", "optim=adam,hig", "compare.search.tau=[nan,1]"], "finite"),
        (["task=toy", "optim=adam,hgi"], "did you mean hig?"),
        (["task=toy", "optim=adam,hig", "compare.baseline=sgd"], "not one of the variants"),
        (["task=toy", "optim=adam,hig", "compare.seeds=0"], "compare.seeds"),
        (["task=toy", "optim=adam,hig", "seed=3"], "compare sets the seeds itself"),
        (["task=toy", "optim=adam,hig", "compare.seeds=2000"], "compare.seeds"),
        (["task=toy", "optim=adam,hig", "hydra.sweep.dir=x"], "give compare.dir=DIR instead"),
        (["task=toy", "optim=adam,hig", "compare.dir=a,b"], "takes one value"),
        # resolved in the jobs to another folder: the study would wait for runs that went elsewhere
        (["task=toy", "optim=adam,hig", "compare.dir=/tmp/s${oc.env:HOME}"], "interpolation"),
        (["task=toy", "optim=adam,hig", "hydra.run.dir=x"], "give compare.dir=DIR instead"),
        # tuning seeds 2, 3, 4 of three studies reach the evaluation seeds 3 ..
        (["task=toy", "optim=adam,hig", "compare.tune_seed=2", "compare.seed=3"], "must differ"),
    ],
)
def test_bad_studies_are_one_line_errors(args, fragment):
    with pytest.raises(UserError, match=fragment.replace("?", r"\?").replace("[", r"\[")):
        settings, axes, common, _ = split_overrides(args)
        build_variants(axes, common, study_settings(settings), [])


def test_a_job_file_composes_to_the_variant_with_its_trial_settings(tmp_path):
    """The trial's learning rate wins over the scene's preset (tuning/oscillator_hig.yaml: lr 1),
    which keeps its batch size; common and variant overrides land as given."""
    folder = tmp_path / "compare_job"
    folder.mkdir()
    groups = {"task", "optim", "tuning"}
    text = job_yaml(
        ["task=oscillator", "trainer.iterations=50", "optim=hig", "optim.clip=norm"],
        groups,
        {"optim.learning_rate": 0.3, "seed": 1_000_000, "trainer.validation": True},
    )
    (folder / "tune_v0_t000.yaml").write_text(text)
    cfg = compose(["+compare_job=tune_v0_t000"], config_dirs=[str(tmp_path)])
    assert (cfg.task.name, cfg.optim.name, cfg.optim.clip) == ("oscillator", "hig", "norm")
    assert cfg.optim.learning_rate == 0.3 and cfg.task.batch_size == 128 and cfg.optim.tau == 1e-6
    assert (cfg.seed, cfg.trainer.iterations, cfg.trainer.validation) == (1_000_000, 50, True)


def test_a_scene_whose_data_ignore_the_key_has_no_default_validation_set():
    import jax

    from physgrad.experiment import validation_set
    from physgrad.job_spec import checked
    from physgrad.tasks import Scene

    def build(**_):
        return Scene(
            init_params=lambda k: {"w": jax.numpy.zeros(2)},
            sample_loss=lambda y, s: (y**2).sum(),
            test_set={"x": jax.numpy.ones((4, 2))},
            train_set={"x": jax.numpy.ones((4, 2))},
            sample_output=lambda p, s: p["w"] * s["x"],
        )

    cfg = compose(["task=toy"])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("physgrad.experiment.build_scene", lambda *a, **k: build())
        with pytest.raises(UserError, match="give its Scene a validation_set"):
            validation_set(checked(cfg), build(), jax.random.PRNGKey(0))


def test_continuing_networks_evaluates_one_job_per_seed():
    settings, axes, common, _ = split_overrides(
        [
            "task=toy",
            "optim=adam,gd",
            "trainer.iterations=30",
            "init_from='start/seed=${seed}/results.h5'",
        ]
    )
    s = study_settings({**settings, "seeds": 3})
    variants = build_variants(axes, common, s, [])
    jobs = evaluation_jobs(
        variants, [{v.name: {} for v in variants}], s, common, {"task", "optim"}, "iteration", 30.0
    )
    assert list(jobs) == [f"eval_v{v}_s{seed}" for v in (0, 1) for seed in range(3)]
    assert "seed=${seed}" in jobs["eval_v0_s2"] and "seeds: 1" in jobs["eval_v0_s2"]


def test_a_tuning_journal_cut_short_is_repaired_and_a_foreign_one_refused(tmp_path):
    """The last line cut short (a kill during an append): moved aside with a one-line note, and
    Optuna reads the rest, the trial it would have told still waiting; a line that is no record in
    the middle: one line."""
    import optuna

    from physgrad.comparison.journal import set_aside_damage

    path = tmp_path / "tuning.journal"
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(path)))
    study = optuna.create_study(study_name="adam", storage=storage)
    for value in (0.1, 0.2):
        trial = study.ask({"learning_rate": optuna.distributions.FloatDistribution(1e-5, 1)})
        study.tell(trial, value)
    whole = path.read_bytes()
    for cut in (5, len(whole.splitlines()[-1]) // 2):
        path.write_bytes(whole[:-cut])
        notes = []
        set_aside_damage(path, notes.append)
        assert len(notes) == 1 and "cut short" in notes[0]
        reread = optuna.load_study(
            study_name="adam",
            storage=optuna.storages.JournalStorage(
                optuna.storages.journal.JournalFileBackend(str(path))
            ),
        )
        assert [t.value for t in reread.trials][0] == 0.1
        assert len(list(tmp_path.glob("tuning.journal.damaged-*"))) >= 1
    path.write_bytes(whole)
    notes = []
    set_aside_damage(path, notes.append)  # a whole journal is left alone
    assert notes == [] and path.read_bytes() == whole
    lines = whole.split(b"\n")
    path.write_bytes(b"\n".join([lines[0], b"\x00\xffgarbage", *lines[1:]]))
    with pytest.raises(UserError, match="line 2 is not a record of Optuna's journal"):
        set_aside_damage(path, notes.append)
    # a JSON record with an op code Optuna does not know (its replay failed in a 42-line
    # AssertionError): one line, both where the damage is looked for and where the journal is read
    path.write_bytes(b"\n".join([lines[0], b'{"op_code": 99, "worker_id": "x"}', *lines[1:]]))
    with pytest.raises(UserError, match="line 2 is not a record of Optuna's journal"):
        set_aside_damage(path, notes.append)
    from physgrad.comparison.journal import OwnJournal

    with pytest.raises(ValueError, match="line 2 is not a record of Optuna's journal"):
        list(OwnJournal(path).read_logs(0))


@pytest.mark.parametrize("planted", ["link", "fifo", "folder", "deep"])
def test_a_planted_tuning_journal_is_refused_in_one_line_never_followed_or_waited_on(
    tmp_path, planted
):
    """A study folder from someone else with a link (to a file elsewhere), a FIFO or a folder at
    tuning.journal, or a record nested 200,000 deep: one line, nothing read through the link, no
    wait on the FIFO, no RecursionError."""
    import signal

    from physgrad.comparison.journal import set_aside_damage

    path, elsewhere = tmp_path / "tuning.journal", tmp_path / "elsewhere"
    elsewhere.write_text('{"op_code": 0}\nsecret, cut')
    if planted == "deep":
        path.write_text('{"op_code": 0}\n' + "[" * 200_000 + "\n{}\n")
    else:
        plant(path, planted, elsewhere)
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("waited on a FIFO"))
    signal.alarm(20)
    try:
        with pytest.raises(UserError) as refused:
            set_aside_damage(path, print)
    finally:
        signal.alarm(0)
    assert "\n" not in str(refused.value) and "tuning.journal" in str(refused.value)
    assert not list(tmp_path.glob("*.damaged-*"))  # nothing of elsewhere copied in


def test_a_planted_stop_mark_or_log_is_data_never_followed_or_waited_on(tmp_path):
    """A sweep's stop mark and a phase's log read from a folder someone else may have written: a
    FIFO or a link there reads as no mark and no error line, at once."""
    import signal

    from physgrad.comparison.jobs import _last_error
    from physgrad.sweeps import STOP_MARK, mark_stopped, stop_count

    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_text("SIGTERM 3\nphysgrad: error: not yours\n")
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("waited on a FIFO"))
    signal.alarm(20)
    try:
        for kind in ("link", "fifo"):
            sweep = tmp_path / kind
            sweep.mkdir()
            for path in (sweep / STOP_MARK, sweep / "tune.log"):
                plant(path, kind, elsewhere)
            assert stop_count(sweep) is None and _last_error(sweep / "tune.log") is None
    finally:
        signal.alarm(0)
    own = tmp_path / "own"
    own.mkdir()
    mark_stopped(own, "SIGTERM", 2)
    assert stop_count(own) == ("SIGTERM", 2)
    (own / "tune.log").write_text("x" * 100_000 + "\n$ run\nphysgrad: error: the last one\n")
    assert _last_error(own / "tune.log") == "the last one"


def _journal(path, studies):
    """A tuning journal by hand: {study name: (readout attr or None, told values, asked only)}."""
    import optuna

    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(path)))
    rate = {"learning_rate": optuna.distributions.FloatDistribution(1e-5, 1, log=True)}
    for name, (version, told, asked) in studies.items():
        study = optuna.create_study(study_name=name, storage=storage)
        if version is not None:
            study.set_user_attr("readout", version)
        for value in told:
            study.tell(study.ask(rate), value)
        for _ in range(asked):
            study.ask(rate)


@pytest.mark.parametrize(
    "studies, stale",
    [
        ({"adam": (None, [0.1], 0)}, "unrecorded"),
        ({"adam": (1, [0.1, 0.2], 0), "gd": (None, [], 2)}, "1"),
        ({"adam": (2, [0.1], 0), "gd": (1, [0.3], 1), "hig": (None, [0.2], 0)}, "1-unrecorded"),
        ({"adam": (2, [0.1], 1), "gd": (None, [], 1)}, None),
        # a version with a terminal escape and a path: safe characters in the name and the note
        ({"adam": ("\x1b]0;x\x07/../y", [0.1], 0)}, "__0_x__.._y"),
    ],
)
def test_a_tuning_journal_scored_by_another_read_out_is_set_aside(tmp_path, studies, stale):
    """A study with a told trial and another read-out's version (or none: before it was recorded)
    sends the whole journal aside under a name that says which, with a one-line note; trials only
    asked, or told under this version, keep it."""
    from physgrad.comparison.journal import set_aside_stale
    from physgrad.readout import READOUT_VERSION

    path = tmp_path / "tuning.journal"
    _journal(path, studies)
    whole = path.read_bytes()
    notes = []
    set_aside_stale(path, notes.append)
    if stale is None:
        assert notes == [] and path.read_bytes() == whole
        return
    assert not path.exists() and len(notes) == 1
    (aside,) = tmp_path.glob(f"tuning.journal.read-out-{stale}-*")
    assert aside.read_bytes() == whole
    assert f"version {stale}" in notes[0] and f"version {READOUT_VERSION}" in notes[0]
    set_aside_stale(path, notes.append)  # nothing left to set aside
    assert len(notes) == 1


def test_on_a_terminal_a_phase_draws_a_bar_of_its_jobs_and_ends_with_one_line():
    """A terminal gets a bar over the phase's jobs (done of total, the running job and its loss,
    the time left) instead of lines along the way; the end is the same one line as in a log."""
    import io

    import physgrad.comparison.progress as console

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    terminal, said = Terminal(), []
    progress = console.Progress("tune", 6, said.append, every=0, stream=terminal)
    assert progress.bar is not None
    for k in range(4):
        progress.read(
            f"[HYDRA] \t#{k} : +compare_job=tune_v{k}\n"
            f"[physgrad][INFO] - toy/hig seed 1000000 (+1) iteration {10 * k}, loss {k}.5, 1.0 s "
            "of training\n"
        )
    drawn = terminal.getvalue().split("\r")[-1]
    assert "tune: 3/6 jobs done" in drawn, drawn
    assert "job 4: toy/hig seed 1000000 (+1): loss 3.5 at iteration 30" in drawn, drawn
    assert " left" in drawn and said == []  # no lines along the way on a terminal
    progress.read("", final=True)
    assert len(said) == 1 and said[0].startswith("tune: 4 of 6 jobs run in ")
    # without a terminal: no bar
    assert console.Progress("tune", 6, said.append, stream=io.StringIO()).bar is None


def test_a_stopped_phase_says_the_jobs_it_ran_not_the_ones_its_launcher_skipped():
    """A sweep stopped by a signal still logs a launch line for each job left (each then "never
    started"), and names the running one "interrupted": the last line counts neither as run."""
    import io

    import physgrad.comparison.progress as console

    said = []
    progress = console.Progress("tune", 6, said.append, stream=io.StringIO())
    log = "".join(f"[HYDRA] \t#{k} : +compare_job=tune_v{k}\n" for k in range(6))
    log += "[HYDRA] job +compare_job=tune_v3: interrupted: seed #0: SIGINT after 9 iterations\n"
    log += "".join(f"[HYDRA] job +compare_job=tune_v{k}: never started\n" for k in (4, 5))
    progress.read(log, final=True)
    assert said[-1].startswith("tune: 3 of 6 jobs run in ")
    assert said[-1].endswith(" min, then stopped (1 interrupted, 2 never started)")


def test_the_time_left_counts_each_job_at_its_variants_pace(monkeypatch):
    """The time left counts each job not done at the mean time of the done jobs of its variant (a
    job of a variant with none done is not counted but said, the time "at least"), less what the
    running one has had; a running
    job slower than that says the time after it and how long it has run (and what its variant's
    done jobs took, where it has any), instead of "about 0 s left" for as long as it runs; nothing
    before a job is done or once all are."""
    import io

    import physgrad.comparison.progress as console

    clock = [1000.0]
    monkeypatch.setattr(console.time, "monotonic", lambda: clock[0])
    # two tuning studies of a fast variant (v0) and a slow one (v1), in launch order
    names = ("tune_st0_v0_t000-007", "tune_st0_v1_t000-007", "tune_st1_v0_t000-007",
             "tune_st1_v1_t000-007")  # fmt: skip
    progress = console.Progress("tune", 4, [].append, names=names, stream=io.StringIO())
    progress.begun = 1000.0

    def launch(job, at):
        clock[0] = 1000.0 + at
        progress.read(f"[HYDRA] \t#{job} : +compare_job={names[job]}\n")

    launch(0, 0)
    assert progress._left(1010.0) == ""  # no job done: no pace yet
    launch(1, 60)  # v0's job took a minute
    # v1's running job and v1's later one have no pace yet (v0's is not theirs): at least v0's
    assert progress._left(1090.0) == (
        "; at least 60 s left after the running job (30 s so far, the first of its variant), and "
        "1 job of a variant not timed yet"
    )
    assert progress._left(1300.0).startswith("; at least 60 s left after the running job (4.0 min")
    # only jobs with no pace after the running one: no "at least 0 s left"
    alone = console.Progress(
        "tune", 3, [].append, names=names[:2] + names[1:2], stream=io.StringIO()
    )
    alone.started, alone.launched_at, alone.took = 2, 1060.0, {0: [60.0]}
    assert alone._left(1090.0) == (
        "; the running job 30 s so far (the first of its variant), and 1 job of a variant not "
        "timed yet"
    )
    launch(2, 660)  # v1's job took ten minutes
    # v0's running job at 60 s, v1's last at 600 s
    assert progress._left(1680.0) == "; about 10.7 min left"
    launch(3, 720)
    assert progress._left(1780.0) == "; about 9.0 min left"
    # v1's last job, slower than v1's first: the time v1's done job took is what was expected
    assert progress._left(2400.0) == (
        "; about 0 s left after the running job (11.3 min so far, about 10.0 min expected)"
    )
    progress.read("", final=True)
    progress.started = 5  # every job done: nothing left to tell
    assert progress._left(2000.0) == ""
    # without names every job is of one kind: the mean of the jobs done
    plain = console.Progress("eval", 3, [].append, stream=io.StringIO())
    plain.started, plain.launched_at, plain.begun = 2, 120.0, 0.0
    plain.took = {None: [120.0]}  # as reading the first job's launch after it leaves it
    assert plain._left(150.0) == "; about 3.5 min left"


def test_a_phase_says_its_progress_from_its_log_without_a_line_per_job(tmp_path, monkeypatch):
    """The console hears where a phase is (Hydra's launch lines in its log): lines along the way at
    most one per interval, and one at the end with the jobs run; nothing for a phase that never
    launched a job."""
    import sys

    import physgrad.comparison.jobs as jobs
    import physgrad.comparison.progress as console

    monkeypatch.setattr(jobs, "POLL_SECONDS", 0.1)
    script = (
        "import time\n"
        "for k in range(6):\n"
        "    print(f'[2026-01-01][HYDRA] \\t#{k} : +compare_job=tune_v{k}', flush=True)\n"
        "    print(f'[2026-01-01][physgrad][INFO] - toy/hig seed 1000000 (+1) '\n"
        "          f'iteration {10 * k}, loss {k}.5, 1.0 s of training', flush=True)\n"
        "    time.sleep(0.2)\n"
    )

    def phase(every):
        said = []
        log = tmp_path / f"tune-{every}.log"
        progress = console.Progress("tune", 6, said.append, every=every)
        assert jobs._run_multirun([sys.executable, "-c", script], log, {}, progress) == 0
        assert log.read_text().count("\t#") == 6  # the log keeps the output whole
        return said

    # an interval longer than the phase: the end only
    said = phase(every=600)
    assert len(said) == 1 and said[0].startswith("tune: 6 of 6 jobs run in ")
    # no interval: every look that found more jobs started or a job's loss moved, in order, then
    # the end
    said = phase(every=0)
    along = said[:-1]
    assert along and all(line.startswith("tune: job ") for line in along), said
    numbers = [int(line.split()[2]) for line in along]
    assert numbers == sorted(numbers) and numbers[-1] <= 6
    # the running job's loss so far, and from the second job on the time left at the jobs' pace
    for line, k in zip(along, numbers):
        assert f"; toy/hig seed 1000000 (+1): loss {k - 1}.5 at iteration {10 * (k - 1)}" in line
        assert (" left" in line) == (k > 1), line
    assert said[-1].startswith("tune: 6 of 6 jobs run in ")
    quiet = []
    log = tmp_path / "q.log"
    jobs._run_multirun(
        [sys.executable, "-c", "pass"], log, {}, console.Progress("eval", 3, quiet.append)
    )
    assert quiet == []


def test_compare_help_is_wrapped_by_words_and_states_the_protocol_as_the_code_applies_it(capsys):
    """`physgrad compare --help`: every line within 100 columns (wrapped between words, not
    mid-word by the terminal), every setting named, and the majority rule of the studies as the
    verdicts apply it (more than half, none against)."""
    from physgrad.comparison.spec import SETTINGS
    from physgrad.comparison.study import main

    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert all(len(line) <= 100 for line in text.splitlines()), max(text.splitlines(), key=len)
    for key in SETTINGS:
        assert f"  compare.{key} " in text
    assert (
        "each holding where 3 of 4 studies (more\n   than half) reach it with none against" in text
    )


def test_a_whole_number_setting_is_searched_over_whole_numbers_of_its_range():
    """A key whose preset is a whole number (here SOAP's preconditioning frequency, given a range on
    the command line) is searched over the whole numbers inside its range: every shifted Halton
    point an int in it, log-uniformly spread (the points below the range's geometric middle about
    half), the learning rate still a float; a trial's value that is no whole number is set aside;
    a range without a whole number from 1 up is refused in one line."""
    import math
    import types

    from physgrad.comparison.points import halton_points, is_whole
    from physgrad.comparison.search_space import search_space
    from physgrad.comparison.tuning import trial_params

    cfg = compose(["task=toy", "optim=soap"])
    space = search_space(cfg, {"precondition_frequency": (1.5, 64.7)})
    assert space["precondition_frequency"] == (2, 64) and is_whole((2, 64))
    assert not is_whole(space["learning_rate"])
    points = [p for seed in range(4) for p in halton_points(space, 16, seed)]
    counts = [p["precondition_frequency"] for p in points]
    assert all(isinstance(c, int) and 2 <= c <= 64 for c in counts)
    assert all(isinstance(p["learning_rate"], float) for p in points)
    below = sum(c < math.sqrt(2 * 64) for c in counts) / len(counts)
    assert 0.35 < below < 0.65, below  # log-uniform, not uniform (that would put 1/10 below 11)
    trial = types.SimpleNamespace(params={"learning_rate": 1e-3, "precondition_frequency": 7.0})
    assert trial_params(trial, space) == {"learning_rate": 1e-3, "precondition_frequency": 7}
    trial.params["precondition_frequency"] = 7.5
    assert trial_params(trial, space) is None
    with pytest.raises(UserError, match="precondition_frequency is a whole number .* widen it"):
        search_space(cfg, {"precondition_frequency": (0.2, 0.9)})


def test_another_studys_tuned_settings_are_read_as_data_by_tunings_own_rule(tmp_path):
    """compare.tuned_in: per tuning study and variant the trial with the lowest finite validation
    loss among the COMPLETE ones (the first where two tie; a NaN, an infinite or a FAIL trial never
    chosen), a count read back as a whole number, {} where every trial diverged; a missing file,
    variant or tuning study, a value outside the space or a fraction for a count refused in one
    line each; compare.tune=false with it refused."""
    from physgrad.comparison.spec import Variant, study_settings
    from physgrad.comparison.tuned_in import tuned_in
    from physgrad.errors import UserError

    adam = Variant("adam", [], None, {"learning_rate": (1e-5, 0.1)})
    soap = Variant(
        "soap", [], None, {"learning_rate": (1e-5, 0.1), "precondition_frequency": (1, 100)}
    )
    rows = [
        "variant,study,trial,learning_rate,precondition_frequency,validation_loss,state",
        "adam,0,0,0.001,,0.5,COMPLETE",
        "adam,0,1,0.01,,0.2,COMPLETE",
        "adam,0,2,0.02,,0.2,COMPLETE",  # ties with trial 1: the first is chosen
        "adam,0,3,0.05,,nan,COMPLETE",
        "adam,0,4,0.06,,0.01,FAIL",
        "adam,1,0,0.003,,inf,COMPLETE",
        "adam,1,1,0.004,,0.7,COMPLETE",
        "soap,0,0,0.001,6.0,0.3,COMPLETE",
        "soap,0,1,0.002,40.0,0.1,COMPLETE",
        "soap,1,0,0.001,6.0,inf,COMPLETE",
        "soap,1,1,0.002,40.0,nan,COMPLETE",
    ]
    (tmp_path / "trials.csv").write_text("\n".join(rows) + "\n")
    best = tuned_in(tmp_path, [adam, soap], 2)
    assert best == [
        {
            "adam": {"learning_rate": 0.01},
            "soap": {"learning_rate": 0.002, "precondition_frequency": 40},
        },
        {"adam": {"learning_rate": 0.004}, "soap": {}},  # every trial of soap diverged
    ]
    assert isinstance(best[0]["soap"]["precondition_frequency"], int)
    for wrong, said in (
        (rows[:1] + rows[1:7], "no trial of soap in tuning study 0"),
        ([r.replace("0.002,40.0", "0.5,40.0") for r in rows], "learning_rate='0.5' is not inside"),
        ([r.replace("40.0", "40.5") for r in rows], "precondition_frequency='40.5' is not inside"),
    ):
        (tmp_path / "trials.csv").write_text("\n".join(wrong) + "\n")
        with pytest.raises(UserError, match=said) as error:
            tuned_in(tmp_path, [adam, soap], 2)
        assert "\n" not in str(error.value)
    with pytest.raises(UserError, match="no trial of adam in tuning study 2"):
        (tmp_path / "trials.csv").write_text("\n".join(rows) + "\n")
        tuned_in(tmp_path, [adam, soap], 3)
    with pytest.raises(UserError, match="no finished study's trials.csv there"):
        tuned_in(tmp_path / "nowhere", [adam], 1)
    with pytest.raises(UserError, match="leave compare.tune=false out"):
        study_settings({"tuned_in": str(tmp_path), "tune": False})


def test_a_compares_report_names_each_run_as_the_study_names_its_variant():
    """study_variant: the variant of the evaluation job whose folder holds the run (eval_v<i>,
    eval_st<k>_v<i>, with or without a seed), the file's own name for a run outside the study's
    evaluation jobs or of an index the study does not have."""
    import types

    from physgrad.comparison.study import study_variant

    names = ["adam scale=1", "hig scale=1", "hig scale=0.01"]
    for path, expected in (
        ("s/eval/+compare_job=eval_v1/seed=3/results.h5", "hig scale=1"),
        ("s/eval/+compare_job=eval_st2_v2_s13/results.h5", "hig scale=0.01"),
        ("s/eval/+compare_job=eval_v0_s0/results.h5", "adam scale=1"),
        ("s/eval/+compare_job=eval_v7/results.h5", "hig"),
        ("elsewhere/run/results.h5", "hig"),
        ("s/tune/+compare_job=tune_v1_t000/results.h5", "hig"),
    ):
        run = types.SimpleNamespace(path=path, variant="hig")
        assert study_variant(run, names) == expected, path
