"""The regime map (payoff.png and its table): where HIG pays off against Adam, by the conditioning
of the physics (across) and HIG's step cost relative to Adam's (down), each cell a compare study
of the claims profile (experiments/conf/studies.yaml, the studies of one tuning study) with both
variants tuned in it. A cell is the time each seed takes to reach the cell's target, HIG / Adam,
with the median's interval (docs/decisions.md, "The regime map").
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from evidence import read_json  # experiments/
from studies import MAP, Study
from study_runs import read_study

from physgrad.files import write_figure
from physgrad.readout import fmt, highest_median
from physgrad.verdict import A_BETTER, B_BETTER, EQUIVALENT, compare_variants, ratio_of


@dataclass(frozen=True)
class Cell:
    study: str
    conditioning: float  # the toy's lambda or the oscillators' coupling
    cost_ratio: float  # HIG's calibrated step cost / Adam's
    ratio: float  # median time-to-target HIG / Adam over the seeds
    low: float
    high: float
    reached: tuple[int, int, int]  # seeds where HIG, Adam reached the target, of n
    verdict: str


def map_cell(root: Path, study: Study) -> Cell | None:
    """One cell: the time each variant's seeds take to reach the cell's target, as per-seed ratios
    HIG / Adam with the verdict rule's median and interval (a seed that never reaches it counts as
    infinite, as a divergence does; a pair where neither does is left out and counted, as a pair
    where both diverged). The target is the higher of
    the two variants' median test loss at the budget (readout.highest_median): what the slower
    variant typically gets to, which the faster one reaches in most seeds. compare's target (the
    lower median) is reached by only about half the better variant's seeds, so with 6 seeds most
    pairs are two misses and no cell can be decided."""
    runs = read_study(root / study.name)
    if runs is None or not {"hig", "adam"} <= set(runs.paths):
        return None
    curves = {v: runs.curves(v) for v in ("hig", "adam")}
    _, target = highest_median(
        {v: [c.at(runs.budget) for c in by.values()] for v, by in curves.items()}
    )
    seeds = sorted(set(curves["hig"]) & set(curves["adam"]))
    times = {
        v: [
            curves[v][s].reaches(target, runs.budget) if math.isfinite(target) else math.inf
            for s in seeds
        ]
        for v in curves
    }
    (result,) = compare_variants(
        {v: {s: _constant(t) for s, t in zip(seeds, times[v])} for v in times},
        1.0,
        fractions=(0.25, 0.5, 1.0),
    )
    p = result.at[1.0]
    cost = math.nan
    calibration = root / study.name / "calibration.json"
    if calibration.is_file():
        try:
            costs = read_json(calibration)["costs"]
            cost = float(costs["hig"]["step_seconds"]) / float(costs["adam"]["step_seconds"])
        except (OSError, ValueError, KeyError, TypeError, ZeroDivisionError):
            pass
    conditioning = float(
        re.search(r"task\.(?:scale|alpha)=([0-9.e-]+)", " ".join(study.overrides)).group(1)
    )
    reached = (
        sum(math.isfinite(t) for t in times["hig"]),
        sum(math.isfinite(t) for t in times["adam"]),
        len(seeds),
    )
    if not math.isfinite(target):  # both diverged in most seeds: nothing to reach, not "equivalent"
        return Cell(
            study.name, conditioning, cost, math.nan, math.nan, math.nan, reached, NO_TARGET
        )
    return Cell(
        study.name,
        conditioning,
        cost,
        p.ratio,
        ratio_of(p.low),
        ratio_of(p.high),
        reached,
        result.verdict,
    )


def _constant(value: float):
    """A time to target as a curve whose 'loss' is that time, read at x = 1 (inf: never reached)."""
    from physgrad.readout import Curve

    return Curve(np.array([0.0]), np.array([value]), 1.0, False, None)


NO_TARGET = "no target (both diverged in most seeds)"


MAP_VERDICTS = {A_BETTER: "HIG first", B_BETTER: "Adam first", EQUIVALENT: "within 10%"}


def plot_map(cells: dict[str, list[Cell]], path: Path, machine: str, note: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    panels = [(name, found) for name, found in cells.items() if found]
    fig, axes = plt.subplots(
        1, len(panels), figsize=(6.6 * len(panels), 5.0), squeeze=False, layout="constrained"
    )
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-2.0, vmax=2.0)
    for ax, (name, found) in zip(axes[0], panels):
        xs = sorted({c.conditioning for c in found}, reverse=name == "toy")
        rows = sorted({c.study.rsplit("_b", 1)[-1] if name == "toy" else "" for c in found})
        grid = np.full((len(rows), len(xs)), np.nan)
        for c in found:
            i = rows.index(c.study.rsplit("_b", 1)[-1] if name == "toy" else "")
            j = xs.index(c.conditioning)
            if not math.isnan(c.ratio):  # no target: left blank
                grid[i, j] = math.log10(min(max(c.ratio, 1e-2), 1e2))
            dark = abs(grid[i, j]) > 1.2
            ax.text(
                j,
                i,
                f"{MAP_VERDICTS.get(c.verdict, c.verdict)}\n{fmt(c.ratio)} [{fmt(c.low)}, "
                f"{fmt(c.high)}]\n"
                f"reached: HIG {c.reached[0]}, Adam {c.reached[1]} of {c.reached[2]}",
                ha="center",
                va="center",
                fontsize=7.5,
                color="white" if dark else "black",
            )
        image = ax.imshow(grid, cmap="RdBu_r", norm=norm, aspect="auto", origin="lower")
        costs = {
            r: np.nanmedian(
                [
                    c.cost_ratio
                    for c in found
                    if (c.study.rsplit("_b", 1)[-1] if name == "toy" else "") == r
                ]
                or [np.nan]
            )
            for r in rows
        }
        labels = [
            (f"batch {r}\n" if r else "") + f"HIG step\n= {fmt(costs[r])} x Adam's" for r in rows
        ]
        ax.set_yticks(range(len(rows)), labels, fontsize=8)
        ax.set_xticks(range(len(xs)), [f"{x:g}" for x in xs])
        ax.set_xlabel(
            "lambda (the second component's scale)\nbadly conditioned to the right"
            if name == "toy"
            else "coupling alpha (the cubic spring)\nstiffer to the right",
            fontsize=9,
        )
        ax.set_title(f"{name}: time to target, HIG / Adam (median [95% interval])", fontsize=9)
    fig.colorbar(image, ax=list(axes[0]), label="log10 HIG / Adam time to target (blue: HIG first)")
    fig.suptitle(
        f"Where HIG pays off: both tuned per cell, equal calibrated training time. {machine}"
        + (f"\n{note}" if note else ""),
        fontsize=8,
    )
    write_figure(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def regime_map(root: Path, out: Path, note: str = "") -> str:
    cells = {
        title: [c for s in MAP if task in s.overrides and (c := map_cell(root, s))]
        for title, task in (("toy", "task=toy"), ("oscillators", "task=oscillator"))
    }
    if not any(cells.values()):
        return ""
    machines = {read_study(root / s.name).machine for s in MAP if read_study(root / s.name)}
    machine = "; ".join(sorted(m for m in machines if m))
    plot_map(cells, out / "payoff.png", machine, note)
    lines = [
        "\n## Where HIG pays off: a regime map\n",
        "![payoff](payoff.png)\n",
        "Each cell is a `physgrad compare` of Adam and HIG, both tuned in that cell, at equal "
        "calibrated "
        "training time: the time each seed takes to reach the cell's target (the higher of the "
        "two variants' "
        "median test loss at the budget: what the slower one typically gets to), as the ratio HIG "
        "/ Adam with "
        "its 95% interval (below 1: HIG gets there first; a seed that never reaches the target "
        "counts as "
        "infinite, a pair where neither does as a tie; 0 or inf: in the middle pair one variant "
        f"got there and the other did not). Machine: {machine or '-'}.\n",
        "| study | conditioning | HIG step / Adam step | time to target HIG / Adam [95%] | "
        "reached HIG, Adam of n | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for found in cells.values():
        for c in found:
            lines.append(
                f"| {c.study} | {c.conditioning:g} | {fmt(c.cost_ratio)} | {fmt(c.ratio)} "
                f"[{fmt(c.low)}, {fmt(c.high)}] | "
                f"{c.reached[0]}, {c.reached[1]} of {c.reached[2]} | "
                f"{MAP_VERDICTS.get(c.verdict, c.verdict)} |"
            )
    return "\n".join(lines) + "\n"
