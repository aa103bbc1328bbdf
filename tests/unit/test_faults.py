"""Unit layer of faults in the results writer: a full disk at any of its writes is one line and
leaves the last good file (repeated PHYSGRAD_FAULT_REPEATS times by `make test-faults`)."""

import errno
import os

import h5py
import numpy as np

from physgrad.errors import ResultsWriteError
from physgrad.results import ResultsWriter, read_run

REPEATS = int(os.environ.get("PHYSGRAD_FAULT_REPEATS", "1"))  # the long form multiplies every count


def test_a_full_disk_at_any_write_is_one_line_and_leaves_the_last_good_file(tmp_path, monkeypatch):
    import physgrad.results as results

    real = h5py.File
    flushes = 5 * REPEATS
    for failing_write in range(1, flushes + 3):  # the first write, each flush, and the final one
        path = tmp_path / f"{failing_write}" / "results.h5"
        writes = []

        def file(name, mode="r", **kwargs):
            if mode == "w":
                writes.append(name)
                if len(writes) == failing_write:
                    raise OSError(errno.ENOSPC, "No space left on device")
            return real(name, mode, **kwargs)

        monkeypatch.setattr(results.h5py, "File", file)
        try:
            writer = ResultsWriter(path, {"task": "toy", "optim": "adam", "seed": 0})
            for i in range(flushes):
                writer.append("train", {"iteration": i, "loss": 1.0})
                writer.flush()
            writer.finish("completed")
            raise AssertionError("the full disk went unnoticed")
        except ResultsWriteError as error:
            assert str(error) == f"cannot write {path}: No space left on device"
        finally:
            monkeypatch.setattr(results.h5py, "File", real)
        if (
            failing_write > 1
        ):  # the file of the last good write is intact: write k holds rows 0 .. k - 2
            run = read_run(path)
            assert run.train.get("iteration", np.empty(0)).tolist() == list(
                range(failing_write - 2)
            )
            assert run.attrs["status"] == "running"
        assert not list(path.parent.glob(".*.tmp"))
