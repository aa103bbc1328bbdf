"""Code the tests share (not tests themselves)."""

import dataclasses
import subprocess
import sys
from pathlib import Path

from physgrad.configs import compose

# What every test's config gets unless the test sets it: no per-run figures (drawing one costs about
# a second of CPU, more than training a tiny run; the tests of figures ask for them: figures=true)
TEST_DEFAULTS = ("figures=false",)
REPO = Path(__file__).resolve().parent.parent  # the repository's root folder
# a text that a crafted results file must never bring into a report
SECRET = "ssh-rsa AAAA-this-must-never-reach-a-report-0123456789"
PHYSGRAD = str(Path(sys.executable).with_name("physgrad"))


def with_defaults(overrides) -> list[str]:
    """The overrides, with each of TEST_DEFAULTS the test did not set itself."""
    overrides = list(overrides)
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    return overrides + [d for d in TEST_DEFAULTS if d.split("=", 1)[0] not in keys]


def load(*overrides: str):
    """The composed run config of `physgrad run` with these overrides (without Hydra's own node),
    with the tests' defaults (TEST_DEFAULTS)."""
    return compose(with_defaults(overrides))


def session_folder(tmp_path_factory) -> Path:
    """The test session's own folder, shared by its pytest-xdist workers (each has its own below
    it): where a fixture computed once for the whole session keeps what the others read."""
    import os

    root = tmp_path_factory.getbasetemp()
    return root.parent if "PYTEST_XDIST_WORKER" in os.environ else root


def console(*args, check=True, **kwargs):
    """`physgrad ARGS` through the installed console script; with check, it must succeed."""
    result = subprocess.run(
        [PHYSGRAD, *args], capture_output=True, text=True, timeout=300, **kwargs
    )
    if check:
        assert result.returncode == 0, result.stderr[-3000:]
    return result


class SimulatedClock:
    """The runner's clock, advanced by the step alone: each step takes `step` seconds (the first
    `first_extra` more), every other reading 1 microsecond, so budgets, evaluation times and the
    first-step correction are exact and independent of the machine."""

    def __init__(self, monkeypatch, step=0.01, first_extra=0.0):
        import physgrad.runner

        self.now, self.step, self.extra, self.calls = 0.0, step, first_extra, 0
        monkeypatch.setattr(physgrad.runner, "clock", self)
        real = physgrad.runner.compile_training

        def compile_with_simulated_steps(*args, **kwargs):
            compiled = real(*args, **kwargs)

            def step(*step_args):
                self.now += self.step + (self.extra if self.calls == 0 else 0.0)
                self.calls += 1
                return compiled.step(*step_args)

            return dataclasses.replace(compiled, step=step)

        monkeypatch.setattr(physgrad.runner, "compile_training", compile_with_simulated_steps)

    def __call__(self):
        self.now += 1e-6
        return self.now


def scheduled_calibration() -> dict:
    """A whole calibration.json of adam (2 ms a step) and psgd_kron (2 ms, 1 ms of it its scheduled
    update, 1.03 ms a step at its floor p = 0.03, from step 4,007 on)."""
    cost = {"step_seconds": 2e-3, "median_seconds": 2.1e-3, "rounds": 30}
    scheduled = {
        "update_seconds": 1e-3,
        "advanced_seconds": 1.03e-3,
        "advanced_step": 4007,
        "floor_probability": 0.03,
    }
    return {
        "quantile": 0.2,
        "load_start": 0.5,
        "load_end": 0.6,
        "machine": {"cpu_count": 2},
        "costs": {"adam": cost, "psgd_kron": {**cost, **scheduled}},
    }


def float32_factorisation_fails(monkeypatch):
    """A stand-in for LAPACK not converging: the kernel returns NaN for float32 input, the true
    result for float64."""
    import jax.numpy as jnp

    import physgrad.optim.spectral as spectral

    real = spectral._direction

    def flaky(jac, g, kappa, tau, route="svd"):
        result, kept = real(jac, g, kappa, tau, route)
        return (result * jnp.nan if jac.dtype == jnp.float32 else result), kept

    monkeypatch.setattr(spectral, "_direction", flaky)


def plant(path: Path, kind: str, other: Path) -> None:
    """What someone else may leave where physgrad expects a file of its own: a "link" to other (made
    empty where it does not exist), a "dangling link", a "fifo", a "folder" or a "hard link" to
    other (made empty where it does not exist)."""
    import os

    if kind in ("link", "hard link") and not other.exists():
        other.write_text("")
    if kind in ("link", "dangling link"):
        path.symlink_to(other)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    elif kind == "hard link":
        os.link(other, path)
    else:
        raise ValueError(f"nothing to plant of kind {kind!r}")
