"""A study's jobs as config files, run as Hydra multiruns of `physgrad run` into the study folder,
and read back; and the study folder itself (which study it holds)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from physgrad.errors import UserError
from physgrad.interrupts import SignalInterrupt, take_lost
from physgrad.sweeps import STUDY_ENV

if TYPE_CHECKING:
    from types import FrameType

    from omegaconf import DictConfig

    from physgrad.results import Run

# what does not make a study another: its folder, Hydra's settings, the variant the others are
# compared with (the same runs, read again), and the number of trials and of tuning studies (a
# finished study given more trials tunes on from where it stopped: the Halton points of n trials
# begin with those of fewer; given more studies, it adds them)
NOT_THE_STUDY = ("compare.dir", "compare.trials", "compare.studies", "compare.baseline", "hydra")
# how a study draws its trial points and seeds; a folder of another protocol is another study.
# 2: each tuning study its own evaluation seeds and randomly shifted trial points (1, unrecorded:
# the studies shared their evaluation seeds and scrambled the points within their cells)
PROTOCOL = 2


# --- the study folder
# --------------------------------------------------------------------------------------


def same_study(record: dict | None) -> tuple[list | None, object] | None:
    """The parts of a study.json record that identify the study."""
    if not isinstance(record, dict):
        return None
    overrides = record.get("overrides")
    return (
        [o for o in overrides if not str(o).startswith(NOT_THE_STUDY)]
        if isinstance(overrides, list)
        else None,
        record.get("config_dir"),
        record.get("protocol", 1),
    )


def configuration_of(configs: list) -> str:
    """A fingerprint of what the variants' scene and rules are (their composed task, optim and
    precision settings): the same command given other defaults (physgrad upgraded, a config file
    edited) is another study, whose earlier tuning and runs must not be resumed."""
    from omegaconf import OmegaConf

    text = json.dumps(
        [
            OmegaConf.to_container(
                OmegaConf.masked_copy(config, ["task", "optim", "precision"]), resolve=False
            )
            for config in configs
        ],
        sort_keys=True,
        default=str,
    )
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def default_folder(
    overrides: list[str], config_dir: str | None, task: str, configuration: str = ""
) -> Path:
    text = json.dumps(
        [
            sorted(o for o in overrides if not o.startswith(NOT_THE_STUDY)),
            os.path.abspath(config_dir) if config_dir else None,
            PROTOCOL,  # a study of another protocol gets another folder
            *([configuration] if configuration else []),  # so do other defaults
        ]
    )
    return Path("outputs") / "compare" / f"{task}-{hashlib.sha1(text.encode()).hexdigest()[:8]}"


def record_study(
    folder: Path, overrides: list[str], config_dir: str | None, configuration: str = ""
) -> None:
    """The study's command in folder/study.json; a folder that holds another study is a UserError
    (the same study given more trials is the same study: its record is updated), and so is one
    that holds this command run with another configuration (configuration_of; a record without
    one, written before it was kept, cannot be checked)."""
    record = {
        "overrides": [o for o in overrides if not o.startswith(("compare.dir", "hydra"))],
        "config_dir": os.path.abspath(config_dir) if config_dir else None,
        "protocol": PROTOCOL,
        **({"configuration": configuration} if configuration else {}),
    }
    from physgrad.files import load_json, read_own_file, replace_file

    stored = folder / "study.json"
    if os.path.lexists(stored):
        try:
            data = read_own_file(stored, 1 << 20)
        except (OSError, ValueError) as error:
            raise UserError(f"{error}; remove it or give another compare.dir") from None
        try:
            before = load_json(data)
        except ValueError:
            before = None
        stored_study, this_study = same_study(before), same_study(record)
        if stored_study and stored_study[:2] == this_study[:2] and stored_study != this_study:
            raise UserError(
                f"{folder} holds this study run by an earlier physgrad, whose tuning studies "
                "shared their evaluation seeds: give another compare.dir (or move the folder "
                "away) to run it with independent studies"
            )
        if stored_study != this_study:
            raise UserError(
                f"{folder} holds another study "
                f"({' '.join((before or {}).get('overrides', ['?']))}): give another compare.dir"
            )
        if before.get("configuration") not in (None, record.get("configuration")):
            raise UserError(
                f"{folder} holds this study run with other settings of its scene or rules (a "
                "changed default: physgrad upgraded, or a config file edited): give another "
                "compare.dir (or move the folder away) to run it again"
            )
    if not stored.exists() or before != record:  # new, or the same study given more trials
        replace_file(stored, (json.dumps(record, indent=1) + "\n").encode())


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

    from physgrad.experiment import member_configs, seed_paths
    from physgrad.resume import finished_before

    cfg = variant_config.copy()
    keys = yaml.safe_load(text) or {}
    keys.pop("defaults", None)
    with open_dict(cfg):
        cfg.pop("hydra", None)
        cfg = OmegaConf.merge(cfg, keys)
    if cfg.get("overwrite", False):
        return False
    paths = seed_paths(cfg, sweep / f"+compare_job={name}")
    return all(
        finished_before(path, member, seed) is not None
        for (seed, path), member in zip(paths, member_configs(cfg, len(paths)))
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


# Hydra's line for each job it launches: "[HYDRA] \t#3 : +compare_job=..."; a job's training
# progress as the runner logs it without a terminal (physgrad.progress): "toy/hig seed 1000000
# (+1) iteration 6214, loss 0.007778, 28.5 s of training"
_EVENT = re.compile(
    r"\[HYDRA\]\s+#(?P<job>\d+) : "
    r"|\[HYDRA\] job \S+: (?P<stopped>never started|interrupted)"
    r"|\] - (?P<label>\S+ seed \d+(?: \(\+\d+\))?) "
    r"iteration (?P<iteration>\d+), loss (?P<loss>\S+),"
)


@dataclass
class Progress:
    """A phase's progress on the console, read from its log as the multirun writes it. On a terminal
    (stream, default stderr), a bar over the phase's jobs with the running job's loss so far and
    the time left, redrawn at every look; without one (a log, nohup, a batch job), a line when
    more of its jobs have started, at most one every `every` seconds, with the same news, so that
    logs stay readable. Either way one line at the end with the jobs it ran (Hydra launches the
    jobs of a local sweep one after another, so job k started means k - 1 done). names: the jobs
    in launch order, where known, so that the time left counts each job at its own variant's pace
    (a Gauss-Newton job may take ten of Adam's)."""

    phase: str
    total: int
    say: Callable[[str], object]
    names: tuple[str, ...] = ()
    every: float = 30.0
    started: int = 0
    said: int = 0
    begun: float = field(default_factory=time.monotonic)
    last: float = field(default_factory=time.monotonic)
    launched_at: float = 0.0  # when the latest job was seen to start
    training: str = ""  # the running job's last progress: its label, loss and iteration
    training_said: str = ""
    stream: object = None  # where the bar is drawn (None: stderr); no bar unless it is a terminal
    bar: object = field(default=None, init=False)  # the terminal's bar (tqdm), if there is one
    took: dict = field(default_factory=dict, init=False)  # a job's kind -> seconds of each done
    # jobs a stopped sweep names as interrupted or never started (its launcher still logs a
    # launch line for each, so the launches alone would count them as run)
    stopped: dict = field(default_factory=dict, init=False)

    def __post_init__(self) -> None:
        import sys

        from tqdm import tqdm

        bar = tqdm(
            total=self.total,
            desc=self.phase,
            unit="job",
            file=self.stream if self.stream is not None else sys.stderr,
            disable=None,  # a bar only on a terminal
            leave=False,
            dynamic_ncols=True,
            bar_format="{desc}: {n}/{total} jobs done |{bar}| {elapsed}{postfix}",
        )
        self.bar = None if bar.disable else bar

    def read(self, text: str, final: bool = False) -> None:
        """Take the log's new text; say where the phase is if it moved on."""
        now = time.monotonic()
        for event in _EVENT.finditer(text):
            if event["job"] is not None and int(event["job"]) + 1 > self.started:
                if self.started:
                    kind = self._kind(self.started - 1)
                    self.took.setdefault(kind, []).append(now - self.launched_at)
                self.started, self.launched_at, self.training = int(event["job"]) + 1, now, ""
            elif event["stopped"] is not None:
                self.stopped[event["stopped"]] = self.stopped.get(event["stopped"], 0) + 1
            elif event["label"] is not None:
                self.training = (
                    f"{event['label']}: loss {event['loss']} at iteration {event['iteration']}"
                )
        moved = self.started > self.said
        minutes = (now - self.begun) / 60
        if self.bar is not None:
            ran = min(self.started - (0 if final else 1), self.total) - sum(self.stopped.values())
            self.bar.n = max(0, ran)
            news = [
                f"job {self.started}: {self.training}" if self.training else "",
                "" if final else self._left(now),
            ]
            self.bar.set_postfix_str("; ".join(n.removeprefix("; ") for n in news if n), False)
            self.bar.refresh()
            if final:
                self.bar.close()
        if final and self.started:
            ran = min(self.started, self.total) - sum(self.stopped.values())
            self.say(
                f"{self.phase}: {ran} of {self.total} jobs run in {minutes:.1f} min"
                + (
                    ", then stopped ("
                    + ", ".join(f"{n} {why}" for why, n in sorted(self.stopped.items()))
                    + ")"
                    if self.stopped
                    else ""
                )
            )
        elif (
            self.bar is None
            and (moved or self.training != self.training_said)
            and now - self.last >= self.every
        ):
            self.say(
                f"{self.phase}: job {min(self.started, self.total)} of {self.total} started, "
                f"{minutes:.1f} min in"
                + (f"; {self.training}" if self.training else "")
                + self._left(now)
            )
            self.said, self.last, self.training_said = self.started, now, self.training

    def _kind(self, index: int) -> int | None:
        """Job index's variant (None where its name does not say, or is not known)."""
        from physgrad.comparison.spec import variant_index

        try:
            return variant_index(self.names[index])
        except (IndexError, AttributeError):  # no name, or one without a variant (calibration)
            return None

    def _left(self, now: float) -> str:
        """The time left at the pace of the jobs done (none before one is done, or once all are):
        each job not done at the mean time of the done jobs of its variant, less what the running
        one has had; once the running one has had more than that, the time left after it, how
        long it has run and, where its variant has a done job, how long those took. Jobs of a
        variant none of whose jobs is done have no pace to count them at: the time is then "at
        least" and says how many such jobs are left (another variant's pace can be ten times
        off: a Gauss-Newton job beside Adam's)."""
        done = self.started - 1
        if done < 1 or done >= self.total:
            return ""

        def pace(index: int) -> float | None:
            times = self.took.get(self._kind(index))
            return sum(times) / len(times) if times else None

        later = [pace(index) for index in range(self.started, self.total)]
        after = sum(p for p in later if p is not None)
        untimed = sum(p is None for p in later)
        running, expected = now - self.launched_at, pace(done)
        bound = "at least" if untimed or expected is None else "about"
        besides = (
            ""
            if not untimed
            else ", and 1 job of a variant not timed yet"
            if untimed == 1
            else f", and {untimed} jobs of variants not timed yet"
        )
        if expected is not None and running <= expected:
            return f"; {bound} {_span(expected - running + after)} left{besides}"
        ran, why = f"{_span(running)} so far", "the first of its variant"
        if expected is not None:
            why = f"about {_span(expected)} expected"
        if untimed and not after:  # "at least 0 s left" would say nothing
            return f"; the running job {ran} ({why}){besides}"
        return f"; {bound} {_span(after)} left after the running job ({ran}, {why}){besides}"


def _span(seconds: float) -> str:
    """A duration as the console says it: seconds up to a minute and a half, then minutes."""
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


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

        try:
            previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
        except ValueError:  # not the main thread: leave signals alone
            previous = {}
        try:
            code = _wait_saying(process, log_path, log.tell(), progress)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
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
    import re

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
