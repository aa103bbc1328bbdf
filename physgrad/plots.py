"""Figures: the style every figure shares (one colour, line style and marker per group; legends
beside the panels; log axes that read well; PNG and PDF through matplotlib's Agg backend) and the
figure of one run (losses, gradient norm and the scene's metrics). The report's figures, which
compare runs, are in physgrad.report_figures and physgrad.cost_figures."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, MaxNLocator, NullFormatter, NullLocator  # noqa: E402

from physgrad.files import write_figure
from physgrad.readout import fmt
from physgrad.results import Run, natural_key  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

COLORS = plt.get_cmap("tab10").colors
LINESTYLES = ("-", "--", ":", "-.")
MARKERS = ("o", "s", "D", "v", "P", "X")  # not "^": it marks a diverged run
DPI = 110  # the PNGs' resolution


def literal(text: object) -> str:
    """Text from a results file (anyone's) as matplotlib should draw it: a `$` is a dollar sign, not
    the start of mathtext to parse (which fails on unbalanced or invalid expressions)."""
    return str(text).replace("$", r"\$")


def group_styles(labels: Iterable[str]) -> dict[str, dict]:
    """One style per group label, the same in every figure and panel of a report: tab10's ten
    colours, and past ten groups another line style and marker with each round of colours, so no two
    groups look alike."""
    styles = {}
    for index, label in enumerate(sorted(set(labels), key=natural_key)):
        round_ = index // len(COLORS)
        styles[label] = {
            "color": COLORS[index % len(COLORS)],
            "linestyle": LINESTYLES[round_ % len(LINESTYLES)],
            "marker": MARKERS[round_ % len(MARKERS)],
        }
    return styles


def design_styles(design: dict[str, tuple[str, int]]) -> dict[str, dict]:
    """One style per group of a designed study (label -> (variant, tuning study)): the colour by
    variant and the line style and marker by tuning study, so that a variant reads as one colour
    across its studies and a study as one line style across its variants."""
    variants = sorted({variant for variant, _ in design.values()}, key=natural_key)
    return {
        label: {
            "color": COLORS[variants.index(variant) % len(COLORS)],
            "linestyle": LINESTYLES[(study - 1) % len(LINESTYLES)],
            "marker": MARKERS[(study - 1) % len(MARKERS)],
        }
        for label, (variant, study) in design.items()
    }


def by_label(groups: dict) -> list[tuple[str, dict]]:
    """A figure's groups (label -> its runs' data) in the labels' natural order."""
    return sorted(groups.items(), key=lambda item: natural_key(item[0]))


def styles_for(runs: list[Run], styles: dict | None) -> dict:
    """The styles given, else group_styles of these runs' groups."""
    return styles if styles is not None else group_styles(run.label or run.variant for run in runs)


def legend_outside(ax: Axes, **kwargs: object) -> None:
    """The legend beside the panel, right of its data (the figure is saved with
    bbox_inches="tight")."""
    ax.legend(
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        borderaxespad=0.0,
        fontsize=7,
        title_fontsize=7,
        **kwargs,
    )


def limit_to(ax: Axes, values: Iterable[float], pad: float = 3.0) -> None:
    """y limits (a log axis) that hold the given values: diverged runs, drawn after, leave at the
    top edge."""
    values = np.asarray([v for v in values if np.isfinite(v) and v > 0], float)
    if values.size:
        low, high = values.min(), values.max()
        ax.set_ylim(low / pad, high * pad)


def _three_figures(value: float, _position: int | None = None) -> str:
    """A tick label: the tables' number format (readout.fmt)."""
    return fmt(float(value))


def log_axis(ax: Axes, which: str = "y") -> None:
    """A log axis whose labels read well: decades in scientific notation, and where the data span
    less than a decade, a few evenly spaced values with three significant figures (matplotlib's
    default then labels minor ticks such as 9.9992x10^-1)."""
    axis = ax.yaxis if which == "y" else ax.xaxis
    (ax.set_yscale if which == "y" else ax.set_xscale)("log")
    low, high = ax.get_ylim() if which == "y" else ax.get_xlim()
    if low > 0 and high / low < 10:
        axis.set_major_locator(MaxNLocator(5))
        axis.set_major_formatter(FuncFormatter(_three_figures))
        axis.set_minor_locator(NullLocator())
        axis.set_minor_formatter(NullFormatter())


