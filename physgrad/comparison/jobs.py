"""A study's jobs as config files, run as Hydra multiruns of `physgrad run` into the study folder,
and read back (the phase's progress on the console: physgrad.comparison.progress; which study the
folder holds: physgrad.comparison.study_folder)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from physgrad.comparison.progress import Progress
from physgrad.errors import UserError
from physgrad.interrupts import SignalInterrupt, handling_signals, take_lost
from physgrad.sweeps import STUDY_ENV

if TYPE_CHECKING:
    from types import FrameType

    from omegaconf import DictConfig

    from physgrad.results import Run

# --- jobs as config files
# ---------------------------------------------------------------------------------


def _nested(values: dict) -> dict:
    tree: dict = {}
    for dotted, value in values.items():
        node = tree
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def job_yaml(overrides: list[str], groups: set, values: dict) -> str:
    """One job as a config file appended to the run config (+compare_job=NAME): the group choices
    among the overrides as `override /group: option`, every other override and `values` as keys
    (packaged _global_)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    defaults, keys = [], {}
    for override in OverridesParser.create().parse_overrides(overrides):
        key = override.key_or_group
        if key in groups and override.package is None:
            defaults.append(f"override /{key}: {override.get_value_element_as_str()}")
        else:
            keys[key] = override.value()
    keys.update(values)
    text = "# @package _global_\n# written by physgrad compare\n"
    if defaults:
        text += "defaults:\n" + "".join(f"  - {line}\n" for line in defaults)
    return text + OmegaConf.to_yaml(OmegaConf.create(_nested(keys)))


