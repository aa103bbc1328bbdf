"""How often repeated tuning studies fake a verdict, and how often they find a real effect.

Simulated `physgrad compare` studies decided by physgrad's own verdict functions (docs/protocol.md,
"Independent tuning studies").

Model of one run: its log loss at log10 learning rate x is log(2) * ((x - best) / 0.5)^2 (the loss
doubles half a decade from the best rate, drawn per simulated study in the middle half of Adam's
range, the same for every variant), plus log(effect) for a variant that is worse by `effect`, plus
run noise from one of four null models:

    gaussian   N(0, 0.3)
    bimodal    a plateau: 10x higher with probability 0.3, and N(0, 0.1) (the toy's plateaus)
    heavy      0.3 x Student t with 2 degrees of freedom
    divergent  N(0, 0.3), and the run diverges with probability 1 / (1 + exp(-(x - best - 0.5) /
               0.1)): rates half a decade above the best diverge, so tuned rates near the edge do

Tuning: each variant tries compare.trials points of each tuning study (the same points for every
variant of a study) on its tuning seed (its own run noise per trial), and the lowest validation loss
wins. Evaluation: the tuned rate on compare.seeds paired seeds (a seed effect shared by the pair,
which cancels, and run noise of each run's own).

Two designs:
    independent  physgrad's: each study its own evaluation seeds (fresh run noise) and points
                 shifted by its own random vector (physgrad.comparison.points.halton_points)
    shared       the design before it: every study on the same evaluation seeds (each variant's run
                 noise at a seed drawn once, whatever the tuned rate) and points scrambled per study
                 (scipy's scrambled Halton sequence)

Rules over the studies, on the same simulated data (each without the test between studies,
study_alpha=None, which experiments/study_luck.py measures on top of "consistent"):
    majority  physgrad.replication.across_studies with need = more than half: the verdict of
              more than half of the studies (each decided by compare_variants with Holm over its
              comparisons), none against
    consistent the majority, and every study's median ratio on the verdict's side (a study
              undecided the other way goes against it)
    unanimous every study reaches the verdict
    pooled    one compare_variants over every study's pairs together (30 pairs at 3 x 10)

    python -m experiments.tuning_power [--sims 1600] [--out docs/evidence/tuning_power.csv]
    python -m experiments.tuning_power --table docs/evidence/tuning_power.csv \
        [--docs docs/protocol.md]
"""

from __future__ import annotations

import argparse
import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from experiments.study_luck import append_missing, rate, tally, write_block
from physgrad.comparison.points import halton_points
from physgrad.optim.capabilities import ADAPTIVE
from physgrad.readout import Curve
from physgrad.replication import across_studies, majority
from physgrad.verdict import compare_variants

RANGE = ADAPTIVE.search_range
BUDGET = 1.0
NULLS = ("gaussian", "bimodal", "heavy", "divergent")
RULES = ("majority", "consistent", "unanimous", "pooled")


@dataclass(frozen=True)
class Cell:
    """One row of the table: a design of `variants` variants, all equal but the last, whose loss is
    `effect` times the others' (1: the null)."""

    null: str
    design: str  # independent or shared
    variants: int
    trials: int
    studies: int
    seeds: int
    effect: float
    sims: int

    @property
    def key(self) -> tuple:
        return (self.null, self.design, self.variants, self.trials, self.studies, self.effect)


