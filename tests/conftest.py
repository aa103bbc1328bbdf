import atexit
import os
import shutil
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One persistent compilation cache for the whole test session, this process and every `physgrad` it
# starts: the tests build the same steps, evaluations and data generators many times over (every
# variant of a scene shares its evaluation; each subprocess would compile its eager operations
# again), and a cached executable is the same code, so results are unchanged. About a third of the
# suite's time on 2 cores. A cache folder given from outside (.ci/run gives make test and make
# test-long one) is used and kept.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="physgrad-test-jax-cache-")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

# Generated datasets (the Kuramoto-Sivashinsky trajectories) go to a cache of the test session,
# never the user's
if "PHYSGRAD_CACHE" not in os.environ:
    _data = tempfile.mkdtemp(prefix="physgrad-test-data-")
    atexit.register(shutil.rmtree, _data, ignore_errors=True)
    os.environ["PHYSGRAD_CACHE"] = _data

import sys  # noqa: E402

import absl.logging  # noqa: E402
import jax  # noqa: E402
import pytest  # noqa: E402

# absl's log handler (optax imports absl) closes its stream when logging shuts handlers down, unless
# that stream is the current sys.stderr or sys.stdout. Created here, its stream would be pytest's
# capture file; a test that runs Hydra (whose logging set-up shuts every handler down) under capsys,
# when sys.stderr is another object, would then close pytest's capture file, and every later test
# of the worker errors with "I/O operation on closed file". The interpreter's own stderr is never
# closed.
absl.logging.get_absl_handler().python_handler.stream = sys.__stderr__


@pytest.fixture(autouse=True)
def default_precision():
    """Every test starts in JAX's default precision (float32), whatever the test before it in the
    same worker left set (a run with precision=64 sets float64 for its process, as it must)."""
    jax.config.update("jax_enable_x64", False)
    yield


@pytest.fixture
def x64():
    """float64 for the duration of one test (finite differences and closed forms need it)."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", previous)


# Fixtures that tests of more than one layer use


@pytest.fixture
def in_example(monkeypatch):
    """The working directory of a user of examples/custom_scene/: its folder (pendulum.py is
    importable from there)."""
    from tests.helpers import REPO

    example = REPO / "examples" / "custom_scene"
    monkeypatch.chdir(example)
    monkeypatch.syspath_prepend(str(example))


@pytest.fixture
def report_figures_skipped(monkeypatch):
    """write_report without its figures, for tests of what a report reads and writes besides them
    (matplotlib's layout is most of a small report's time): the runs each call would have drawn
    are recorded instead. The figures have tests of their own."""
    import physgrad.report_figures

    drawn = []
    monkeypatch.setattr(
        physgrad.report_figures, "write_figures", lambda runs, *args: drawn.append(runs) or []
    )
    return drawn


@pytest.fixture
def secret_file(tmp_path):
    """A file that a crafted results file must never read into a report (its text: SECRET)."""
    import numpy as np

    from tests.helpers import SECRET

    path = tmp_path / "id_rsa"
    path.write_bytes(np.frombuffer(SECRET.encode().ljust(24 * 8, b"x"), dtype=np.uint8).tobytes())
    return path


@pytest.fixture
def studies(monkeypatch):
    """experiments/claims.py and regime_map.py reading fake studies: by folder name, or by the
    whole folder path where one is given (two profiles' folders of one study name)."""
    from pathlib import Path

    from tests.helpers import REPO

    sys.path.insert(0, str(REPO / "experiments"))
    import claims
    import regime_map

    found = {}

    def read_study(folder):
        return found.get(str(folder), found.get(Path(folder).name))

    for module in (claims, regime_map):
        monkeypatch.setattr(module, "read_study", read_study)
    monkeypatch.setattr(claims, "study_protocol", lambda folder: (8, 3, 10))
    return found
