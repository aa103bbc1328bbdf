"""End-to-end layer of `physgrad check` and the output folder check: an output folder the console
script cannot write is one line on stderr with exit code 2, and `physgrad check --help` answers."""

import subprocess

import pytest


# a folder under a file in make test, one in /proc in make test-long
@pytest.mark.parametrize(
    "make_target", ["under_a_file", pytest.param("proc", marks=pytest.mark.long)]
)
def test_an_unwritable_output_folder_is_a_one_line_error(tmp_path, make_target):
    from tests.helpers import console as physgrad

    if make_target == "under_a_file":
        (tmp_path / "file.txt").write_text("not a folder")
        target = tmp_path / "file.txt" / "run"
    else:
        target = "/proc/physgrad/run"  # not writable, even for root
    for args in (
        ["run", f"hydra.run.dir={target}"],
        ["run", "-m", "optim=adam,gd", f"hydra.sweep.dir={target}"],
    ):
        result = physgrad(*args, "trainer.iterations=1", check=False)
        lines = result.stderr.strip().splitlines()
        assert (
            result.returncode == 2 and len(lines) == 1 and "cannot write results to" in lines[0]
        ), result.stderr


def test_check_command_is_wired():
    from tests.helpers import PHYSGRAD

    result = subprocess.run([PHYSGRAD, "check", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "--small" in result.stdout
