"""What a result was measured on, and whether its timing can be trusted.

machine_attributes(): the CPU (model, cores), the device, the thread settings of XLA and BLAS, the
versions and the project's git commit, recorded in every results file (docs/results.md).
step_statistics() and contention(): the step-time percentiles of a run and the contention rule
(docs/decisions.md, "Timing"): a run is flagged ``contended`` when
  - its step times spread: p90 / p50 > CONTENTION_SPREAD and p90 - p50 > CONTENTION_JITTER_SECONDS,
    over at least CONTENTION_MIN_STEPS steps of a step whose cost does not depend on the data (not
    L-BFGS's line search): a shape-static step costs the same every time, up to the operating
    system's sub-millisecond jitter, which spreads sub-millisecond steps on a quiet machine (Adam on
    the toy: p90 / p50 up to 1.8 at 0.3 ms), while another process holding a core delays a step by a
    scheduler time slice (milliseconds), or
  - the machine was oversubscribed: the 1-minute load average at the start or the end, less the
    run's own one runnable process, reached the number of cores.
"""

from __future__ import annotations

import functools
import os
import platform
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from physgrad.version import __version__

CONTENTION_SPREAD = 1.5
CONTENTION_JITTER_SECONDS = 1e-3
CONTENTION_MIN_STEPS = 20
THREAD_VARIABLES = (
    "XLA_FLAGS",
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "TF_NUM_INTEROP_THREADS",
    "TF_NUM_INTRAOP_THREADS",
)
# XLA's concurrency-optimized CPU scheduler can wedge the step of several members trained together
# (SOAP with 6 or more seeds or trials on the oscillators, 2 cores: every thread idle, the result
# never ready). Off, members trained together step as fast (8 Adam trials: 19.4 s against 19.8
# s for 1,000 steps) and one member alone about 40% slower (Adam: 4.1 ms against 2.8 ms), so
# physgrad turns it off only where members train together, unless XLA_FLAGS already sets it.
MEMBERS_XLA_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"


def members_environment(env: Mapping[str, str]) -> dict[str, str]:
    """env for processes that train members together: XLA_FLAGS with MEMBERS_XLA_FLAG added,
    unless it already sets that option."""
    flags = env.get("XLA_FLAGS", "")
    if MEMBERS_XLA_FLAG.partition("=")[0] in flags:
        return dict(env)
    return {**env, "XLA_FLAGS": f"{flags} {MEMBERS_XLA_FLAG}".strip()}


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, platform elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")):
                return line.split(":", 1)[1].strip()[:200]
    except OSError:
        pass
    return (platform.processor() or platform.machine() or "unknown")[:200]


def cpu_count() -> int:
    """The cores this process may run on (the affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def load_average() -> float:
    """The 1-minute load average (NaN where the OS has none)."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return float("nan")


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """The commit of the git checkout physgrad runs from, with '+dirty:<hash>' for uncommitted
    changes (the first 12 hex digits of the SHA-256 of `git diff HEAD`: two runs from the same
    changes record the same hash); '' for an installed copy outside a checkout."""
    return checkout_commit(Path(__file__).resolve().parent.parent)


def checkout_commit(root: Path) -> str:
    """The commit of the git checkout at root, '+dirty:<hash>' appended for uncommitted changes to
    tracked files (git_commit); '' outside a checkout or where git cannot tell."""
    import hashlib

    if not (root / ".git").exists():
        return ""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10
        ).stdout

    try:
        commit = git("rev-parse", "HEAD").strip()
        dirty = git("status", "--porcelain", "--untracked-files=no").strip()
        diff = git("diff", "HEAD") if commit and dirty else ""
    except (OSError, subprocess.SubprocessError):
        return ""
    if not (commit and dirty):
        return commit
    return f"{commit}+dirty:{hashlib.sha256(diff.encode()).hexdigest()[:12]}"


def device_name() -> str:
    """'cpu' or the accelerator's model, as jax sees its first device."""
    import jax

    device = jax.devices()[0]
    return (
        device.platform if device.platform == "cpu" else f"{device.platform}: {device.device_kind}"
    )


def machine_attributes() -> dict:
    """The machine and software a run is measured on (root attributes of results.h5)."""
    import jax
    import jaxlib

    threads = "; ".join(
        f"{name}={os.environ[name]}" for name in THREAD_VARIABLES if name in os.environ
    )
    return {
        "cpu_model": cpu_model(),
        "cpu_count": cpu_count(),
        "device": device_name(),
        "thread_settings": threads or "default",
        "jax_version": jax.__version__,
        "jaxlib_version": jaxlib.__version__,
        "physgrad_version": __version__,
        "git_commit": git_commit(),
        "hostname": platform.node()[:200],
    }


def machine_label(attrs: Mapping) -> str:
    """One line naming where a run was measured: CPU model and cores, and the device when it is not
    the CPU."""
    model = str(attrs.get("cpu_model", "") or "")
    if not model:
        return "unknown machine"
    label = f"{model} ({attrs.get('cpu_count', '?')} cores)"
    device = str(attrs.get("device", "") or "")
    return label if not device or device == "cpu" else f"{label}, {device}"


def step_statistics(step_seconds: Sequence[float]) -> dict:
    """p10, p50, p90 and p99 of a run's step times (seconds; the first, compiling call left out by
    the caller)."""
    times = np.asarray(step_seconds, float)
    if times.size == 0:
        return {}
    p10, p50, p90, p99 = np.percentile(times, [10, 50, 90, 99])
    return {
        "step_seconds_p10": float(p10),
        "step_seconds_p50": float(p50),
        "step_seconds_p90": float(p90),
        "step_seconds_p99": float(p99),
    }


def contention(
    statistics: dict,
    steps: int,
    load_start: float,
    load_end: float,
    cores: int,
    static_cost: bool = True,
) -> str:
    """Why a run's timing is not to be trusted ('' when it is): the rule of this module's docstring.
    static_cost: whether the step's cost is independent of the data (else only the load is
    judged)."""
    reasons = []
    p50, p90 = statistics.get("step_seconds_p50"), statistics.get("step_seconds_p90")
    if (
        static_cost
        and steps >= CONTENTION_MIN_STEPS
        and p50
        and p90 is not None
        and p90 > CONTENTION_SPREAD * p50
        and p90 - p50 > CONTENTION_JITTER_SECONDS
    ):
        reasons.append(f"step times spread: p90/p50 = {p90 / p50:.2f} > {CONTENTION_SPREAD:g}")
    loads = [x for x in (load_start, load_end) if np.isfinite(x)]
    if loads and max(loads) - 1.0 >= cores:
        reasons.append(
            f"load average {max(loads):.2f} with {cores} cores (other work beside the run)"
        )
    return "; ".join(reasons)


def timing_attributes(
    step_seconds: list[float], load_start: float, load_end: float, static_cost: bool = True
) -> dict:
    """The step-time percentiles, the load average at the start and the end, and the contention flag
    with its reason (contention)."""
    statistics = step_statistics(step_seconds)
    cores = cpu_count()
    why = contention(statistics, len(step_seconds), load_start, load_end, cores, static_cost)
    attrs = {
        **statistics,
        "load_start": load_start,
        "load_end": load_end,
        "contended": int(bool(why)),
    }
    if why:
        attrs["contention"] = why
    return attrs
