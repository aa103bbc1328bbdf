"""What Hydra calls around the jobs of `physgrad run`: the name of a sweep's job folder (a resolver
of hydra.sweep.subdir), the job's log file (a logging handler of hydra.job_logging) and the sweep's
summary (a callback in the process that launched the sweep: it holds the folder, turns signals into
a stop of every job and counts the runs at the end)."""

from __future__ import annotations

import hashlib
import logging
import os
import stat
import sys
from collections import Counter
from collections.abc import Iterable
from contextlib import ExitStack
from pathlib import Path
from typing import IO, Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from physgrad.errors import FolderOwned
from physgrad.files import open_append, own_folder
from physgrad.results import find_results, read_final
from physgrad.sweeps import (
    STOP_MARK,
    expected_jobs,
    launcher_signals,
    stop_count,
    unfinished_jobs,
    write_manifest,
)

log = logging.getLogger("physgrad")


# what an experiment can find; anything else is a failure
OUTCOMES = ("completed", "diverged", "refused")
# set by SweepSummary at the end of a sweep: `physgrad run -m` exits 1 if non-zero
FAILED_JOBS: list[int] = []
INTERRUPTED_BY_SIGNAL: list[str] = []  # ... and 130 if a signal stopped it (the signal's name)


def job_folder_name(override_dirname: str, task_overrides: Iterable | None) -> str:
    """The job folder of a sweep (hydra.sweep.subdir): the job's overrides
    (hydra.job.override_dirname), plus init_from when the command line sets it, as a short hash of
    the path (a path's slashes would make folders, and without it two jobs that differ only in
    init_from would share one folder); names too long for a file system end in a hash of the full
    name instead."""
    parts = [override_dirname] if override_dirname else []
    for override in task_overrides or ():
        key, _, value = str(override).lstrip("+~").partition("=")
        if key == "init_from" and value not in ("", "null"):
            parts.append(f"init_from={hashlib.sha1(value.encode()).hexdigest()[:8]}")
    name = ",".join(parts)
    if len(name.encode()) > NAME_LIMIT:
        digest = hashlib.sha1(name.encode()).hexdigest()[:12]
        name = name.encode()[: NAME_LIMIT - 16].decode(errors="ignore") + f"...{digest}"
    return name


NAME_LIMIT = 200  # bytes: file systems allow 255 per folder name
OmegaConf.register_new_resolver("physgrad_job_folder", job_folder_name, replace=True)


class JobLogFile(logging.FileHandler):
    """The job's log file (hydra.job_logging's file handler), opened at its first record: a folder
    that cannot be written (read-only, full) costs one warning line, not the job or the sweep."""

    def __init__(
        self,
        filename: str | os.PathLike,
        mode: str = "a",
        encoding: str | None = None,
        delay: bool = True,
        errors: str | None = None,
    ) -> None:
        super().__init__(filename, mode, encoding, delay=True, errors=errors)
        self.unwritable = False

    def _open(self) -> IO[str]:
        # appended without following a link: a rerun sweep's folder may come from someone else

        return open_append(Path(self.baseFilename))

    def emit(self, record: logging.LogRecord) -> None:
        if self.unwritable:
            return
        try:
            super().emit(record)
        except (OSError, ValueError) as error:  # ValueError: the door's (a link, a FIFO)
            self.unwritable = True
            print(
                f"physgrad: warning: the job log {self.baseFilename} cannot be written "
                f"({getattr(error, 'strerror', None) or error}): logging to the terminal only",
                file=sys.stderr,
            )


def _clear_hydra_record(path: Path) -> None:
    """Hydra's sweeper writes its record (multirun.yaml) with a plain open: a link, a second name
    of another file (a hard link) or a FIFO planted at that name in a sweep folder from someone
    else is removed first, so that Hydra creates a file of its own; a folder there ends the sweep
    in one line (exit 2)."""
    try:
        found = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISREG(found.st_mode) and found.st_nlink == 1:
        return
    try:
        path.unlink()
    except OSError as error:
        print(
            f"physgrad: error: {path} is not a file physgrad can replace "
            f"({error.strerror or error}): remove it and run again",
            file=sys.stderr,
        )
        sys.exit(2)


class SweepSummary(Callback):
    """Around a sweep, in the process that launched it (whatever the launcher): holds the sweep
    folder (a second sweep into it is refused while this one runs), writes the manifest of expected
    jobs, turns SIGINT and SIGTERM into a stop of every job (physgrad.sweeps); at the end, the runs
    it wrote counted by status, the jobs that never started or left no file, and the report command
    to run next. A failed, interrupted or missing run makes `physgrad run -m` exit with status 1;
    refused and diverged runs are outcomes, not failures."""

    def __getstate__(self) -> dict:
        # a launcher sends the callbacks to its workers with each job: the sweep's state stays here
        return {}

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from hydra_plugins.physgrad_launchers.slurm import use_physgrad_launcher

        folder = Path(str(config.hydra.sweep.dir))
        self.held = ExitStack()
        try:
            self.held.enter_context(own_folder(folder, "sweep"))
        except FolderOwned as error:
            print(f"physgrad: error: {error}", file=sys.stderr)
            sys.exit(2)
        except OSError as error:
            print(
                f"physgrad: error: cannot write the sweep folder {folder}: "
                f"{error.strerror or error}",
                file=sys.stderr,
            )
            sys.exit(2)
        (folder / STOP_MARK).unlink(missing_ok=True)
        _clear_hydra_record(folder / "multirun.yaml")
        use_physgrad_launcher(config)  # before Hydra builds the launcher (physgrad.cluster)
        jobs = expected_jobs(config)
        if jobs is not None:
            write_manifest(folder, jobs)
        self.held.enter_context(launcher_signals(folder))
        # what was there before: a file counts as this sweep's if it is new or was written since
        self.before = {path: _changed(path) for path in find_results([folder])}
        FAILED_JOBS.clear()
        INTERRUPTED_BY_SIGNAL.clear()

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        folder = Path(str(config.hydra.sweep.dir))
        written, earlier = Counter(), 0
        for path in find_results([folder]) if folder.is_dir() else []:
            try:
                status = read_final(path)[0].get("status", "?")
            except ValueError:
                status = "unreadable"
            if getattr(self, "before", {}).get(path) != _changed(path):
                written[status] += 1
            else:
                # untouched by this sweep: completed or diverged before with the same config, or
                # another job's
                earlier += 1
        for job_name, why in unfinished_jobs(folder, interrupted=True):
            log.warning("job %s: %s", job_name, why)
            if not why.startswith("interrupted"):  # an interrupted run's file is counted above
                written[why.split(":")[0]] += 1
        stopped = stop_count(folder)
        INTERRUPTED_BY_SIGNAL[:] = [stopped[0]] if stopped else []
        # a run left running or crashed (its worker was killed), interrupted, failed, unreadable or
        # missing
        FAILED_JOBS[:] = [sum(n for status, n in written.items() if status not in OUTCOMES)]
        counts = (
            ", ".join(f"{n} {status}" for status, n in sorted(written.items())) or "no runs written"
        )
        skipped = (
            f"; {earlier} untouched (completed or diverged before: skipped)" if earlier else ""
        )
        how = f"stopped by {stopped[0]}" if stopped else "finished"
        log.info(
            "sweep %s: %s%s in %s; next: physgrad report %s", how, counts, skipped, folder, folder
        )
        held = getattr(self, "held", None)
        if held is not None:
            held.close()


def _changed(path: Path) -> int | None:
    """When the entry at path last changed (a link's own time, not its target's); None if gone."""
    try:
        return os.lstat(path).st_mtime_ns
    except OSError:
        return None
