"""One GPU per job on a machine with several.

physgrad trains on one device (seeds and trials trained together share it), and jax, once started,
takes memory on every GPU it sees (75% of each unless XLA_PYTHON_CLIENT_PREALLOCATE=false). Jobs
run side by side by a local launcher (hydra/launcher=joblib) would all share the first GPU and
each take memory on all of them. So each job process claims one GPU before jax starts:

- the GPUs are those of CUDA_VISIBLE_DEVICES when it is set, else those `nvidia-smi -L` lists;
- a process claims the first GPU that no other physgrad process of this user on this machine holds
  (an exclusive, non-blocking lock on a file per GPU in the user's runtime folder, released by the
  operating system when the process ends, however it ends), and sets CUDA_VISIBLE_DEVICES to it;
- with all of them held, it shares the one its job number selects, with one warning;
- one GPU or none visible (a CPU machine, a SLURM job given one GPU): nothing changes.

`physgrad compare` on a machine with several GPUs runs each phase's jobs side by side, one per GPU
(local_launcher_args), and its own calibration on one GPU without taking memory on the others
(pin_this_process); the jobs get the environment the command was started with.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import stat
import subprocess
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

# the lock of the GPU this process holds, kept open for the process's life
_held: list[int] = []
# this process's environment before pin_this_process changed it (what its jobs get)
_original: dict[str, str | None] = {}


def visible_gpus(environ: dict[str, str] | None = None) -> list[str]:
    """The GPUs a process started with `environ` may use, as CUDA_VISIBLE_DEVICES entries."""
    environ = os.environ if environ is None else environ
    listed = environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        entries = [entry.strip() for entry in listed.split(",") if entry.strip()]
        # CUDA stops at the first invalid entry; "-1" is the usual way to hide every GPU
        valid = []
        for entry in entries:
            if entry.startswith("-"):
                break
            valid.append(entry)
        return valid
    if shutil.which("nvidia-smi") is None:
        return []
    try:
        listing = subprocess.run(
            ["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20, check=False
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, line in enumerate(listing.splitlines()) if line.startswith("GPU ")]


def lock_folder() -> Path | None:
    """The user's folder of GPU locks on this machine (in the runtime folder, else the temporary
    folder, which others can write to); None, with a warning, where it cannot be the user's own: it
    cannot be made, it is a link or no folder, another user owns it, or others may write in it (a
    mode beyond 0700). Another user's folder would let them hold or read the claims."""
    base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    folder = Path(base) / f"physgrad-gpus-{os.getuid()}"
    try:
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:
            pass  # the folder from before, or something else in its place: told below
        found = os.lstat(folder)
    except OSError as error:
        why = f"not usable ({error.strerror or error})"
    else:
        why = (
            "a link"
            if stat.S_ISLNK(found.st_mode)
            else "not a folder"
            if not stat.S_ISDIR(found.st_mode)
            else f"owned by user {found.st_uid}"
            if found.st_uid != os.getuid()
            else f"open to other users (mode {stat.S_IMODE(found.st_mode):o}, not 700)"
            if found.st_mode & 0o077
            else None
        )
    if why is None:
        return folder
    log.warning("GPU locks: %s is %s: this job is not pinned to one GPU", folder, why)
    return None


def _try_lock(path: Path) -> int | None:
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def claim_gpu(job_number: int = 0) -> str | None:
    """Give this process one GPU of several (module docstring) by setting CUDA_VISIBLE_DEVICES;
    returns the GPU, or None where nothing was changed (one GPU or none, or a lock folder or file
    that cannot be used: a warning, and the job runs unpinned). Call before jax starts its
    backend."""
    gpus = visible_gpus()
    if len(gpus) <= 1 or _held:
        return None
    folder = lock_folder()
    if folder is None:
        return None
    for gpu in gpus:
        lock = folder / f"{gpu.replace('/', '_')}.lock"
        try:
            fd = _try_lock(lock)
        except OSError as error:  # a link, a name too long, a read-only file system: not pinned
            log.warning(
                "GPU locks: %s cannot be used (%s): this job is not pinned to one GPU",
                lock,
                error.strerror or error,
            )
            return None
        if fd is not None:
            _held.append(fd)
            os.environ["CUDA_VISIBLE_DEVICES"] = gpu
            log.info(
                "GPU %s of %s for this job process (CUDA_VISIBLE_DEVICES)", gpu, ",".join(gpus)
            )
            return gpu
    gpu = gpus[job_number % len(gpus)]
    log.warning(
        "all %d GPUs are held by other physgrad jobs of this user: this job shares GPU %s",
        len(gpus),
        gpu,
    )
    os.environ["CUDA_VISIBLE_DEVICES"] = gpu
    return gpu


def pin_this_process() -> int:
    """Where several GPUs are visible, let this process (a comparison's calibration) see the first
    only, without taking its memory up front, and remember the environment its jobs get
    (job_environment). Returns the number of GPUs visible before."""
    gpus = visible_gpus()
    if len(gpus) > 1 and not _original:
        for name in ("CUDA_VISIBLE_DEVICES", "XLA_PYTHON_CLIENT_PREALLOCATE"):
            _original[name] = os.environ.get(name)
        os.environ["CUDA_VISIBLE_DEVICES"] = gpus[0]
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    return len(gpus)


def original_environment() -> dict[str, str]:
    """This process's environment as it started (before pin_this_process)."""
    env = dict(os.environ)
    for name, value in _original.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value
    return env


def local_launcher_args(hydra_args: list[str], gpus: int) -> list[str]:
    """Hydra's arguments for a comparison's jobs: with several GPUs and no launcher chosen, the
    jobs run side by side, one per GPU (the joblib launcher, one process per GPU; where that plugin
    is not installed, one after another, with a warning that says how to install it)."""
    import importlib.util

    chose = any(arg.split("=")[0] in ("hydra/launcher", "+hydra/launcher") for arg in hydra_args)
    if gpus <= 1 or chose:
        return hydra_args
    if importlib.util.find_spec("hydra_plugins.hydra_joblib_launcher") is None:
        log.warning(
            "%d GPUs, but Hydra's joblib launcher is not installed: the jobs run one after another "
            "on one GPU (pip install 'physgrad[launchers]' runs one per GPU)",
            gpus,
        )
        return hydra_args
    return [*hydra_args, "hydra/launcher=joblib", f"hydra.launcher.n_jobs={gpus}"]
