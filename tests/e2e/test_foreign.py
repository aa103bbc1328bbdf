"""End-to-end layer of files from somebody else: YAML alias and interpolation bombs in a results
file, a job's overrides and a sweep manifest are refused or left unresolved, and the report goes
on, in a child process under a time and memory cap."""

import subprocess
import sys
import textwrap

import pytest

from tests.unit.test_foreign import (
    CONFIG,
    good_run,
    rewrite,
    set_attr,
)

BOMB_LEVELS = 9  # each level refers to the one below ten times: 10^9 leaves once expanded


def alias_bomb() -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, BOMB_LEVELS + 1)]
    return "\n".join(lines) + "\n"


def interpolation_bomb() -> str:
    text = "x: ${oc.env:HOME}\n"
    for i in range(1, 30):
        text += f"x{i}: ${{x{i - 1 if i > 1 else ''}}}${{x{i - 1 if i > 1 else ''}}}\n"
    return text


def run_capped(code: str, seconds: int = 60, memory: int = 2 << 30) -> subprocess.CompletedProcess:
    """code in a child process that caps its own address space (start-up's 3 GiB plus `memory`)
    first, within `seconds`."""
    cap = memory + (3 << 30)
    preamble = f"import resource\nresource.setrlimit(resource.RLIMIT_AS, ({cap}, {cap}))\n"
    return subprocess.run(
        [sys.executable, "-c", preamble + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=seconds,
    )


# make test-long and make test-faults: each bomb under a time and memory cap
@pytest.mark.long
@pytest.mark.parametrize("bomb", ["alias", "interpolation"])
def test_config_bombs_are_refused_in_bounded_time_and_memory(tmp_path, bomb):
    good_run(tmp_path / "good", seed=1)
    path = good_run(tmp_path / "job")
    rewrite(path, set_attr("config", alias_bomb() if bomb == "alias" else interpolation_bomb()))
    (tmp_path / "job" / ".hydra").mkdir()
    (tmp_path / "job" / ".hydra" / "overrides.yaml").write_text(alias_bomb())
    (tmp_path / "jobs.yaml").write_text(alias_bomb() + "jobs: *a9\n")
    done = run_capped(f"""
        from pathlib import Path
        from omegaconf import OmegaConf
        from physgrad.report import write_report
        from physgrad.members import comparable_config
        from physgrad.resume import finished_before
        from physgrad.sweeps import job_folders, read_manifest
        folder = Path({str(tmp_path)!r})
        cfg = OmegaConf.create({CONFIG!r})
        assert finished_before(folder / "job" / "results.h5", comparable_config(cfg)) is None
        assert read_manifest(folder) is None and job_folders(folder) == {{}}
        body = write_report([folder], out_dir=folder / "report")
        print(body)
    """)
    assert done.returncode == 0, done.stderr[-2000:]
    if bomb == "alias":
        assert "unreadable: " in done.stdout and "aliases" in done.stdout
    else:  # text, never resolved: the run is readable and its config holds the ${...} as written
        assert "unreadable" not in done.stdout
