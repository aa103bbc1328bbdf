"""End-to-end layer (the console script in subprocesses) of the tests of:
The `logger` group: TensorBoard, MLflow and Weights & Biases (offline) receive each results file
of a job as one run, read back here with the libraries' own readers (W&B's offline log with a reader
of its record format); a failing tracker is a warning, never the run."""

from tests.helpers import REPO


def test_hydra_under_capsys_leaves_pytests_capture_open_after_absl_was_imported(tmp_path):
    """The order that broke a CI run: absl imported while pytest captures the output, then a test
    under capsys sets logging up as Hydra does (dictConfig shuts every handler down). With the
    suite's conftest every later test still runs; without it, they all error."""
    import shutil
    import subprocess
    import sys

    (tmp_path / "test_order.py").write_text(
        "import logging.config\n\n"
        "def test_import():\n    import absl.logging  # noqa: F401\n\n"
        "def test_set_up(capsys):\n    logging.config.dictConfig({'version': 1})\n\n"
        "def test_later():\n    pass\n"
    )
    shutil.copy(REPO / "tests" / "conftest.py", tmp_path / "conftest.py")
    ran = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_order.py"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert ran.returncode == 0 and "3 passed" in ran.stdout, ran.stdout[-2000:] + ran.stderr[-2000:]
