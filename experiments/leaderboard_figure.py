"""The leaderboard's heat map (docs/leaderboard.png and .pdf): each rule's median test loss
against Adam's per scene, the verdict in every decided cell."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from leaderboard_detail import MARKS  # experiments/
from leaderboard_scenes import RULES, SCENES, planned_studies

from physgrad.comparison.coverage import FEW_STEPS  # noqa: F401 - a cell on fewer is marked
from physgrad.readout import fmt
from physgrad.verdict import A_BETTER, B_BETTER, EQUIVALENT, MARGIN


def plot(found: dict, path: Path, protocol: str = "") -> None:
    """The heat map: log10 of the median ratio rule / Adam (blue: the rule lower), a verdict in
    every decided cell, undecided cells hatched, rules that do not apply grey; protocol: a line
    in its title on the protocol its studies ran under, where the page's is not the current one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from physgrad.plots import save_figure

    scenes = list(SCENES)  # every column, so that what is still to run shows
    grid = np.full((len(RULES), len(scenes)), np.nan)
    fig, ax = plt.subplots(figsize=(1.6 + 1.45 * len(scenes), 0.9 + 0.48 * len(RULES)))
    for j, entry in enumerate(scenes):
        for i, rule in enumerate(RULES):
            cell = found.get(entry.name, ({},))[0].get(rule)
            if cell is not None and math.isfinite(cell.ratio) and cell.ratio > 0:
                grid[i, j] = math.log10(cell.ratio)
    limit = max(1.0, float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 1.0)
    image = ax.imshow(grid, cmap="RdBu_r", vmin=-limit, vmax=limit, aspect="auto")
    for j, entry in enumerate(scenes):
        for i, rule in enumerate(RULES):
            cell = found.get(entry.name, ({},))[0].get(rule)
            if rule in entry.refused:
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, color="0.85"))
                ax.text(j, i, "n/a", ha="center", va="center", fontsize=7, color="0.4")
            elif cell is None:
                ax.text(j, i, "not run", ha="center", va="center", fontsize=7, color="0.4")
            else:
                decided = cell.verdict in MARKS
                if not decided:
                    ax.add_patch(
                        plt.Rectangle(
                            (j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", color="0.6", lw=0
                        )
                    )
                symbol = {A_BETTER: "\u25bc ", B_BETTER: "\u25b2 ", EQUIVALENT: "= "}.get(
                    cell.verdict, "? "
                )
                strong = abs(grid[i, j]) > 0.6 * limit if np.isfinite(grid[i, j]) else False
                few = "\n<100 steps" if cell.iterations < FEW_STEPS else ""
                ax.text(
                    j,
                    i,
                    f"{symbol}{fmt(cell.ratio)}x{few}",
                    ha="center",
                    va="center",
                    fontsize=8,
                    color="white" if strong else "black",
                    fontweight="bold" if decided else "normal",
                )
    ran = {
        name: (len(runs.tuning or (runs,)), planned_studies(runs))
        for name, (_, runs, _) in found.items()
    }
    labels = [
        e.title
        + (
            f"\n({ran[e.name][0]} of {ran[e.name][1]} studies)"
            if 0 < ran.get(e.name, (0, 0))[0] < ran.get(e.name, (0, 0))[1]
            else ""
        )
        for e in scenes
    ]
    ax.set_xticks(range(len(scenes)), labels, rotation=25, ha="right")
    ax.set_yticks(range(len(RULES)), RULES)
    bar = fig.colorbar(image, ax=ax, fraction=0.04, pad=0.02)
    bar.set_label("log10 (test loss of the rule / Adam's), median over seeds")
    ax.set_title(
        "Each rule against Adam at equal calibrated time"
        + (f" ({protocol})" if protocol else "")
        + "\n"
        f"\u25bc lower than Adam, \u25b2 higher (beyond {MARGIN:g}x), = within {MARGIN:g}x, "
        f"? undecided (hatched), n/a: does not apply; <{FEW_STEPS} steps: decided on fewer than "
        f"{FEW_STEPS} of the rule's steps",
        fontsize=9,
    )
    save_figure(fig, path, "")