def run_noise(rng: np.random.Generator, null: str, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(log-loss noise, uniform draws that decide divergence) of `size` runs."""
    if null == "bimodal":
        noise = rng.normal(0.0, 0.1, size) + math.log(10.0) * (rng.random(size) < 0.3)
    elif null == "heavy":
        noise = 0.3 * rng.standard_t(2.0, size)
    else:
        noise = rng.normal(0.0, 0.3, size)
    return noise, rng.random(size)


def log_loss(x: np.ndarray, best: float, effect: float, null: str, noise, uniform) -> np.ndarray:
    """The model's log loss at log10 rates x (inf: diverged)."""
    value = math.log(2.0) * ((np.asarray(x) - best) / 0.5) ** 2 + math.log(effect) + noise
    if null == "divergent":
        diverges = uniform < 1.0 / (1.0 + np.exp(-(np.asarray(x) - best - 0.5) / 0.1))
        value = np.where(diverges, np.inf, value)
    return value


def scrambled_points(count: int, seed: int) -> np.ndarray:
    """The points of the shared design: scipy's scrambled Halton sequence, a scramble per study."""
    from scipy.stats import qmc

    return qmc.Halton(d=1, scramble=True, seed=seed).random(count)[:, 0]


def one_study(rng: np.random.Generator, cell: Cell) -> dict[str, list[str]]:
    """Each rule's verdicts (one per pair, compare_variants' order) of one simulated study."""
    low, high = (math.log10(v) for v in RANGE)
    best = rng.uniform(low + (high - low) / 4, high - (high - low) / 4)
    names = [f"v{i}" for i in range(cell.variants)]
    effects = [1.0] * (cell.variants - 1) + [cell.effect]
    tune_seed = int(rng.integers(2**31))
    # the shared design: each variant's evaluation noise per seed, drawn once for all studies
    shared = [run_noise(rng, cell.null, cell.seeds) for _ in names]
    per_study, pooled = [], {name: {} for name in names}
    for k in range(cell.studies):
        if cell.design == "independent":
            points = halton_points({"learning_rate": RANGE}, cell.trials, tune_seed + k)
            unit = np.array([(math.log10(p["learning_rate"]) - low) / (high - low) for p in points])
        else:
            unit = scrambled_points(cell.trials, tune_seed + k)
        rates = low + unit * (high - low)
        curves = {}
        for index, name in enumerate(names):
            scores = log_loss(
                rates, best, effects[index], cell.null, *run_noise(rng, cell.null, cell.trials)
            )
            tuned = rates[int(np.argmin(scores))] if np.isfinite(scores).any() else rates[0]
            noise = (
                shared[index] if cell.design == "shared" else run_noise(rng, cell.null, cell.seeds)
            )
            final = np.exp(
                log_loss(np.full(cell.seeds, tuned), best, effects[index], cell.null, *noise)
            )
            curves[name] = {
                s: Curve(np.array([BUDGET]), np.array([final[s]]), math.inf)
                for s in range(cell.seeds)
            }
            pooled[name].update({k * cell.seeds + s: c for s, c in curves[name].items()})
        per_study.append(compare_variants(curves, BUDGET, fractions=(1.0,)))
    return {
        "majority": [
            v.verdicts[1.0][0]
            for v in across_studies(
                per_study, need=majority(cell.studies), same_side=False, study_alpha=None
            )
        ],
        "consistent": [
            v.verdicts[1.0][0]
            for v in across_studies(
                per_study, need=majority(cell.studies), same_side=True, study_alpha=None
            )
        ],
        "unanimous": [
            v.verdicts[1.0][0]
            for v in across_studies(per_study, need=cell.studies, same_side=False, study_alpha=None)
        ],
        "pooled": [v.verdicts[1.0][0] for v in compare_variants(pooled, BUDGET, fractions=(1.0,))],
    }


def simulate(cell: Cell, seed: int = 0) -> dict[str, dict[str, int]]:
    """Per rule: studies with a false "better" on some pair (family-wise), false "better" verdicts
    over all pairs (per pair), and, where the last variant is worse, studies that found it worse
    than the first (power)."""
    rng = np.random.default_rng([seed, *(ord(c) for c in cell.null + cell.design), cell.trials])
    counts = {rule: {"family": 0, "pairs": 0, "found": 0} for rule in RULES}
    pairs = [(i, j) for i in range(cell.variants) for j in range(i + 1, cell.variants)]
    for _ in range(cell.sims):
        verdicts = one_study(rng, cell)
        for rule in RULES:
            tally(counts[rule], pairs, verdicts[rule], cell.effect)
    return counts


DESIGNS = (("shared", 3), ("independent", 3), ("independent", 4))  # (design, tuning studies)
# what physgrad compare does: compare.studies=4, physgrad.replication.across_studies' defaults
PHYSGRAD = ("independent", 4, "consistent")
# what it did before independent studies: three studies on shared seeds, the plain majority
BEFORE = ("shared", 3, "majority")


def cells(sims: int) -> list[Cell]:
    """The table: per null model, false "better" per pair at 8 trials x 10 seeds and power at 20%
    and 2x, for the design before independent studies (3 shared) and for 3 and 4 independent
    studies; then family-wise over three equal rules at `make run`'s 4 trials, before (3 shared
    studies) and now (4 independent)."""
    rows = []
    for null in NULLS:
        for design, studies in DESIGNS:
            rows.append(Cell(null, design, 2, 8, studies, 10, 1.0, sims))
            for effect in (1.2, 2.0):
                rows.append(Cell(null, design, 2, 8, studies, 10, effect, sims // 2))
    # three variants cost three times two: fewer simulated studies
    for null in NULLS:
        for design, studies in (("shared", 3), ("independent", 4)):
            rows.append(Cell(null, design, 3, 4, studies, 10, 1.0, 3 * sims // 8))
    return rows


FIELDS = [*Cell.__dataclass_fields__, "rule", "family", "pairs", "found"]


def write_cells(path: Path, sims: int) -> None:
    """Every cell not yet in the CSV at path, appended row by row (a stopped run resumes)."""
    key = ("null", "design", "variants", "trials", "studies", "effect")
    append_missing(path, cells(sims), key, simulate, FIELDS)


def table(path: Path) -> str:
    """The markdown table of docs/protocol.md from the CSV at path: a row per null model, design
    and rule."""
    with open(path) as file:
        rows = list(csv.DictReader(file))
    lines = [
        "| noise | studies | rule | false better per pair | family-wise, 3 equal rules, 4 trials | "
        "found at 1.2x | found at 2x |",
        "|---|---|---|---|---|---|---|",
    ]
    for null in NULLS:
        for design, studies in DESIGNS:
            for rule in RULES:
                mine = [
                    r
                    for r in rows
                    if (r["null"], r["design"], int(r["studies"]), r["rule"])
                    == (null, design, studies, rule)
                ]
                if not mine:
                    continue

                def of(variants, effect, what, mine=mine):
                    row = next(
                        (
                            r
                            for r in mine
                            if int(r["variants"]) == variants and float(r["effect"]) == effect
                        ),
                        None,
                    )
                    if row is None:
                        return "-"
                    sims = int(row["sims"])
                    total = sims * (variants * (variants - 1) // 2) if what == "pairs" else sims
                    return rate(int(row[what]), total)

                label = {
                    PHYSGRAD: f"**{rule}: physgrad** (before studies as draws)",
                    BEFORE: f"{rule}: before",
                }.get((design, studies, rule), rule)
                lines.append(
                    f"| {null} | {studies} {design} | {label} | {of(2, 1.0, 'pairs')} | "
                    f"{of(3, 1.0, 'family')} | {of(2, 1.2, 'found')} | {of(2, 2.0, 'found')} |"
                )
    return "\n".join(lines)


BEGIN, END = "<!-- generated: python -m experiments.tuning_power", "<!-- end of generated table -->"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sims", type=int, default=1600)
    parser.add_argument("--out", type=Path, default=Path("docs/evidence/tuning_power.csv"))
    parser.add_argument("--table", type=Path, help="print the table of a finished CSV")
    parser.add_argument("--docs", type=Path, help="with --table: write it into this markdown file")
    args = parser.parse_args()
    if args.table and args.docs:
        write_block(args.docs, BEGIN, END, table(args.table))
        return
    if args.table:
        print(table(args.table))
        return
    write_cells(args.out, args.sims)
    print(table(args.out))


if __name__ == "__main__":
    main()
