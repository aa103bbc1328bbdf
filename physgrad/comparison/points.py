"""The trial points of the tuning studies: shifted Halton points in the unit cube, mapped
log-uniformly onto each variant's search space, the same for every variant of a study, and
interleaved between the studies of one design (docs/protocol.md, "Points that interleave")."""

from __future__ import annotations

import math

import numpy as np


def is_rate_key(key: str) -> bool:
    """learning_rate or learning_rate.init_value (search_space.learning_rate_key): the key every
    variant tunes, whatever its rule family."""
    return key.split(".")[0] == "learning_rate"


def point_dimensions(spaces: list[dict]) -> list[str]:
    """The coordinates of a study's trial points: the learning rate first (whichever key holds it),
    then every other search key of any variant, sorted. A variant's key keeps its coordinate
    whatever keys the others have, so a search key cannot move another key's points."""
    others = sorted({key for space in spaces for key in space if not is_rate_key(key)})
    return ["learning_rate", *others]


HALTON_BASES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37)  # scipy's Halton: the d-th prime


def halton_cell(count: int, dimension: int) -> float:
    """The width of the grid the first `count` Halton points lie on in coordinate `dimension`
    (base b, the dimension's prime): 1 / b^m with b^m the first power of b at or above count."""
    base = HALTON_BASES[dimension] if dimension < len(HALTON_BASES) else 0
    if not base:
        return 0.0  # beyond the listed primes the studies are not interleaved
    cells = 1
    while cells < count:
        cells *= base
    return 1.0 / cells


ROTATIONS = (
    4  # tuning seeds in groups of this many share a shift and interleave (compare.studies' default)
)


def unit_points(count: int, dimensions: int, seed: int) -> np.ndarray:
    """The first `count` points of the Halton sequence in [0, 1)^dimensions, shifted modulo 1 (a
    Cranley-Patterson rotation) by u_d + (seed mod ROTATIONS) / ROTATIONS x h_d: u_d uniform, drawn
    from (seed // ROTATIONS, d) alone (so it does not depend on how many coordinates there are),
    and h_d the width of the grid the points lie on in coordinate d (halton_cell). Shifted, the
    points keep their spacing (n points of n + m begin with those of n) and every point is uniform
    on [0, 1) over seeds; the tuning studies of one design, on consecutive tuning seeds
    (tune_seed + k, whether one compare runs them or one compare each), take the same u and
    rotate by equal fractions of a cell, so their point sets interleave: in every coordinate the
    sets of two studies lie at least h_d / ROTATIONS apart (modulo 1), where independent shifts
    put them anywhere from 0 up (two studies' tuning luck then nearly coincides)."""
    from scipy.stats import qmc

    base = qmc.Halton(d=dimensions, scramble=False).random(count)
    group, turn = divmod(seed, ROTATIONS)
    shift = np.array(
        [
            np.random.default_rng([group, d]).random() + turn / ROTATIONS * halton_cell(count, d)
            for d in range(dimensions)
        ]
    )
    return np.mod(base + shift, 1.0)


def is_whole(bounds: tuple) -> bool:
    """Whether a search range is one of whole numbers (both ends ints: search_space gives a key
    whose preset is a whole number such a range), drawn log-uniformly and rounded."""
    return all(isinstance(b, int) and not isinstance(b, bool) for b in bounds)


def _mapped(unit: float, bounds: tuple) -> float | int:
    """A unit coordinate mapped log-uniformly onto bounds; rounded to the nearest whole number of
    the range for a range of whole numbers."""
    low, high = bounds
    value = math.exp(math.log(low) + unit * (math.log(high) - math.log(low)))
    return min(high, max(low, round(value))) if is_whole(bounds) else float(value)


def halton_points(
    space: dict, count: int, seed: int, dimensions: list[str] | None = None
) -> list[dict]:
    """count shifted Halton points (unit_points of the tuning seed) mapped log-uniformly onto the
    space (rounded where a range is of whole numbers, is_whole). dimensions: the study's
    coordinates (point_dimensions of every variant's space; default: this space's), so that every
    variant of a study is tried at the same points of its own ranges."""
    dimensions = dimensions or point_dimensions([space])
    column = {key: dimensions.index("learning_rate" if is_rate_key(key) else key) for key in space}
    unit = unit_points(count, len(dimensions), seed)
    return [{key: _mapped(row[column[key]], space[key]) for key in sorted(space)} for row in unit]
