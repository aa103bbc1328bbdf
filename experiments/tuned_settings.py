"""The tuned settings behind the claims' and the leaderboard's verdicts, from the kept evidence
(each tuning study's `tuned` and `trials`, experiments/study_runs.tuned_trials): what each study's
tuning chose per variant, and where a choice sits in the outer tenth of the values its trials
tried."""

from __future__ import annotations

import math
from pathlib import Path

from evidence import read_json  # experiments/

from physgrad.readout import fmt

EDGE = 0.1  # the outer tenth of the log span the trials tried


def tuned_table(root: Path) -> str:
    """A markdown table: per kept study and variant, each tuning study's tuned values and the span
    its trials tried, flagged where a tuned value lies in the outer tenth of that span (the best
    setting may lie beyond it); the kept studies tuned before the evidence kept their tuning
    named in one line after it."""
    rows, unrecorded = [], []
    for path in sorted(root.glob("*.json")):
        if path.name.endswith(".calibration.json"):
            continue
        try:
            record = read_json(path)
        except (OSError, ValueError):
            continue
        studies = record.get("tuning_studies") if isinstance(record, dict) else None
        if not isinstance(studies, dict):
            continue
        by_variant: dict[str, list[str]] = {}
        for k in sorted(studies, key=lambda key: int(key) if str(key).isdigit() else 0):
            for variant, said in tuned_in_study(studies[k]).items():
                by_variant.setdefault(variant, []).append(f"study {k}: {said}")
        rows += [f"| {path.stem} | {v} | {'; '.join(t)} |" for v, t in by_variant.items()]
        if not by_variant and _tuned(record) and not path.stem.endswith("-preset"):
            unrecorded.append(path.stem)
    missing = (
        f"not recorded for {', '.join(unrecorded)} (kept before the evidence kept its tuning; each "
        "tuning study's compare.md lists it)"
    )
    if not rows:
        said = missing if unrecorded else "none of these studies was tuned"
        return f"\nTuned settings: {said}.\n"
    return (
        "\nTuned settings, per study, variant and tuning study (the setting of lowest validation "
        "loss among its trials, and the span its trials tried; the presets are in conf/optim and "
        "conf/tuning); *edge*: in the outer tenth of that span, so the best may lie beyond "
        "it:\n\n"
        "| study | variant | tuned |\n|---|---|---|\n"
        + "\n".join(rows)
        + "\n"
        + (f"\nTuned settings {missing}.\n" if unrecorded else "")
    )


def tuned_in_study(study: object) -> dict[str, str]:
    """variant -> what one tuning study's record (its `tuned` and `trials`) says it chose: each
    tuned key as key=value with the span its trials tried, *edge* where the value lies in the
    outer tenth of that span, "untuned" where every trial's validation loss was the same (a rule
    that takes no step within the budget); {} for a record without them."""
    study = study if isinstance(study, dict) else {}
    trials = study.get("trials") if isinstance(study.get("trials"), list) else []
    tuned = study.get("tuned") if isinstance(study.get("tuned"), dict) else {}
    found = {}
    for variant, values in sorted(tuned.items()):
        if not isinstance(values, dict):
            continue
        losses = [
            t.get("validation_loss")
            for t in trials
            if isinstance(t, dict) and t.get("variant") == variant
        ]
        count = len(losses)
        recorded = all(isinstance(v, (int, float)) and math.isfinite(v) for v in losses)
        if count > 1 and recorded and len(set(losses)) == 1:  # no trial told the others apart
            found[str(variant)] = f"untuned: its {count} trials tied (the first one's settings ran)"
            continue
        said = []
        for key, value in sorted(values.items()):
            tried = [
                float(t[key])
                for t in trials
                if isinstance(t, dict) and t.get("variant") == variant and key in t
            ]
            span = f" of [{fmt(min(tried))}, {fmt(max(tried))}]" if tried else ""
            said.append(f"{key}={fmt(float(value))}{span}{_edge(float(value), tried)}")
        found[str(variant)] = ", ".join(said)
    return found


def at_the_edge(studies: dict, variant: str) -> int:
    """How many of a kept record's tuning studies (its `tuning_studies`) tuned a value of the
    variant in the outer tenth of the log span its trials tried (tuned_in_study's *edge*)."""
    return sum(
        "*edge*" in tuned_in_study(study).get(variant, "")
        for study in (studies.values() if isinstance(studies, dict) else ())
    )


def _tuned(record: dict) -> bool:
    """Whether a kept study was tuned (trials per variant in its record), not presets alone."""
    trials = record.get("trials")
    return isinstance(trials, (int, float)) and trials > 0


def _edge(value: float, tried: list[float]) -> str:
    """ " *edge*" where value lies in the outer tenth of the log span of tried (three or more
    positive values), "" otherwise."""
    tried = [t for t in tried if t > 0 and math.isfinite(t)]
    if len(tried) < 3 or not value > 0 or min(tried) == max(tried):
        return ""
    low, high = math.log(min(tried)), math.log(max(tried))
    where = (math.log(value) - low) / (high - low)
    return " *edge*" if where < EDGE or where > 1 - EDGE else ""
