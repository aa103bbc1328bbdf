"""End-to-end layer of the trackers' logging set-up: in a pytest run of its own, Hydra setting
logging up under capsys after absl was imported leaves the later tests' capture open."""

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
