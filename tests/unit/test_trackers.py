"""Unit layer of the `logger` group: a logger entry that cannot be built is refused in one line
with exit code 2."""

import pytest

TINY = (
    "task=toy",
    "task.test_size=8",
    "trainer.batch_size=4",
    "trainer.iterations=4",
    "trainer.eval_every=2",
)


def test_a_logger_entry_that_cannot_be_built_is_one_line(tmp_path, capsys):
    from physgrad.cli import main

    with pytest.raises(SystemExit) as leaving:
        main(
            [
                "run",
                *TINY,
                "logger=tensorboard",
                "+logger.tensorboard.flush_secs=3",
                f"hydra.run.dir={tmp_path}",
            ]
        )
    assert leaving.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        len(err) == 1
        and "logger.tensorboard.flush_secs is not a setting of physgrad.trackers.TensorBoard"
        in err[0]
    )
