"""Runs as a report reads them: found under paths (or LABEL=PATH sets), without duplicates, and
labelled by scene and group.

A *scene* is a task with the problem settings that differ between its runs (task keys, unroll,
precision): one panel and one block of rows each in a report. Within a scene, a *group* is every
run with the same resolved configuration except the seed (and keys that do not change what is
computed: output paths, logging, evaluation cadence, init_from's file name): its label is the
variant plus the settings that differ between the scene's runs of that variant, e.g. ``adam
learning_rate=0.01``. The same configuration and seed found twice counts once (collect names what
it dropped). Sets of runs given as LABEL=PATH keep their label in front of the group's, so sweeps
from different days can be compared.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from physgrad.errors import UserError
from physgrad.readout import config_row
from physgrad.results import Run, find_results, read_run

# keys that never tell two runs apart: the seed (what a group pools over), files and cadences that
# do not change the computation (`seeds` does count: seeds trained together share one step time)
# (init_from is identified by the variant's "from ...")
NOT_COMPUTATION = (
    "seed",
    "overwrite",
    "figures",
    "calibrate",
    "init_from",
    "trainer.flush_seconds",
    "trainer.log_seconds",
    "trainer.eval_every",
    "trainer.eval_seconds",
)
# problem settings besides task.*: each value is its own scene
SCENE_KEYS = ("unroll", "precision")
# what the variant label already says
VARIANT_KEYS = ("task.name", "optim.name", "optim.backprop", "optim.clip")


def parse_sources(arguments: Iterable[str | Path]) -> list[tuple[str, Path]]:
    """(set label, path) per argument: a path as given (label ""), or LABEL=PATH where the whole
    argument is not itself an existing path (Hydra's job folders have '=' in their names)."""
    sources = []
    for argument in map(str, arguments):
        label, sep, rest = argument.partition("=")
        if sep and not Path(argument).exists() and label and "/" not in label:
            sources.append((label, Path(rest)))
        else:
            sources.append(("", Path(argument)))
    return sources


@dataclass
class Dropped:
    path: Path
    kept: Path
    why: str


def collect(
    arguments: Iterable[str | Path],
) -> tuple[list[Run], list[tuple[Path, str]], list[Dropped]]:
    """Every readable run under the given paths (or LABEL=PATH sets), without duplicates; (path,
    reason) for each file that is not a readable results file; and what was dropped as a duplicate.
    UserError (one line) if a path does not exist or holds no results file."""
    runs, unreadable, seen, repeated = [], [], {}, []
    for label, path in parse_sources(arguments):
        try:
            found = find_results([path])
        except FileNotFoundError as error:
            raise UserError(f"{error}: give results.h5 files or folders that hold them") from None
        if not found:
            raise UserError(f"{path}: no results.h5 under it: give the folder of a run or a sweep")
        for file in found:
            key = (label, os.path.realpath(file))  # a link loop is the reader's to refuse
            if key in seen:  # a folder and its parent both given: the same file once
                if seen[key] is not None:
                    repeated.append(Dropped(file, seen[key], "the same file, found twice"))
                    seen[key] = None  # said once
                continue
            seen[key] = file
            try:  # a link found under a folder is refused: it could point anywhere
                run = read_run(file, follow=file == Path(path))
            except ValueError as error:
                unreadable.append((file, str(error)))
                continue
            except MemoryError:
                unreadable.append((file, "too large to read into this machine's memory"))
                continue
            run.collection = label
            runs.append(run)
    runs, dropped = drop_duplicates(runs)
    return runs, unreadable, repeated + dropped


def _identity(run: Run) -> tuple:
    """What makes two files the same run: the set, every setting that changes the computation (as
    for grouping), the seed the file trained and the network it started from; a file without a
    stored configuration is only itself."""
    config = {k: v for k, v in config_row(run).items() if k not in NOT_COMPUTATION}
    if not config:
        return (str(run.path.resolve()),)
    # another start is another run
    return (
        run.collection,
        repr(sorted(config.items())),
        run.attrs.get("task"),
        run.variant,
        str(run.attrs.get("seed")),
        str(run.attrs.get("init_from", "")),
    )


def drop_duplicates(runs: list[Run]) -> tuple[list[Run], list[Dropped]]:
    """One run per configuration and seed: a completed run before any other, then the newest."""
    by_identity = defaultdict(list)
    for run in runs:
        by_identity[_identity(run)].append(run)
    kept, dropped = [], []
    for same in by_identity.values():
        same.sort(
            key=lambda r: (r.attrs.get("status") == "completed", str(r.attrs.get("finished", ""))),
            reverse=True,
        )
        kept.append(same[0])
        dropped += [Dropped(r.path, same[0].path, "same configuration and seed") for r in same[1:]]
    order = {id(run): i for i, run in enumerate(runs)}
    return sorted(kept, key=lambda r: order[id(r)]), dropped


def setting_text(value: object) -> str:
    """A setting's value in a label: six significant figures, so that close values (an Optuna
    study's learning rates) keep apart, while round ones stay short (0.01)."""
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def label_runs(runs: list[Run]) -> None:
    """Set each run's scene settings (run.setting, e.g. "poles=3") and group label (run.label, e.g.
    "old: adam learning_rate=0.01"): scene settings are the task keys, unroll and precision that
    differ between runs of the same task; group settings every other key that differs between runs
    of the same variant in the same scene (seed and NOT_COMPUTATION keys aside)."""
    configs = {
        id(run): {k: v for k, v in config_row(run).items() if k not in NOT_COMPUTATION}
        for run in runs
    }
    # the unroll length the run used (unroll=null means the scene's own, task.unroll)
    for run in runs:
        if "unroll" in run.attrs:
            configs[id(run)]["unroll"] = run.attrs["unroll"]

    def varying(members: list[Run], keys_of: Callable[[dict], Iterable[str]]) -> list[str]:
        keys = sorted({k for run in members for k in keys_of(configs[id(run)])})
        return [k for k in keys if len({repr(configs[id(run)].get(k)) for run in members}) > 1]

    def scene_key(k: str) -> bool:
        return k.startswith("task.") and k not in ("task.name", "task.batch_size")

    by_task = defaultdict(list)
    for run in runs:
        by_task[run.attrs.get("task")].append(run)
    for members in by_task.values():
        keys = varying(
            members, lambda config: [k for k in config if scene_key(k) or k in SCENE_KEYS]
        )
        for run in members:
            run.setting = " ".join(
                f"{k.removeprefix('task.')}={setting_text(configs[id(run)].get(k))}" for k in keys
            )
    by_variant = defaultdict(list)
    for run in runs:
        by_variant[(run.scene, run.variant)].append(run)
    for members in by_variant.values():
        keys = varying(
            members,
            lambda config: [
                k for k in config if not (scene_key(k) or k in SCENE_KEYS or k in VARIANT_KEYS)
            ],
        )
        for run in members:
            settings = " ".join(
                f"{k.split('.', 1)[-1]}={setting_text(configs[id(run)].get(k))}" for k in keys
            )
            run.label = " ".join(part for part in (run.variant, settings) if part)
            if run.collection:
                run.label = f"{run.collection}: {run.label}"
