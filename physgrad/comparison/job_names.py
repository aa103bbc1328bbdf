"""How a study names its jobs: <phase>_[st<k>_]v<index>[_t<trial>|_s<seed>], read back by the
variant index and tuning study they hold."""

from __future__ import annotations

import re


def variant_index(job: str) -> int:
    """The variant index a job name holds (tune_v2_t003, tune_st1_v0_t000-007, eval_v1_s3: v<index>
    after the phase and study)."""
    return int(re.match(r"^[a-z]+_(?:st\d+_)?v(\d+)", job).group(1))


def study_prefix(study: int) -> str:
    """What a job name of tuning study k starts with after its phase: nothing for the first study
    (a study folder written before repeated studies reads as its first), st<k>_ for the others."""
    return "" if study == 0 else f"st{study}_"


def tuning_study_of(job: str) -> int | None:
    """The tuning study (1, 2, ...) of an evaluation job's name (eval_v0, eval_st1_v0_s3), or of its
    folder's (+compare_job=eval_st1_v0); None for another name."""
    found = re.fullmatch(r"eval_(?:st(\d+)_)?v\d+(?:_s\d+)?", job.rpartition("=")[2])
    return None if found is None else int(found.group(1) or 0) + 1