def cadence(cfg: DictConfig, axis: str, budget: float) -> dict:
    """Evaluations fine enough to read the budget's quarters (time budgets: the runner's budget /
    20)."""
    if axis == "iteration" and cfg.trainer.get("eval_every", 100) * 20 > budget:
        return {"trainer.eval_every": max(1, int(budget) // 20)}
    return {}


# --- running
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Launcher:
    """Where and how a study's jobs run: the study folder, the user's config folder, Hydra's own
    arguments of the command line (a launcher, a search path) and the printer of progress lines."""

    folder: Path
    config_dir: str | None
    hydra_args: list[str]
    say: Callable[[str], object]

    def run(self, phase: str, jobs: dict[str, str], configs: dict | None = None) -> None:
        """The jobs as one multirun into folder/phase (launch), leaving out those whose results
        files finished before with the same config (configs: each job's variant config, to tell;
        none left: nothing is launched); KeyboardInterrupt where it was interrupted; UserError
        (one line) where the multirun was refused or jobs did not finish (interrupted one by one:
        scancel, a time limit, preemption; never started; crashed), naming them, their scheduler
        ids and why."""
        sweep = self.folder / phase
        # a phase or job folder that is a link is someone else's: its runs would be read into the
        # verdicts, and the jobs would write through it
        for where in (sweep, *(sweep / f"+compare_job={name}" for name in jobs)):
            if where.is_symlink():
                raise UserError(
                    f"{where}: a link: refused (a study folder may come from someone else); "
                    "remove it or give another compare.dir"
                )
        todo = {
            name: text
            for name, text in jobs.items()
            if configs is None or not job_finished(sweep, name, text, configs[name])
        }
        if not todo:
            self.say(f"{phase}: the {len(jobs)} jobs finished before: nothing to launch")
            return
        if len(todo) < len(jobs):
            self.say(f"{phase}: {len(jobs) - len(todo)} of {len(jobs)} jobs finished before")
        code = launch(self.folder, phase, todo, self.config_dir, self.hydra_args, self.say)
        if code == 130:
            raise KeyboardInterrupt
        if code != 0:
            _raise_unfinished(sweep, phase, todo, self.folder / f"{phase}.log")


def job_finished(sweep: Path, name: str, text: str, variant_config: DictConfig) -> bool:
    """Whether the job `name` (its config file's text, written by job_yaml for a variant of this
    config) finished before: every member's results file completed or diverged with the config the
    job would run (physgrad.resume.finished_before: the check the job itself makes at its start)."""
    import yaml
    from omegaconf import OmegaConf, open_dict

    from physgrad.job_spec import Refusal, check
    from physgrad.resume import finished_before

    cfg = variant_config.copy()
    keys = yaml.safe_load(text) or {}
    keys.pop("defaults", None)
    with open_dict(cfg):
        cfg.pop("hydra", None)
        cfg = OmegaConf.merge(cfg, keys)
    job = check(cfg)
    if isinstance(job, Refusal) or job.overwrite:
        return False
    folder = sweep / f"+compare_job={name}"
    return all(
        finished_before(folder / member.path, member.config, member.seed) is not None
        for member in job.members
    )


def _raise_unfinished(sweep: Path, phase: str, jobs: dict[str, str], log_path: Path) -> None:
    """A multirun that ended with a failure: UserError naming the jobs of `jobs` that did not
    finish (not the failed or refused ones: the phase reads those as outcomes) with their scheduler
    ids and why, or the multirun's own refusal (its `physgrad: error:` line in the log)."""
    from physgrad.sweeps import unfinished_jobs

    prefix = "+compare_job="
    left = [
        (job.removeprefix(prefix), why)
        for job, why in unfinished_jobs(sweep, interrupted=True)
        if job.removeprefix(prefix) in jobs and not why.startswith(("failed", "refused"))
    ]
    if left:
        listed = "; ".join(f"{name}: {why}" for name, why in left[:3])
        more = f"; and {len(left) - 3} more" if len(left) > 3 else ""
        raise UserError(
            f"{phase}: {len(left)} of {len(jobs)} jobs did not finish ({listed}{more}; log: "
            f"{log_path}): run the same command again to finish them"
        )
    refusal = _last_error(log_path)
    if refusal is not None:
        raise UserError(f"{phase}: {refusal}")


def _last_error(log_path: Path) -> str | None:
    """The last `physgrad: error:` line the multirun wrote to its log (read as data, its tail)."""
    from physgrad.files import clean_text, read_own_file

    try:  # the log as data: no link followed, no FIFO waited on; its last 64 KiB
        tail = read_own_file(log_path, 1 << 16, tail=True).decode(errors="replace")
    except (OSError, ValueError):
        return None
    tail = tail.rpartition("\n$ ")[2]  # this launch's part
    lines = [line for line in tail.splitlines() if line.startswith("physgrad: error: ")]
    return clean_text(lines[-1].removeprefix("physgrad: error: "), 400) if lines else None


def launch(
    folder: Path,
    phase: str,
    jobs: dict[str, str],
    config_dir: str | None,
    hydra_args: list[str],
    say: Callable[[str], object],
) -> int:
    """Write the jobs' config files and run them as one multirun into folder/phase (a job that
    completed or diverged before with the same config is skipped); its output goes to
    folder/<phase>.log. Returns the multirun's exit status.

    The multirun reads the job files from a folder this process creates and removes (never from
    the study folder, which may come from someone else: a config placed there, a tuning/ or
    logger/ option with a _target_, would otherwise run as code); folder/configs/compare_job/ keeps
    a copy as the record of the exact runs, written beside and renamed (a link planted there is
    replaced, not followed)."""
    import shutil
    import tempfile

    from physgrad.files import make_folder, replace_file

    record = make_folder(folder / "configs" / "compare_job", levels=2)
    private = Path(tempfile.mkdtemp(prefix="physgrad-jobs-"))
    try:
        (private / "compare_job").mkdir()
        for name, text in jobs.items():
            (private / "compare_job" / f"{name}.yaml").write_text(text)
            replace_file(record / f"{name}.yaml", text.encode())
        command = multirun_command(private, folder, phase, jobs, config_dir, hydra_args)
        say(f"{phase}: {len(jobs)} jobs -> {folder / phase} (log: {folder / (phase + '.log')})")
        progress = Progress(phase, len(jobs), say, names=tuple(jobs))
        env = job_environment()
        if any(members_together(text) for text in jobs.values()):
            from physgrad.machine import members_environment

            env = members_environment(env)
        return _run_multirun(command, folder / f"{phase}.log", env, progress)
    finally:
        shutil.rmtree(private, ignore_errors=True)


def _run_multirun(
    command: list[str], log_path: Path, env: dict[str, str], progress: Progress | None = None
) -> int:
    """The multirun as a child process in its own session, its output appended to log_path (opened
    without following a link: a study folder may come from someone else); its progress read from
    that output every few seconds (Progress)."""
    from physgrad.files import open_append

    try:
        log = open_append(log_path)
    except ValueError as error:  # the door's own line: a link, a FIFO, a second name
        raise UserError(f"{error}; remove it or give another compare.dir") from None
    except OSError as error:
        why = error.strerror or error
        raise UserError(f"{log_path}: {why}; remove it or give another compare.dir") from None
    with log:
        log.write(f"\n$ {' '.join(command)}\n")
        log.flush()
        # a signal the interpreter dropped since the last phase (physgrad.interrupts)
        lost = take_lost()
        if lost is not None:
            raise SignalInterrupt(lost)
        # its own session: a terminal's Ctrl-C reaches this process only, which passes it (or a
        # SIGTERM) on once, so the sweep stops as a whole and records what it stopped
        # (physgrad.sweeps)
        process = subprocess.Popen(
            command,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**env, STUDY_ENV: str(os.getpid())},
        )
        received = []

        def forward(signum: int, frame: FrameType | None) -> None:
            received.append(signum)
            process.send_signal(signum)

        with handling_signals(forward):  # not in another thread than the main one
            code = _wait_saying(process, log_path, log.tell(), progress)
        if received:
            raise KeyboardInterrupt(signal.Signals(received[0]).name)
        return code


def _wait_saying(
    process: subprocess.Popen, log_path: Path, offset: int, progress: Progress | None
) -> int:
    """process.wait(), reading what it appends to log_path after offset for progress (the log was
    opened without following a link just before; it is read the same way, and a log that cannot
    be read only leaves the console quiet)."""
    if progress is None:
        return process.wait()
    from physgrad.files import open_foreign

    try:
        reader = open_foreign(log_path)
    except (OSError, ValueError):
        return process.wait()
    try:
        while True:
            try:
                code = process.wait(timeout=POLL_SECONDS)
            except subprocess.TimeoutExpired:
                code = None
            try:
                text = os.pread(reader, 1 << 22, offset)  # a few MB at most per look
                offset += len(text)
            except OSError:
                text = b""
            progress.read(text.decode("utf-8", "replace"), final=code is not None)
            if code is not None:
                return code
    finally:
        os.close(reader)


POLL_SECONDS = 5.0


def members_together(job_text: str) -> bool:
    """Whether a job (its config file's text) trains several members in one step: seeds > 1 or
    trial_values."""
    import yaml

    keys = yaml.safe_load(job_text) or {}
    return bool(keys.get("trial_values")) or int(keys.get("seeds") or 1) > 1


def job_environment() -> dict[str, str]:
    """The environment of a study's jobs: this process's, with JAX's persistent compilation cache in
    the user's physgrad cache (physgrad.files.cache_dir()/jax) unless the user chose one
    (JAX_COMPILATION_CACHE_DIR). The jobs of a study compile the same evaluations, data generators
    and, where only a tuned value differs, often the same steps again: a cached executable is the
    same code, so results do not change. Never in the study folder: a compiled executable is code,
    and a study folder may come from someone else. The GPU settings are those the command started
    with (physgrad.gpus: each job claims its own GPU)."""
    from physgrad.files import cache_dir
    from physgrad.gpus import original_environment

    env = original_environment()
    if "JAX_COMPILATION_CACHE_DIR" not in env:
        env["JAX_COMPILATION_CACHE_DIR"] = str(cache_dir() / "jax")
        # every executable, not only those that took a second to compile: a study's jobs compile
        # many small ones (evaluations, data generators) alike, each a fraction of a second
        env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    return env


def multirun_command(
    job_files: Path,
    folder: Path,
    phase: str,
    jobs: dict[str, str],
    config_dir: str | None,
    hydra_args: list[str],
) -> list[str]:
    """`physgrad run -m` over the jobs' config files in job_files/compare_job (+compare_job=a,b,...)
    into folder/phase, with the user's config folder and Hydra overrides (a hydra.searchpath given
    is searched before the jobs' files)."""
    search = [f"file://{job_files.resolve()}"]
    extra = []
    for arg in hydra_args:
        if arg.startswith("hydra.searchpath="):
            from physgrad.configs import searchpath_entries

            search = searchpath_entries([arg]) + search
        else:
            extra.append(arg)
    return [
        sys.executable,
        "-m",
        "physgrad",
        "run",
        "-m",
        *(["-cd", config_dir] if config_dir else []),
        f"hydra.searchpath=[{','.join(search)}]",
        f"hydra.sweep.dir={hydra_quoted(str(folder / phase))}",
        *extra,
        "+compare_job=" + ",".join(jobs),
    ]


def hydra_quoted(value: str) -> str:
    """value as one quoted string of Hydra's override grammar, so that a folder name with a comma,
    a space, brackets or any letter stays one value: a quote is escaped, and so are the backslashes
    before a quote or at the end (Hydra reads other backslashes as they are)."""

    doubled = re.sub(r"(\\+)(?='|$)", lambda m: m.group(1) * 2, value)
    return "'" + doubled.replace("'", "\\'") + "'"


def job_runs(sweep: Path, name: str) -> list[Run]:
    """The readable runs of a job: its results.h5, or its members' (seed=<s>/ or trial=<i>/, in
    numeric order); a member folder or a file that is a link is not read (someone else's)."""
    from physgrad.results import member_order, read_run

    folder = sweep / f"+compare_job={name}"
    runs = []
    members = sorted(
        [*folder.glob("seed=*/results.h5"), *folder.glob("trial=*/results.h5")],
        key=member_order,
    )
    for path in sorted(folder.glob("results.h5")) + members:
        if path.parent.is_symlink() or folder.is_symlink():  # a linked file: the reader refuses
            continue
        try:
            runs.append(read_run(path))
        except ValueError:
            continue
    return runs
