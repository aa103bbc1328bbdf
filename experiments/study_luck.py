"""How often tuning luck makes a verdict: simulated `physgrad compare` studies whose tuning studies
each carry an offset, decided by physgrad's own functions (compare_variants, across_studies).

Model of one evaluation run of variant v in tuning study k on seed s: its log loss is

    log(effect_v) + offset_vk + noise_vks

offset_vk ~ N(0, tau^2 / 2): how good a setting study k's tuning gave v (two variants' offsets
differ by sd tau: the pair's offset in that study); noise_vks: the seed's run noise of sd
spread / sqrt(2) (a pair's log ratio then has sd `spread`), normal or Student t with 3 degrees of
freedom scaled to that sd ("t3"); a run diverges with probability `diverge` (inf). effect: 1 for
every variant but the last, which is `effect` times worse (1: the null).

Rules over the studies, decided on the same simulated data:
    before   physgrad.replication.across_studies without the test between studies: a majority,
             none against, every median on the verdict's side
    0.05, 0.02, 0.01
             the same, and the studies taken as one draw each (between_studies, Hartung-Knapp) at
             that level; physgrad's rule is the one at replication.STUDY_ALPHA

    python -m experiments.study_luck [--sims 2000] [--out docs/evidence/study_luck.csv]
    python -m experiments.study_luck --table docs/evidence/study_luck.csv [--docs docs/protocol.md]
"""

from __future__ import annotations

import argparse
import csv
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from physgrad.files import open_append, write_text
from physgrad.readout import Curve
from physgrad.replication import STUDY_ALPHA, across_studies
from physgrad.verdict import A_BETTER, B_BETTER, compare_variants

# the rule before the test between studies, and the test at three levels (physgrad's: STUDY_ALPHA)
RULES = {"before": None, "0.05": 0.05, "0.02": 0.02, "0.01": 0.01}


@dataclass(frozen=True)
class Model:
    """One row of the table."""

    noise: str  # normal or t3
    spread: float
    tau: float
    diverge: float
    variants: int
    studies: int
    seeds: int
    effect: float
    sims: int

    @property
    def key(self) -> tuple:
        return tuple(str(v) for v in asdict(self).values())


def run_noise(rng: np.random.Generator, model: Model, size) -> np.ndarray:
    scale = model.spread / math.sqrt(2.0)
    if model.noise == "t3":
        return scale * rng.standard_t(3.0, size) / math.sqrt(3.0)
    return rng.normal(0.0, scale, size)


def one_compare(rng: np.random.Generator, model: Model) -> list:
    """The per-study verdicts of one simulated compare (its pairs in compare_variants' order)."""
    names = [f"v{i}" for i in range(model.variants)]
    effects = [1.0] * (model.variants - 1) + [model.effect]
    per_study = []
    for _ in range(model.studies):
        seed_level = rng.normal(0.0, 1.0, model.seeds)  # shared by a seed's runs: cancels
        curves = {}
        for name, effect in zip(names, effects):
            offset = rng.normal(0.0, model.tau / math.sqrt(2.0))
            log_loss = math.log(effect) + offset + seed_level + run_noise(rng, model, model.seeds)
            log_loss[rng.random(model.seeds) < model.diverge] = math.inf
            curves[name] = {
                s: Curve(np.array([1.0]), np.array([math.exp(v)]), math.inf)
                for s, v in enumerate(log_loss)
            }
        per_study.append(compare_variants(curves, 1.0, fractions=(1.0,)))
    return per_study


def simulate(model: Model, seed: int = 0) -> dict[str, dict[str, int]]:
    """Per rule: compares with a false "better" on some pair (family), false "better" verdicts over
    all pairs (pairs), and, where the last variant is worse, compares that found it worse than the
    first (found)."""
    rng = np.random.default_rng([seed, *(int(1000 * float(v)) for v in model.key[1:-1])])
    counts = {rule: {"family": 0, "pairs": 0, "found": 0} for rule in RULES}
    pairs = [(i, j) for i in range(model.variants) for j in range(i + 1, model.variants)]
    for _ in range(model.sims):
        per_study = one_compare(rng, model)
        for rule, alpha in RULES.items():
            verdicts = [v.verdicts[1.0][0] for v in across_studies(per_study, study_alpha=alpha)]
            tally(counts[rule], pairs, verdicts, model.effect)
    return counts


def tally(counts: dict[str, int], pairs: list, verdicts: list, effect: float) -> None:
    """One simulated compare's verdicts (one per pair (i, j), i < j, of variants all equal but the
    last, `effect` times worse) added to counts: "pairs", the false "better" verdicts (any between
    equal variants, "B better" against the worse last); "family", 1 if there was one; "found", the
    first variant found better than a worse last."""
    last = max(j for _, j in pairs)
    false = 0
    for (i, j), verdict in zip(pairs, verdicts):
        equal = effect == 1.0 or j != last
        if verdict in (A_BETTER, B_BETTER) and (equal or verdict == B_BETTER):
            false += 1
        if not equal and i == 0 and verdict == A_BETTER:
            counts["found"] += 1
    counts["pairs"] += false
    counts["family"] += false > 0


