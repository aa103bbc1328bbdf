"""sensitivity.png: what a study's tuning found, one panel per variant."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from physgrad.files import write_figure

if TYPE_CHECKING:
    from physgrad.comparison.spec import Variant


def plot_sensitivity(
    path: Path, variants: list[Variant], trials_rows: list[dict], best: list[dict[str, dict]]
) -> None:
    """Validation loss at the budget against the learning rate, one panel per variant: every trial
    (a colour per tuning study), each study's chosen one starred, the preset as a dashed line,
    diverged trials as crosses at the top."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # at most three panels a row: six variants are two rows, not one strip
    columns = min(len(variants), 3)
    panel_rows = -(-len(variants) // columns)
    fig, grid = plt.subplots(
        panel_rows, columns, figsize=(3.6 * columns, 3.2 * panel_rows), squeeze=False
    )
    axes = [list(grid.ravel()[: len(variants)])]
    for ax in grid.ravel()[len(variants) :]:
        ax.remove()
    for ax, variant in zip(axes[0], variants):
        rows = [r for r in trials_rows if r["variant"] == variant.name]
        rate = variant.rate_key
        lr = np.array([r.get(rate, np.nan) for r in rows], float)
        loss = np.array([r["validation_loss"] for r in rows], float)
        study = np.array([r.get("study", 0) for r in rows], int)
        ok = np.isfinite(loss)
        for k in range(len(best)):
            mine = ok & (study == k)
            label = "trial" if len(best) == 1 else f"trial, tuning study {k + 1}"
            ax.scatter(lr[mine], loss[mine], s=18, color=f"C{2 * k}", label=label)
        if (~ok).any():
            top = loss[ok].max() * 2 if ok.any() else 1.0
            ax.scatter(lr[~ok], np.full((~ok).sum(), top), marker="x", color="C3", label="diverged")
        for k, chosen_settings in enumerate(best):
            if rate not in chosen_settings[variant.name]:
                continue
            value = chosen_settings[variant.name][rate]
            chosen = [r for r in rows if r.get(rate) == value and r.get("study", 0) == k]
            ax.scatter(
                [value],
                [chosen[0]["validation_loss"]],
                marker="*",
                s=140,
                color="C1",
                label="chosen",
                zorder=3,
            )
        preset = variant.preset.get(rate)
        if isinstance(preset, (int, float)):
            ax.axvline(preset, ls="--", color="0.4", label="preset")
        ax.set_xscale("log")
        if ok.any() and loss[ok].min() > 0:
            ax.set_yscale("log")
        ax.set_title(variant.name)
        ax.set_xlabel("learning rate")
        ax.grid(alpha=0.3)
    for ax in grid[:, 0]:
        ax.set_ylabel("validation loss at the budget")
    legend = {}
    for ax in axes[0]:  # one legend for all panels, below them, off the data
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    fig.legend(
        legend.values(),
        legend.keys(),
        loc="lower center",
        ncol=len(legend),
        fontsize=8,
        frameon=False,
    )
    fig.tight_layout(rect=(0, 0.07 / panel_rows, 1, 1))
    for suffix in (".png", ".pdf"):
        write_figure(fig, path.with_suffix(suffix), dpi=130)
    plt.close(fig)
