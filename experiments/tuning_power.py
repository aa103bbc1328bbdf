"""How often the tuning in front of the verdict fakes one, and how often it finds a real effect:
simulated studies of a model of tuning (docs/protocol.md, "Repeated tuning studies").

Model: a variant's loss at learning rate lr is best * 2 ** ((log10(lr / lr_best) / 0.5) ** 2)
(it doubles half a decade from its best rate), times a seed effect that both runs of a paired seed
share, times run noise exp(N(0, noise)) of its own, in tuning and in evaluation alike. lr_best is
drawn per simulated study, log-uniformly in the middle half of the range, the same for both
variants; a true effect multiplies B's loss by `effect` at every rate. The tuning is physgrad's:
compare.trials scrambled Halton points (physgrad.comparison.tuning.halton_points) over Adam's
learning-rate range, each study's best trial evaluated on the paired seeds, the verdicts by
physgrad.verdict (compare_variants per study, across_studies over them). `same_points=False` gives
each variant its own scramble (seed + variant index), as physgrad did before its trial points were
common.

    python -m experiments.tuning_power [--sims 400]
"""

from __future__ import annotations

import argparse
import math
from collections import Counter

import numpy as np

from physgrad.comparison.tuning import halton_points
from physgrad.optim.capabilities import ADAPTIVE
from physgrad.readout import Curve
from physgrad.verdict import A_BETTER, B_BETTER, across_studies, compare_variants

RANGE = ADAPTIVE.search_range
BUDGET = 1.0


def loss_curve(x: float) -> float:
    """The model's loss relative to its best: doubles half a decade from the best rate."""
    return 2.0 ** ((x / 0.5) ** 2)


def one_study(
    rng: np.random.Generator,
    effect: float,
    trials: int,
    studies: int,
    seeds: int,
    noise: float,
    same_points: bool,
) -> str:
    """The verdict at the budget of one simulated `physgrad compare` of A against B."""
    low, high = (math.log10(v) for v in RANGE)
    best_rate = rng.uniform(low + (high - low) / 4, high - (high - low) / 4)
    scale = {"A": 1.0, "B": effect}
    seed_effect = np.exp(rng.normal(0.0, 1.0, seeds))  # shared by the pair: cancels in the ratio
    per_study = []
    for k in range(studies):
        curves = {}
        for index, name in enumerate("AB"):
            points = halton_points(
                {"lr": RANGE}, trials, 1_000_000 + k + (0 if same_points else index)
            )
            rates = np.log10([p["lr"] for p in points])
            tuned = rates[
                np.argmin(
                    [loss_curve(r - best_rate) * np.exp(rng.normal(0.0, noise)) for r in rates]
                )
            ]
            final = (
                scale[name]
                * loss_curve(tuned - best_rate)
                * seed_effect
                * np.exp(rng.normal(0.0, noise, seeds))
            )
            curves[name] = {
                s: Curve(np.array([BUDGET]), np.array([final[s]]), math.inf) for s in range(seeds)
            }
        per_study.append(compare_variants(curves, BUDGET, fractions=(1.0,)))
    return across_studies(per_study)[0].verdicts[1.0][0]


def simulate(
    effect: float = 1.0,
    trials: int = 16,
    studies: int = 3,
    seeds: int = 10,
    noise: float = 0.3,
    sims: int = 400,
    same_points: bool = True,
    seed: int = 0,
) -> Counter:
    """The verdicts of `sims` simulated studies, counted."""
    rng = np.random.default_rng(seed)
    return Counter(
        one_study(rng, effect, trials, studies, seeds, noise, same_points) for _ in range(sims)
    )


def rate(counts: Counter, verdicts: tuple[str, ...]) -> float:
    return sum(counts[v] for v in verdicts) / sum(counts.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sims", type=int, default=400)
    args = parser.parse_args()
    print("| trials | studies | points | twins called better | true 2x effect found |")
    print("|---|---|---|---|---|")
    for trials in (2, 4, 8, 16):
        for studies, same in ((1, False), (1, True), (3, True)):
            twins = simulate(1.0, trials, studies, sims=args.sims, same_points=same)
            found = simulate(2.0, trials, studies, sims=args.sims, same_points=same)
            print(
                f"| {trials} | {studies} | {'common' if same else 'per variant'} | "
                f"{100 * rate(twins, (A_BETTER, B_BETTER)):.1f}% | "
                f"{100 * rate(found, (A_BETTER,)):.1f}% |",
                flush=True,
            )


if __name__ == "__main__":
    main()
