"""The unrolling study's comparison on Kuramoto-Sivashinsky, from the runs of
conf/experiment/fig9_ks.yaml: ks_unroll.png (held-out relative error and unstable share of long
rollouts against the unroll length, one line per training modality, one column per stepper) and
ks_claims.md (the study's claims, as measured here).

Usage: python experiments/ks_study.py RUNS_FOLDER [OUT_FOLDER]
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from physgrad.files import write_figure, write_text
from physgrad.readout import config_row, fmt
from physgrad.results import find_results, read_run

MODALITIES = ("ONE", "NOG", "WIG")
STEPPERS = ("predict", "correct")


def collect(folders: list[Path]) -> dict:
    """{(stepper, training, unroll): {seed: (final held-out loss, final unstable share)}} of
    completed runs; a diverged run counts as an infinite error (it is a result)."""
    table = defaultdict(dict)
    for path in find_results(folders):
        run = read_run(path)
        config = config_row(run)
        if run.attrs.get("task") != "ks" or run.attrs.get("status") not in (
            "completed",
            "diverged",
        ):
            continue
        key = (config["task.stepper"], config["task.training"], int(run.attrs["unroll"]))
        if run.attrs["status"] == "diverged":
            table[key][int(run.attrs["seed"])] = (np.inf, 1.0)
        else:
            table[key][int(run.attrs["seed"])] = (
                run.final("eval"),
                float(run.eval["unstable_fraction"][-1]),
            )
    return table


def median(values) -> float:
    """The median, NaN (0/0, inf/inf) ignored; NaN if nothing is left."""
    values = np.asarray(values, float)
    values = values[~np.isnan(values)]
    return float(np.median(values)) if len(values) else float("nan")


def paired(table, better, worse) -> tuple[int, int, float]:
    """Seeds where `better` has the lower error, seeds compared, median ratio worse / better over
    seeds."""
    # seeds where both diverged say nothing about which is better: left out
    seeds = sorted(
        s
        for s in set(table.get(better, {})) & set(table.get(worse, {}))
        if np.isfinite(table[better][s][0]) or np.isfinite(table[worse][s][0])
    )
    wins = sum(table[better][s][0] < table[worse][s][0] for s in seeds)
    with np.errstate(all="ignore"):
        ratios = [table[worse][s][0] / table[better][s][0] for s in seeds]
    return wins, len(seeds), median(ratios)


def _fmt(value: float) -> str:
    return "inf (diverged)" if value == np.inf else fmt(value)


def claims(table) -> str:
    unrolls = sorted({key[2] for key in table})
    lines = [
        "| claim (the study) | measured here | seeds: wins / compared, median ratio |",
        "|---|---|---|",
    ]
    # 1: correction beats prediction (the study: about 4.5x)
    pairs = [
        (("correct", t, m), ("predict", t, m))
        for t in MODALITIES
        for m in unrolls
        if ("correct", t, m) in table and ("predict", t, m) in table
    ]
    wins = sum(paired(table, a, b)[0] for a, b in pairs)
    compared = sum(paired(table, a, b)[1] for a, b in pairs)
    ratios = [r for r in (paired(table, a, b)[2] for a, b in pairs) if not np.isnan(r)]
    measured = (
        f"median over settings of predict/correct error ratio: {fmt(median(ratios))} (range "
        f"{fmt(min(ratios))} to {fmt(max(ratios))})"
        if ratios
        else "no setting has finished runs of both steppers: nothing to compare"
    )
    lines.append(
        f"| correction beats prediction (about 4.5x lower error) | {measured} | correct lower in "
        f"{wins} / {compared} |"
    )
    # 2: WIG best, NOG close; WIG far below ONE
    for stepper in STEPPERS:
        for m in unrolls:
            if m == 1:
                continue  # at m = 1 the three modalities are the same computation
            medians = {
                t: median([v[0] for v in table.get((stepper, t, m), {}).values()])
                for t in MODALITIES
            }
            if any(np.isnan(v) for v in medians.values()):
                continue
            order = " < ".join(sorted(MODALITIES, key=lambda t: medians[t]))
            w_nog, n_nog, r_nog = paired(table, (stepper, "WIG", m), (stepper, "NOG", m))
            w_one, n_one, r_one = paired(table, (stepper, "WIG", m), (stepper, "ONE", m))
            lines.append(
                f"| WIG best, NOG close, WIG below ONE ({stepper}, m={m}) | median error "
                + ", ".join(f"{t} {_fmt(medians[t])}" for t in MODALITIES)
                + f"; order {order} | "
                f"WIG < NOG {w_nog}/{n_nog} (NOG/WIG {fmt(r_nog)}), WIG < ONE {w_one}/{n_one} "
                f"(ONE/WIG {fmt(r_one)}) |"
            )
    # 3: an unroll length with the lowest error
    for stepper in STEPPERS:
        for t in ("NOG", "WIG"):
            by_m = {
                m: median([v[0] for v in table[(stepper, t, m)].values()])
                for m in unrolls
                if (stepper, t, m) in table
            }
            if by_m:
                best = min(by_m, key=lambda m: by_m[m])
                curve = ", ".join(f"m={m}: {_fmt(v)}" for m, v in by_m.items())
                lines.append(
                    f"| an unroll length with the lowest error ({stepper}, {t}) | best m = {best}; "
                    f"median error {curve} | |"
                )
    return "\n".join(lines) + "\n"


def plot(table, path: Path, note: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex=True, squeeze=False)
    for column, stepper in enumerate(STEPPERS):
        for t in MODALITIES:
            points = sorted(m for (s, tt, m) in table if s == stepper and tt == t)
            for row in (0, 1):
                values = [
                    np.array([v[row] for v in table[(stepper, t, m)].values()]) for m in points
                ]
                finite = [v[np.isfinite(v)] for v in values]
                mid = np.array([np.median(v) if len(v) else np.nan for v in finite])
                low = mid - np.array([v.min() if len(v) else np.nan for v in finite])
                high = np.array([v.max() if len(v) else np.nan for v in finite]) - mid
                axes[row, column].errorbar(
                    points, mid, yerr=[low, high], fmt="o-", capsize=3, label=t
                )
        axes[0, column].set_title(f"stepper: {stepper}", fontsize=10)
        axes[0, column].set_yscale("log")
        axes[0, column].set_ylabel("relative error over 12 steps (test sizes)")
        axes[1, column].set_ylabel("unstable share of long rollouts")
        axes[1, column].set_ylim(-0.05, 1.05)
        for row in (0, 1):
            axes[row, column].set_xscale("log", base=2)
            axes[row, column].xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.0f}"))
            axes[row, column].grid(True, which="both", alpha=0.3)
            axes[row, column].legend(
                fontsize=8, title="median over seeds, bars: min-max", title_fontsize=7
            )
        axes[1, column].set_xlabel("unroll length m (ONE: m one-step pairs per sample)")
    fig.suptitle(
        note or "Kuramoto-Sivashinsky: training modality and stepper against unroll length",
        fontsize=10,
    )
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)


def write(folders: list[Path], out: Path, note: str = "") -> tuple[list[str], str]:
    """Draw ks_unroll.png and write ks_claims.md into out from the runs under the folders; returns
    (figure names, the claims table)."""
    table = collect(folders)
    out.mkdir(parents=True, exist_ok=True)
    if not table:
        return [], "no completed Kuramoto-Sivashinsky runs\n"
    plot(table, out / "ks_unroll.png", note)
    text = claims(table)
    write_text(
        out / "ks_claims.md",
        "# Kuramoto-Sivashinsky: the unrolling study's claims, as measured\n\n"
        + (f"{note}\n\n" if note else "")
        + text,
    )
    return ["ks_unroll.png"], text


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        print(__doc__.split("\n\n")[-1], file=sys.stderr)
        sys.exit(2)
    folder = Path(sys.argv[1])
    images, text = write([folder], Path(sys.argv[2]) if len(sys.argv) == 3 else folder)
    print(text)
