"""The papers' claims from experiments/conf/claims.yaml: each claim's name, the paper's statement
and where, its parts (physgrad.claim's Lower, Close, Grows, Stalls, Reaches), how the comparison
departs from the paper's, and the paper's budget."""

from __future__ import annotations

from pathlib import Path

import yaml
from studies import CONF  # experiments/

from physgrad.claim import Claim, Close, Grows, Lower, Reaches, Stalls
from physgrad.errors import UserError

PART_KINDS = {"lower": Lower, "close": Close, "grows": Grows, "stalls": Stalls, "reaches": Reaches}


def _part(entry: dict) -> object:
    """A claim's part from its entry: its kind as the key of its study (grows: [easy, hard]), then
    its own fields (physgrad.claim)."""
    (kind,) = set(entry) & set(PART_KINDS)
    rest = {k: v for k, v in entry.items() if k != kind}
    if kind == "grows":
        return Grows(*entry[kind], **rest)
    return PART_KINDS[kind](entry[kind], **rest)


def load_claims(path: Path = CONF / "claims.yaml") -> tuple[Claim, ...]:
    """The claims from their YAML file; anything else is a UserError (one line)."""
    try:
        return tuple(
            Claim(**{**entry, "parts": tuple(_part(p) for p in entry["parts"])})
            for entry in yaml.safe_load(path.read_text())["claims"]
        )
    except (KeyError, TypeError, ValueError) as error:
        raise UserError(f"{path}: {type(error).__name__}: {error}") from None


CLAIMS = load_claims()
