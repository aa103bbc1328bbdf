"""Unit layer of the command line: mistakes refused before anything runs, one line each, through
physgrad.cli.main called in-process (their rendering by the console script:
tests/e2e/test_cli.py)."""

import pytest

from physgrad.cli import main


@pytest.mark.parametrize(
    "override, fragment",
    [
        (
            "+trainer.iteratons=5",
            "unknown key 'trainer.iteratons': did you mean trainer.iterations?",
        ),
        ("++trainer.iteratons=5", "did you mean trainer.iterations?"),
        ("+foo=1", "unknown key 'foo' (the top level has: "),
        ("init_from=a/optim=adam,seed=0/results.h5", "must be quoted, e.g. init_from='"),
    ],
)
def test_added_keys_nothing_reads_and_unquoted_paths_are_one_line_errors(override, fragment):
    from physgrad.configs import check_overrides
    from physgrad.errors import UserError

    with pytest.raises(UserError) as caught:
        check_overrides(["task=toy", override], multirun=False)
    assert fragment in str(caught.value) and "\n" not in str(caught.value)
    # a keyword for the factory
    check_overrides(["task=toy", "+optim.weight_decay=0.1"], multirun=False)


@pytest.mark.parametrize(
    "args, fragment",
    [
        (
            ["task=nope"],
            "unknown task 'nope' (choose one of guidance, ks, multicart, oscillator, poisson, "
            "quantum, ",
        ),
        (
            ["optim=hgi"],
            "unknown optim 'hgi': did you mean hig? (choose one of adam, bptt, gauss_newton, gd, "
            "hig, ",
        ),
        (["trainer.iteratons=5"], "did you mean trainer.iterations?"),
        (["optim.lr=0.1"], "did you mean optim.learning_rate?"),
        (["seed=0,1"], "add -m"),
        (
            ["-m", "optim.learning_rate=interval(0.001,0.1)"],
            "basic sweeper cannot sample: tune with 'physgrad compare'",
        ),
    ],
)
def test_user_mistakes_are_one_line_errors(args, fragment, tmp_path, capsys):
    """Refused before a job starts, by physgrad.cli.main as the console script calls it: exit code
    2 and one line (its rendering on the console: tests/e2e/test_cli.py)."""
    assert main(["run", *args, f"hydra.run.dir={tmp_path}"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0], lines


@pytest.mark.parametrize("multirun", [True, False])
def test_the_output_folder_checked_is_the_one_hydra_reads(tmp_path, monkeypatch, multirun):
    """A quoted folder (compare writes every sweep folder quoted) is created without its quotes,
    and nothing is created in the working folder under the quoted name."""
    from physgrad.cli import check_writable
    from physgrad.comparison.jobs import hydra_quoted

    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    target = tmp_path / "a study, with [odd] 'names'" / "eval"
    check_writable([f"{key}={hydra_quoted(str(target))}"], multirun=multirun)
    assert target.is_dir() and list(work.iterdir()) == []
    # only the fixed part of an interpolated folder
    check_writable([f"{key}=runs/fixed/${{now:%H-%M-%S}}"], multirun=multirun)
    assert [p.relative_to(work).as_posix() for p in work.rglob("*")] == ["runs", "runs/fixed"]


def test_members_trained_together_get_the_scheduler_that_does_not_wedge_and_alone_do_not():
    """XLA's concurrency-optimized CPU scheduler wedged steps of 6 or more members trained together
    (physgrad.machine.MEMBERS_XLA_FLAG): a command line or a study's job that trains members
    together runs with it off; one member alone keeps XLA's default (40% faster on a cheap step);
    a user's own setting of the option is kept."""
    from physgrad.cli import members_asked
    from physgrad.comparison.jobs import job_yaml, members_together
    from physgrad.machine import MEMBERS_XLA_FLAG, members_environment

    assert members_asked(["task=toy", "seeds=8"]) and members_asked(["seeds=1,4"])
    assert members_asked(["+trial_values={learning_rate:[0.1,0.2]}"])
    assert not members_asked(["task=toy", "seeds=1"]) and not members_asked(["task=toy"])
    job = lambda **values: job_yaml(["task=toy", "optim=adam"], {"task", "optim"}, values)  # noqa: E731
    assert members_together(job(seed=0, seeds=3))
    assert members_together(job(seed=0, seeds=1, trial_values={"learning_rate": [0.1, 0.2]}))
    assert not members_together(job(seed=0, seeds=1))
    assert members_environment({"XLA_FLAGS": "--a=1"})["XLA_FLAGS"] == f"--a=1 {MEMBERS_XLA_FLAG}"
    assert members_environment({})["XLA_FLAGS"] == MEMBERS_XLA_FLAG
    own = {"XLA_FLAGS": "--xla_cpu_enable_concurrency_optimized_scheduler=true"}
    assert members_environment(own) == own


def test_a_link_planted_at_a_folder_physgrad_creates_is_one_line(monkeypatch, capsys, tmp_path):
    """A study's configs/ (or any folder physgrad makes through the write door) planted as a link:
    the LinkedFolder refusal ends the command with one line and exit 2, not a traceback."""
    import physgrad.comparison
    from physgrad.files import make_folder

    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "configs").symlink_to(outside)
    monkeypatch.setattr(
        physgrad.comparison, "main", lambda args: make_folder(tmp_path / "configs" / "job", 2)
    )
    assert main(["compare", "task=toy"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("physgrad: error: ") and "is a link, not a folder" in error
    assert "\n" not in error and not any(outside.iterdir())
