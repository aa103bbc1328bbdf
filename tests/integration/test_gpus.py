"""Integration layer of one GPU per job: the GPUs read from CUDA_VISIBLE_DEVICES, one or none
changing nothing, a comparison pinning itself and running its jobs side by side (in turn, with a
warning, without joblib), and lock folders or files not the user's own leaving a job unpinned."""

import os

import pytest

from physgrad import gpus


@pytest.mark.parametrize(
    "listed, expected",
    [
        ("0,1,2", ["0", "1", "2"]),
        ("", []),
        ("-1", []),
        ("0, 2,-1,3", ["0", "2"]),  # CUDA stops at the first invalid entry
        ("GPU-aa,GPU-bb", ["GPU-aa", "GPU-bb"]),
        ("3", ["3"]),
    ],
)
def test_visible_gpus_read_cuda_visible_devices(listed, expected):
    assert gpus.visible_gpus({"CUDA_VISIBLE_DEVICES": listed}) == expected


def test_one_gpu_or_none_changes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    for listed in ("0", "", "-1"):
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", listed)
        assert gpus.claim_gpu() is None
        assert os.environ["CUDA_VISIBLE_DEVICES"] == listed


def test_a_comparison_pins_itself_and_its_jobs_get_the_environment_it_started_with(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,5")
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    monkeypatch.setattr(gpus, "_original", {})
    assert gpus.pin_this_process() == 2
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "4"
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    from physgrad.comparison.jobs import job_environment

    env = job_environment()
    assert env["CUDA_VISIBLE_DEVICES"] == "4,5" and "XLA_PYTHON_CLIENT_PREALLOCATE" not in env


def test_several_gpus_run_a_comparisons_jobs_side_by_side_unless_a_launcher_is_chosen():
    assert gpus.local_launcher_args([], 1) == []
    assert gpus.local_launcher_args([], 0) == []
    assert gpus.local_launcher_args(["hydra.verbose=true"], 4) == [
        "hydra.verbose=true",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=4",
    ]
    chosen = ["hydra/launcher=submitit_slurm"]
    assert gpus.local_launcher_args(chosen, 4) == chosen


def test_without_the_joblib_plugin_the_jobs_run_in_turn_with_a_warning(monkeypatch, caplog):
    import importlib.util
    import logging

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == "hydra_plugins.hydra_joblib_launcher" else real(name, *a),
    )
    with caplog.at_level(logging.WARNING, logger="physgrad.gpus"):
        assert gpus.local_launcher_args([], 4) == []
    assert "physgrad[launchers]" in caplog.text


def test_a_lock_folder_or_file_that_is_not_the_users_own_leaves_the_job_unpinned(
    tmp_path, monkeypatch, caplog
):
    """Without a runtime folder the GPU locks live in the temporary folder, which others can write
    to: a lock folder that is a link, no folder, another user's or open to others, a lock file that
    is a link, or a folder that cannot be made, is a warning and an unpinned job (nothing written
    through a link), never a traceback before the job's own error handling; the user's own folder
    gives a GPU."""
    import shutil

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    folder, elsewhere = tmp_path / f"physgrad-gpus-{os.getuid()}", tmp_path / "elsewhere"
    elsewhere.mkdir()

    def unpinned(why: str) -> None:
        monkeypatch.setattr(gpus, "_held", [])
        caplog.clear()
        assert gpus.claim_gpu() is None, why
        assert os.environ["CUDA_VISIBLE_DEVICES"] == "0,1", why
        assert why in caplog.text and "not pinned" in caplog.text, caplog.text
        assert not list(elsewhere.iterdir())

    folder.symlink_to(elsewhere)
    unpinned("a link")
    folder.unlink()
    folder.write_text("")
    unpinned("not a folder")
    folder.unlink()
    folder.mkdir(mode=0o700)
    folder.chmod(0o777)
    unpinned("open to other users (mode 777")
    folder.chmod(0o700)
    if os.getuid() == 0:  # root can give the folder to another user, as another user's would be
        os.chown(folder, 12345, 12345)
        unpinned("owned by user 12345")
        os.chown(folder, 0, 0)
    (folder / "0.lock").symlink_to(elsewhere / "0.lock")
    unpinned("cannot be used")
    shutil.rmtree(folder)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "no such folder"))
    unpinned("No such file or directory")

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    held = []
    monkeypatch.setattr(gpus, "_held", held)
    try:
        assert gpus.claim_gpu() == "0" and os.environ["CUDA_VISIBLE_DEVICES"] == "0"
    finally:
        for fd in held:
            os.close(fd)