def save_figure(fig: Figure, path: str | Path, note: str) -> None:
    """path without suffix: written as path.png and path.pdf."""
    top = 1.0
    if note:
        fig.suptitle(literal(note), fontsize=9, color="dimgray")
        # the note's lines, in inches
        top -= (0.2 + 0.17 * (note.count("\n") + 1)) / fig.get_figheight()
    fig.tight_layout(rect=(0, 0, 1, top))
    # legends sit outside: the box around everything drawn, found once for both formats (where
    # bbox_inches="tight" lays the figure out and measures it again for each); measured at the
    # resolution it is saved at, since text extents do not scale exactly with it (a long legend
    # entry measured at 100 dpi was cut at 110)
    fig.set_dpi(DPI)
    fig.draw_without_rendering()
    box = fig.get_tightbbox().padded(plt.rcParams["savefig.pad_inches"])
    for suffix in (".png", ".pdf"):
        write_figure(fig, Path(path).with_suffix(suffix), dpi=DPI, bbox_inches=box)
    plt.close(fig)


PLAIN_COLUMNS = ("iteration", "wall_time", "calibrated_time", "loss", "grad_norm")


def plot_run(run: Run, path: str | Path) -> None:
    """One run: train and test loss against iteration and training time; the gradient norm, the
    update norm and the largest |y|; the update rule's diagnostics where it logs any (HIG and
    Gauss-Newton: kept singular values, SVD failures; the combined gradient C: zeroed fraction,
    cos(g_M, g_R); a rule's own scalars); the scene's metrics at the evaluations. A quantity that
    spans more than two decades is on a log axis."""
    metrics = sorted(
        k
        for k in run.eval
        if k not in ("iteration", "wall_time", "calibrated_time", "loss", "validation_loss")
    )
    diagnostics = sorted(
        k
        for k in run.train
        if k not in (*PLAIN_COLUMNS, "update_norm", "output_max_abs", "state_max_abs")
    )
    fig, axes = plt.subplots(3, 2, figsize=(11, 10.5))
    for ax, x_key, x_label in zip(
        axes[0], ("iteration", "wall_time"), ("iteration", "training time [s]")
    ):
        if run.train.get("loss") is not None and run.train["loss"].size and x_key in run.train:
            ax.plot(
                run.train[x_key], run.train["loss"], lw=0.7, alpha=0.5, label="train (minibatch)"
            )
        if run.eval.get("loss") is not None and run.eval["loss"].size:
            ax.plot(run.eval[x_key], run.eval["loss"], "o-", ms=3, label="test")
        ax.set_xlabel(x_label)
        ax.set_ylabel("loss")
        log_axis(ax)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_lines():  # a run stopped before its first evaluation has nothing to show
            ax.legend(fontsize=8)
    ax = axes[1, 0]
    for name, label in (
        ("grad_norm", "gradient (before the update rule)"),
        ("update_norm", "update"),
        ("output_max_abs", "largest |y|"),
    ):
        if name in run.train and run.train[name].size:
            ax.plot(run.train["iteration"], run.train[name], lw=0.7, label=label)
    _fit_axis(ax)
    ax.set_xlabel("iteration")
    ax.set_ylabel("norm")
    if ax.get_lines():
        ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[1, 1]
    for name in metrics:
        ax.plot(run.eval["iteration"], run.eval[name], "o-", ms=3, label=literal(name))
    _fit_axis(ax)
    _empty_or_legend(ax, "test metric", "this scene has no metric besides the loss")
    ax = axes[2, 0]
    for name in diagnostics:
        ax.plot(run.train["iteration"], run.train[name], lw=0.8, label=literal(name))
    _fit_axis(ax)
    _empty_or_legend(ax, "update rule diagnostic", "this update rule logs no diagnostics")
    axes[2, 1].set_visible(False)
    status = run.attrs.get("status", "?")
    reason = f" ({run.attrs['reason']})" if run.attrs.get("reason") else ""
    fig.suptitle(
        literal(
            f"{run.attrs.get('task')} / {run.variant}, seed {run.attrs.get('seed')}: "
            f"{status}{reason}"
        ),
        fontsize=10,
    )
    fig.tight_layout()
    write_figure(fig, path, dpi=110)
    plt.close(fig)


def _fit_axis(ax: Axes) -> None:
    """A log y axis where the drawn values are positive and span more than two decades."""
    values = np.concatenate(
        [np.asarray(line.get_ydata(), float) for line in ax.get_lines()] or [np.empty(0)]
    )
    values = values[np.isfinite(values)]
    if values.size and values.min() > 0 and values.max() / values.min() > 100:
        log_axis(ax)


def _empty_or_legend(ax: Axes, ylabel: str, empty: str) -> None:
    ax.set_xlabel("iteration")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_lines():
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, empty, ha="center", va="center", transform=ax.transAxes, color="dimgray")
