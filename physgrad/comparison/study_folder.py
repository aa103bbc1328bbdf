"""The study folder: which study it holds (study.json: the command, its config folder, the
protocol and a fingerprint of the composed settings), so that a folder holding another study, or
this one under other defaults, is refused rather than resumed."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from physgrad.errors import UserError

# what does not make a study another: its folder, Hydra's settings, the variant the others are
# compared with (the same runs, read again), and the number of trials and of tuning studies (a
# finished study given more trials tunes on from where it stopped: the Halton points of n trials
# begin with those of fewer; given more studies, it adds them)
NOT_THE_STUDY = ("compare.dir", "compare.trials", "compare.studies", "compare.baseline", "hydra")
# how a study draws its trial points and seeds; a folder of another protocol is another study.
# 2: each tuning study its own evaluation seeds and randomly shifted trial points (1, unrecorded:
# the studies shared their evaluation seeds and scrambled the points within their cells)
PROTOCOL = 2


# --- the study folder
# --------------------------------------------------------------------------------------


def same_study(record: dict | None) -> tuple[list | None, object] | None:
    """The parts of a study.json record that identify the study."""
    if not isinstance(record, dict):
        return None
    overrides = record.get("overrides")
    return (
        [o for o in overrides if not str(o).startswith(NOT_THE_STUDY)]
        if isinstance(overrides, list)
        else None,
        record.get("config_dir"),
        record.get("protocol", 1),
    )


def configuration_of(configs: list) -> str:
    """A fingerprint of what the variants' scene and rules are (their composed task, optim and
    precision settings): the same command given other defaults (physgrad upgraded, a config file
    edited) is another study, whose earlier tuning and runs must not be resumed."""
    from omegaconf import OmegaConf

    text = json.dumps(
        [
            OmegaConf.to_container(
                OmegaConf.masked_copy(config, ["task", "optim", "precision"]), resolve=False
            )
            for config in configs
        ],
        sort_keys=True,
        default=str,
    )
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def default_folder(
    overrides: list[str], config_dir: str | None, task: str, configuration: str = ""
) -> Path:
    text = json.dumps(
        [
            sorted(o for o in overrides if not o.startswith(NOT_THE_STUDY)),
            os.path.abspath(config_dir) if config_dir else None,
            PROTOCOL,  # a study of another protocol gets another folder
            *([configuration] if configuration else []),  # so do other defaults
        ]
    )
    return Path("outputs") / "compare" / f"{task}-{hashlib.sha1(text.encode()).hexdigest()[:8]}"


def record_study(
    folder: Path, overrides: list[str], config_dir: str | None, configuration: str = ""
) -> None:
    """The study's command in folder/study.json; a folder that holds another study is a UserError
    (the same study given more trials is the same study: its record is updated), and so is one
    that holds this command run with another configuration (configuration_of; a record without
    one, written before it was kept, cannot be checked)."""
    record = {
        "overrides": [o for o in overrides if not o.startswith(("compare.dir", "hydra"))],
        "config_dir": os.path.abspath(config_dir) if config_dir else None,
        "protocol": PROTOCOL,
        **({"configuration": configuration} if configuration else {}),
    }
    from physgrad.files import load_json, read_own_file, replace_file

    stored = folder / "study.json"
    if os.path.lexists(stored):
        try:
            data = read_own_file(stored, 1 << 20)
        except (OSError, ValueError) as error:
            raise UserError(f"{error}; remove it or give another compare.dir") from None
        try:
            before = load_json(data)
        except ValueError:
            before = None
        stored_study, this_study = same_study(before), same_study(record)
        if stored_study and stored_study[:2] == this_study[:2] and stored_study != this_study:
            raise UserError(
                f"{folder} holds this study run by an earlier physgrad, whose tuning studies "
                "shared their evaluation seeds: give another compare.dir (or move the folder "
                "away) to run it with independent studies"
            )
        if stored_study != this_study:
            raise UserError(
                f"{folder} holds another study ({_stored_command(before)}): give another "
                "compare.dir"
            )
        if before.get("configuration") not in (None, record.get("configuration")):
            raise UserError(
                f"{folder} holds this study run with other settings of its scene or rules (a "
                "changed default: physgrad upgraded, or a config file edited): give another "
                "compare.dir (or move the folder away) to run it again"
            )
    if not stored.exists() or before != record:  # new, or the same study given more trials
        replace_file(stored, (json.dumps(record, indent=1) + "\n").encode())


def _stored_command(record: object) -> str:
    """What a study.json (data from whoever wrote the folder) says its command was, safe to print:
    its overrides joined, each as text with control characters replaced, cut to 300 characters;
    "not a study record" for anything else."""
    from physgrad.files import clean_text

    overrides = record.get("overrides") if isinstance(record, dict) else None
    if not isinstance(overrides, list):
        return "its study.json is not a study record"
    return clean_text(" ".join(str(o) for o in overrides), 300)
