"""Runs that build on earlier ones: a re-run sweep skips what completed or diverged with the same
config (resume) and sets aside a file it cannot read, and a run can start from another run's final
network (init_from)."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from physgrad.errors import UserError
from physgrad.members import NOT_RESULT_KEYS
from physgrad.results import Run, cut_short, parse_config, read_end, read_final, read_params
from physgrad.runner import Outcome

log = logging.getLogger("physgrad")


def finished_before(path: Path, config: dict, seed: int | None = None) -> Outcome | None:
    """The outcome recorded at path if that run completed or diverged with this same config
    (config: the member's, as members.comparable_config gives it; a sweep being re-run) and, given
    the member's seed, on that seed, with its rows whole (results.cut_short): both are results the
    same config gives again; interrupted, failed and refused runs run again, as do a file copied
    from another seed or cut short (the checks a study's evaluation makes, so that the two never
    disagree). The stored config is compared as data: nothing in it is resolved (a file from
    elsewhere may hold anything)."""
    if not path.exists():
        return None
    try:
        attrs, last_eval, last_train = read_end(path)
        stored = parse_config(attrs.get("config", ""))
    except ValueError:
        return None
    if (seed is not None and attrs.get("seed") != seed) or cut_short(attrs, last_train):
        return None
    for key in NOT_RESULT_KEYS:
        stored.pop(key, None)
    status = attrs.get("status")
    if status not in ("completed", "diverged") or stored != config:
        return None
    final = {k: float(v) for k, v in last_eval.items() if k not in ("iteration", "wall_time")}
    why = f" ({attrs['reason']})" if status == "diverged" and attrs.get("reason") else ""
    return Outcome(
        status,
        f"already {status}{why}: skipped (overwrite=true runs it again)",
        int(attrs.get("iterations", 0)),
        float(attrs.get("train_seconds", 0)),
        final,
    )


def start_from(path: str, params: Any, task_name: str) -> tuple[Any, dict]:
    """The final network of the run at path, in the structure and dtype of params, and attributes
    that record where it came from; UserError (one line) if it is missing or does not fit this
    scene's network."""
    if not Path(path).is_file():
        raise UserError(f"init_from={path}: no such file: give the results.h5 of an earlier run")
    try:
        flat = read_params(path, follow=True)  # the user's own path
        # attributes only, not the curves
        source = Run(Path(path), read_final(path, follow=True)[0], {}, {})
    except ValueError as error:
        raise UserError(f"init_from={error}") from None
    own, unravel = ravel_pytree(params)
    if flat.shape != own.shape or source.attrs.get("task") != task_name:
        raise UserError(
            f"init_from={path}: that run trained a {source.attrs.get('task')} network with "
            f"{flat.size} "
            f"parameters, this one is {task_name} with {own.size}: use a run of the same scene"
        )
    status = source.attrs.get("status")
    if status != "completed":
        # a network from a run that diverged, was interrupted or is still running is allowed (to
        # go on from where it stopped), but it is not the end of a finished run: say so, and keep it
        import logging

        logging.getLogger("physgrad").warning(
            "init_from=%s: that run ended %s, not completed: starting from its last network",
            path,
            status,
        )
    attrs = {
        "init_from": str(path),
        "init_variant": source.variant,
        "init_iterations": int(source.attrs.get("iterations", 0)),
        "init_train_seconds": float(source.attrs.get("train_seconds", 0.0)),
    }
    return unravel(jnp.asarray(flat, own.dtype)), attrs


def set_aside_unreadable(path: Path) -> Path | None:
    """A results.h5 that cannot be read (damaged, or not a physgrad file) is renamed, never deleted,
    so the job can run again; returns the new name."""
    if not path.exists():
        return None
    try:
        read_final(path)
        return None
    except ValueError:
        aside = path.with_name(f"{path.name}.unreadable-{time.strftime('%Y%m%dT%H%M%S')}")
        os.replace(path, aside)
        log.warning("%s could not be read: set aside as %s, the job runs again", path, aside.name)
        return aside
