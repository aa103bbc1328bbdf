"""Does a busy machine flip an equal-time comparison? One `physgrad compare` study run twice: on the
machine as it is, then beside CPU-bound processes (one per core) that this script starts and stops
itself, reusing the quiet study's calibration (compare.calibration), as a user re-running a
comparison on a busy laptop would. While the processes run it also calibrates the variants again, to
show what a calibration under load measures. Writes timing_check.md into OUT: both runs' verdicts
side by side, each variant's calibrated-clock test loss at the budget (median and range over seeds),
how many runs of each were flagged contended, and the step costs calibrated quiet and under load.

    python experiments/timing_check.py [--out outputs/timing_check] [--hogs N] -- task=toy
    optim=adam,gauss_newton,hig trainer.time_budget=5

Both studies are resumable (their folders are OUT/quiet and OUT/loaded): run the same command again
after an interruption. The verdicts must agree and the losses of the loaded run lie within the quiet
run's seed range (docs/decisions.md, "Timing").
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
from pathlib import Path

import numpy as np

from physgrad.files import write_text

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def burn() -> None:
    """A CPU-bound process: what another user's job does to the cores."""
    x = 0
    while True:
        x = (x * 1103515245 + 12345) % 2**31


def study(overrides: list[str], folder: Path):
    import physgrad

    return physgrad.compare(*overrides, f"compare.dir={folder}")


def calibrate_under_load(overrides: list[str]) -> dict:
    """The study's variants calibrated again, now (physgrad.comparison.calibration)."""
    from omegaconf import open_dict

    from physgrad.comparison import build_variants, split_overrides, study_settings
    from physgrad.timing import calibrate

    given, axes, common, _ = split_overrides(overrides)
    settings = study_settings(given)
    configs = {}
    for variant in build_variants(axes, common, settings, []):
        cfg = variant.config.copy()
        with open_dict(cfg):
            del cfg["hydra"]
        configs[variant.name] = cfg
    return calibrate(configs, settings.tune_seed)


def summary(result) -> dict:
    runs = result.runs
    out = {}
    for variant, rows in runs.groupby("variant", sort=False):
        losses = rows["test_loss_at_1"].to_numpy(float)
        out[variant] = {
            "median": float(np.nanmedian(losses)),
            "low": float(np.nanmin(losses)),
            "high": float(np.nanmax(losses)),
            "contended": int(rows["contended"].sum()),
            "runs": len(rows),
            "iterations": float(np.median(rows["iterations"])),
        }
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/timing_check")
    parser.add_argument(
        "--hogs",
        type=int,
        default=os.cpu_count() or 2,
        help="CPU-bound processes (default: one per core)",
    )
    parser.add_argument("overrides", nargs="+")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    quiet = study(args.overrides, out / "quiet")
    # spawned, not forked: the parent has JAX's threads running
    hogs = [
        multiprocessing.get_context("spawn").Process(target=burn, daemon=True)
        for _ in range(args.hogs)
    ]
    for hog in hogs:
        hog.start()
    try:
        under_load = calibrate_under_load(args.overrides)
        loaded = study(
            [*args.overrides, f"compare.calibration={out / 'quiet' / 'calibration.json'}"],
            out / "loaded",
        )
    finally:
        for hog in hogs:
            hog.terminate()
            hog.join()
    text, agree = report(args.overrides, args.hogs, out, quiet, loaded, under_load)
    write_text(out / "timing_check.md", text)
    print(text)
    return 0 if agree else 1


def report(overrides, hogs: int, out: Path, quiet, loaded, under_load: dict) -> tuple[str, bool]:
    """timing_check.md's text, and whether the verdicts agree and the loaded medians lie within
    the quiet seed ranges."""
    q, loaded_summary = summary(quiet), summary(loaded)
    lines = [
        f"# Timing check: {' '.join(overrides)}",
        "",
        f"Quiet study: {out / 'quiet'}; loaded study (beside {hogs} CPU-bound processes): "
        f"{out / 'loaded'}.",
        "",
        "| A vs B | verdict, quiet | verdict, loaded | same |",
        "|---|---|---|---|",
    ]
    same = True
    for vq, vl in zip(quiet.verdicts, loaded.verdicts):
        agree = vq.verdict == vl.verdict
        same &= agree
        lines.append(
            f"| {vq.a} vs {vq.b} | {vq.verdict} | {vl.verdict} | {'yes' if agree else '**no**'} |"
        )
    lines += [
        "",
        "| variant | test loss at the budget, quiet: median [min, max] | loaded: median [min, "
        "max] | "
        "loaded median within the quiet range | iterations quiet, loaded (median) | contended "
        "quiet, loaded |",
        "|---|---|---|---|---|---|",
    ]
    within = True
    for variant in q:
        a, b = q[variant], loaded_summary.get(variant)
        if b is None:
            continue
        inside = a["low"] <= b["median"] <= a["high"]
        within &= inside
        lines.append(
            f"| {variant} | {a['median']:.4g} [{a['low']:.4g}, {a['high']:.4g}] | "
            f"{b['median']:.4g} "
            f"[{b['low']:.4g}, {b['high']:.4g}] | {'yes' if inside else '**no**'} | "
            f"{a['iterations']:.0f}, "
            f"{b['iterations']:.0f} | {a['contended']} of {a['runs']}, {b['contended']} of "
            f"{b['runs']} |"
        )
    from physgrad.files import load_json, read_own_file

    quiet_costs = load_json(read_own_file(out / "quiet" / "calibration.json", 1 << 20))
    lines += [
        "",
        "| variant | step cost, quiet calibration | under load | ratio | load average quiet, "
        "loaded |",
        "|---|---|---|---|---|",
    ]
    for variant, cost in quiet_costs["costs"].items():
        loaded_cost = under_load["costs"][variant]["step_seconds"]
        lines.append(
            f"| {variant} | {cost['step_seconds']:.4g} s | {loaded_cost:.4g} s | "
            f"{loaded_cost / cost['step_seconds']:.2f} | {quiet_costs['load_start']:.2f}, "
            f"{under_load['load_start']:.2f} |"
        )
    lines += [
        "",
        f"Verdicts {'agree' if same else 'DIFFER'}; loaded medians "
        f"{'within' if within else 'OUTSIDE'} the quiet seed ranges.",
    ]
    return "\n".join(lines) + "\n", same and within


if __name__ == "__main__":
    sys.exit(main())
