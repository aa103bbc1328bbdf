"""What a variant of a study is tuned over: its learning rate over its rule family's range, the
rule's own knobs where the study asks for them, the scene's tuning file's ranges and the command
line's, each log-uniform; over whole numbers for a setting whose preset is one
(docs/protocol.md)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from physgrad.errors import UserError

if TYPE_CHECKING:
    from omegaconf import DictConfig


def learning_rate_key(optim_cfg: DictConfig) -> str | None:
    """The optim key compare tunes: learning_rate, or learning_rate.init_value where the rate is a
    schedule (e.g. _target_: optax.exponential_decay with init_value: the schedule's shape is kept,
    its scale tuned); None if there is neither."""
    rate = optim_cfg.get("learning_rate")
    if rate is None:
        return None
    if hasattr(rate, "keys"):
        return "learning_rate.init_value" if "init_value" in rate else None
    return "learning_rate"


def search_space(cfg: DictConfig, search: dict, knobs: bool = False) -> dict:
    """The tuned optim keys of a variant with their log-uniform ranges: its learning rate over its
    rule family's range (physgrad.optim.capabilities); with knobs, the rule's own knobs over their
    declared ranges (Capabilities.knobs); then every key of the scene's tuning file's `search`
    (conf/tuning/<task>_<optim>.yaml: the ranges this rule is tuned over on this scene), then
    every key of search (compare.search), each where the variant's optim has it. A key other than
    the learning rate whose preset is a whole number (L-BFGS's memory, SOAP's preconditioning
    frequency) is searched over the whole numbers of its range (ints: points.is_whole); UserError
    if the range holds none from 1 up."""
    optim_cfg = cfg.optim
    rate = learning_rate_key(optim_cfg)
    if rate is None:
        raise UserError(
            f"optim={optim_cfg.get('name')} has no learning_rate to tune (a number, or a schedule "
            "with init_value): add one to its YAML, or compare it untuned (compare.tune=false)"
        )
    from omegaconf import OmegaConf

    from physgrad.optim.capabilities import capabilities  # JAX: not for compare --help (2.2 CPU-s)

    kind = capabilities(optim_cfg)
    space = {rate: kind.search_range}
    if knobs:
        space |= {key: (low, high) for key, low, high in kind.knobs if key in optim_cfg}
    declared = cfg.get("search")
    declared = OmegaConf.to_container(declared) if OmegaConf.is_config(declared) else {}
    for key, bounds in declared.items():
        where = (
            f"search.{key} (the tuning file of task={cfg.task.get('name')}, "
            f"optim={optim_cfg.get('name')})"
        )
        if not (
            isinstance(bounds, list)
            and len(bounds) == 2
            and all(isinstance(b, (int, float)) and not isinstance(b, bool) for b in bounds)
            and 0 < bounds[0] < bounds[1] < math.inf
        ):
            raise UserError(f"{where} must be [low, high] with 0 < low < high, not {bounds}")
        if key in optim_cfg:
            space[rate if key == "learning_rate" else key] = (float(bounds[0]), float(bounds[1]))
    for key, bounds in search.items():
        if key in optim_cfg:
            space[rate if key == "learning_rate" else key] = bounds
    counts = {key for key in space if key != rate and _counts(optim_cfg.get(key))}
    return {
        key: _whole(key, bounds, optim_cfg) if key in counts else bounds
        for key, bounds in space.items()
    }


def _counts(preset: object) -> bool:
    return isinstance(preset, int) and not isinstance(preset, bool)


def _whole(key: str, bounds: tuple, optim_cfg: DictConfig) -> tuple[int, int]:
    """bounds narrowed to the whole numbers inside them, as ints."""
    low, high = max(1, math.ceil(bounds[0])), math.floor(bounds[1])
    if low > high:
        raise UserError(
            f"optim={optim_cfg.get('name')}'s {key} is a whole number ({optim_cfg.get(key)}) and "
            f"its range [{bounds[0]:g}, {bounds[1]:g}] holds none from 1 up: widen it"
        )
    return low, high
