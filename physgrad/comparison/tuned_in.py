"""Settings tuned in another study (compare.tuned_in): each variant's best trial per tuning study,
read as data from that study's trials.csv, so that a study evaluates the same settings at another
budget (a longer one: is a verdict the budget's?) without tuning them again."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from physgrad.comparison.points import is_whole
from physgrad.comparison.spec import Variant
from physgrad.errors import UserError

TRIALS_LIMIT = 16 << 20  # a study's trials.csv is kilobytes; beyond this it is not one


def tuned_in(folder: Path, variants: list[Variant], count: int) -> list[dict[str, dict]]:
    """Per tuning study k < count, each variant's best settings in folder/trials.csv by tuning's
    own rule: among its COMPLETE trials with a finite validation loss the lowest, the first such
    trial where several tie; {} (its configured settings) where every trial diverged. Each value
    must be one of the variant's search space (a number inside the range, a whole number for a
    count). UserError (one line) where the file is not such a table or lacks a variant or a
    tuning study, or a value lies outside the variant's space."""
    from physgrad.files import read_own_file

    path = Path(folder) / "trials.csv"
    try:  # a folder the user named: followed if a link, never a FIFO or a device
        text = read_own_file(path, TRIALS_LIMIT, follow=True).decode()
        rows = list(csv.DictReader(io.StringIO(text)))
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise UserError(
            f"compare.tuned_in={folder}: no finished study's trials.csv there ({error}); give "
            "the folder of a finished study, or finish that study first (its command resumes it)"
        ) from None
    best = []
    for k in range(count):
        chosen = {}
        for variant in variants:
            trials = [
                r for r in rows if r.get("variant") == variant.name and r.get("study") == str(k)
            ]
            if not trials:
                raise UserError(
                    f"compare.tuned_in={folder}: its trials.csv has no trial of {variant.name} in "
                    f"tuning study {k}: give a study of the same variants and tuning studies"
                )
            chosen[variant.name] = _best(trials, variant, folder)
        best.append(chosen)
    return best


def _best(trials: list[dict], variant: Variant, folder: Path) -> dict:
    """The settings of the best of one variant's trials (tuned_in's rule), checked against its
    search space."""
    done = []
    for row in trials:
        loss = _number(row.get("validation_loss"))
        if row.get("state") == "COMPLETE" and math.isfinite(loss):
            done.append((loss, _number(row.get("trial")), row))
    if not done:
        return {}
    _, _, row = min(done, key=lambda d: (d[0], d[1]))
    settings = {}
    for key, (low, high) in variant.space.items():
        value = _number(row.get(key))
        if not low <= value <= high or (is_whole((low, high)) and value != round(value)):
            raise UserError(
                f"compare.tuned_in={folder}: {variant.name}'s tuned {key}={row.get(key)!r} is not "
                f"inside its search space [{low:g}, {high:g}]: give a study tuned over the same "
                "spaces (the same compare.knobs and compare.search)"
            )
        settings[key] = int(round(value)) if is_whole((low, high)) else value
    return settings


def _number(text: object) -> float:
    try:
        return float(str(text))
    except ValueError:
        return math.nan