def models(sims: int) -> list[Model]:
    """The table's rows: the null at study offsets tau 0 to 1 (spread 0.3, 10 seeds), with 20
    seeds, heavy tails and divergences; the 3-variant design family-wise; power at 1.5x and 2x."""
    rows = [Model("normal", 0.3, tau, 0.0, 2, 4, 10, 1.0, sims) for tau in (0, 0.15, 0.3, 0.5, 1)]
    rows += [
        Model("normal", 0.3, 0.3, 0.0, 2, 4, 20, 1.0, sims),
        Model("t3", 0.3, 0.3, 0.0, 2, 4, 10, 1.0, sims),
        Model("normal", 0.3, 0.3, 0.2, 2, 4, 10, 1.0, sims),
        Model("normal", 0.3, 0.3, 0.0, 3, 4, 10, 1.0, sims // 2),
        Model("normal", 0.3, 0.5, 0.0, 3, 4, 10, 1.0, sims // 2),
    ]
    rows += [Model("normal", 0.3, 0.0, 0.0, 2, 4, 10, e, sims // 2) for e in (1.5, 2.0)]
    rows += [
        Model("normal", 0.3, 0.3, 0.0, 2, 4, 10, 2.0, sims // 2),
        Model("normal", 0.3, 0.0, 0.2, 2, 4, 10, 2.0, sims // 2),
    ]
    return rows


FIELDS = [*Model.__dataclass_fields__, "rule", "family", "pairs", "found"]


def append_missing(path: Path, items: list, key_fields: tuple, simulate, fields: list) -> None:
    """Each item (a dataclass) whose key_fields' values (as text) are not yet a row of the CSV at
    path simulated and appended, one row per rule of what simulate returns (rule -> counts), item by
    item: a stopped run resumes where it stopped."""
    done = set()
    if path.exists():
        with open(path) as file:
            done = {tuple(r[f] for f in key_fields) for r in csv.DictReader(file)}
    path.parent.mkdir(parents=True, exist_ok=True)
    for item in items:
        row = asdict(item)
        if tuple(str(row[f]) for f in key_fields) in done:
            continue
        counts = simulate(item)
        new = not path.exists()
        with open_append(path) as file:
            writer = csv.DictWriter(file, fields)
            if new:
                writer.writeheader()
            for rule, numbers in counts.items():
                writer.writerow({**row, "rule": rule, **numbers})
        print(item, counts, flush=True)


def write(path: Path, sims: int) -> None:
    """Every row not yet in the CSV at path, appended row by row (a stopped run resumes)."""
    append_missing(path, models(sims), tuple(Model.__dataclass_fields__), simulate, FIELDS)


def write_block(doc: Path, begin: str, end: str, text: str) -> None:
    """The lines between the line that starts with begin and the one that starts with end of a
    markdown file, replaced by text."""
    page = doc.read_text()
    start = page.index("\n", page.index(begin)) + 1
    write_text(doc, page[:start] + text + "\n" + page[page.index(end) :])


def rate(count: int, total: int) -> str:
    """count / total as a percentage with its 95% Wilson interval."""
    from scipy.stats import binomtest

    ci = binomtest(count, total).proportion_ci(method="wilson")
    return f"{100 * count / total:.2f}% [{100 * ci.low:.1f}, {100 * ci.high:.1f}]"


def table(path: Path) -> str:
    """The markdown table of docs/protocol.md from the CSV: a row per model, a column per rule."""
    with open(path) as file:
        rows = list(csv.DictReader(file))
    lines = [
        "| model | what is counted | "
        + " | ".join(f"**{r}: physgrad**" if RULES[r] == STUDY_ALPHA else r for r in RULES)
        + " |",
        "|---|---|" + "---|" * len(RULES),
    ]
    keys = list(dict.fromkeys(tuple(r[f] for f in Model.__dataclass_fields__) for r in rows))
    for key in keys:
        mine = {
            r["rule"]: r for r in rows if tuple(r[f] for f in Model.__dataclass_fields__) == key
        }
        m = dict(zip(Model.__dataclass_fields__, key))
        variants, sims, effect = int(m["variants"]), int(m["sims"]), float(m["effect"])
        label = (
            f"{m['noise']}, spread {m['spread']}, tau {m['tau']}, "
            + (f"{float(m['diverge']):.0%} diverge, " if float(m["diverge"]) else "")
            + f"{m['seeds']} seeds, {variants} variants"
            + (f", {effect:g}x" if effect != 1.0 else "")
        )
        if effect != 1.0:
            what, cells = (
                f"found, of {sims}",
                [rate(int(mine[r]["found"]), sims) for r in RULES],
            )
        elif variants == 2:
            what, cells = (
                f"false better per pair, of {sims}",
                [rate(int(mine[r]["pairs"]), sims) for r in RULES],
            )
        else:
            what, cells = (
                f"family-wise, of {sims}",
                [rate(int(mine[r]["family"]), sims) for r in RULES],
            )
        lines.append(f"| {label} | {what} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


BEGIN, END = "<!-- generated: python -m experiments.study_luck", "<!-- end of study_luck table -->"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sims", type=int, default=2000)
    parser.add_argument("--out", type=Path, default=Path("docs/evidence/study_luck.csv"))
    parser.add_argument("--table", type=Path, help="print the table of a finished CSV")
    parser.add_argument("--docs", type=Path, help="with --table: write it into this markdown file")
    args = parser.parse_args()
    if args.table:
        text = table(args.table)
        if args.docs:
            write_block(args.docs, BEGIN, END, text)
        else:
            print(text)
        return
    write(args.out, args.sims)
    print(table(args.out))


if __name__ == "__main__":
    main()
