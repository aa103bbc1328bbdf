"""What PSGD Kron's steps cost along a run, against what the calibrated clock charges them.

PSGD Kron updates its preconditioner at step t with probability p_t (psgdax's schedule: 1 for the
first 500 steps, then exp(-0.001 (t - 500)), at least 0.03). A calibration without the update's
cost (the leaderboard's kept clocks) times the rule's first steps, where p_t = 1 (it takes fewer
than 500 of them on every leaderboard scene but the toy), and the clock charges every step that
cost (a calibration with it charges the expected cost: docs/decisions.md). Later steps update less
often: with a step costing c + p u at update probability p, a run of N steps costs
N (c + mean_{t<N} p_t u) against the N (c + u) charged, so it takes (c + mean p u) / (c + u) of
the wall-clock time its budget assumes.

This script compiles the rule's step as `physgrad run` does (one seed: a real branch, where several
seeds trained together compute both branches at every step) on each leaderboard scene twice, runs
one copy on to step ADVANCED (p = 0.03), and times Adam's step, the fresh copy (p = 1) and the
advanced one in turn, one burst each per round, as the calibration does; c and u follow from the two
PSGD costs. It then runs the calibration itself (physgrad.timing.calibrate of Adam and PSGD Kron),
which sets the step counter instead of running a copy on, and sets its share of the update beside
this one. PSGD Kron's iterations at the budget come from the kept evidence
(docs/evidence/leaderboard/<scene>.json), the wall-clock ratio its tuning studies recorded (runs
trained alone, median over the studies, on the machine that ran them) is set beside the prediction.

    python experiments/psgd_clock.py [--scenes toy,ks] [--out outputs/psgd_clock.json]

Prints one markdown row per scene (docs/benchmarks.md, "PSGD Kron on the calibrated clock")."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))

from leaderboard_scenes import EVIDENCE, SCENES  # noqa: E402  experiments/

from physgrad.files import write_text
from physgrad.optim.psgd import annealed_probability  # noqa: E402

RULE = "psgd_kron"
ADVANCED = 5000  # steps run before timing: p_t = 0.03 from step 4,007 on
FRESH_STEPS = 400  # the fresh copy's timed steps in all, so that its p_t stays 1
ROUNDS = 20


def measure(entry, seed: int) -> dict:
    """The step costs (0.2 quantile of bursts timed in turn) of Adam and of PSGD Kron fresh and
    advanced on entry's scene."""
    from physgrad.configs import compose
    from physgrad.machine import load_average, machine_attributes
    from physgrad.timing import CALIBRATION_QUANTILE, calibrate, compiled_step, interleaved_times

    dirs = [entry.config_dir] if entry.config_dir else []
    if entry.config_dir:  # a scene from examples/: its module beside its conf folder
        sys.path.append(str(Path(entry.config_dir).resolve().parent))
    common = [*entry.overrides, f"trainer.time_budget={entry.budget:g}"]
    configs = {optim: compose([*common, f"optim={optim}"], dirs) for optim in ("adam", RULE)}
    steps = {
        name: compiled_step(configs[optim], [seed])[-1]
        for name, optim in (("adam", "adam"), ("fresh", RULE), ("advanced", RULE))
    }
    for _ in range(ADVANCED):
        steps["advanced"]()
    burst = FRESH_STEPS // (ROUNDS + 1)  # the +1: the untimed warm-up burst

    def bursts(step):
        def run() -> None:
            for _ in range(burst):
                step()

        return run

    load = load_average()
    times = interleaved_times([bursts(s) for s in steps.values()], ROUNDS, 0.0)
    costs = {
        name: float(np.quantile(np.asarray(t[:ROUNDS]) / burst, CALIBRATION_QUANTILE))
        for name, t in zip(steps, times)
    }
    # the calibration's own measurement: the counter set to the start and to the floor
    calibrated = calibrate(configs, seed)["costs"][RULE]
    return costs | {
        "calibration_update_share": calibrated["update_seconds"] / calibrated["step_seconds"],
        "machine": machine_attributes()["cpu_model"],
        "load": [load, load_average()],
    }


def row(entry, measured: dict) -> dict:
    """c and u of PSGD Kron's step (over Adam's), the mean p_t over its iterations at the budget,
    the wall-clock ratio to Adam's that the clock's charge predicts and the one recorded."""
    from leaderboard_detail import wall_ratios

    about = json.loads((EVIDENCE / f"{entry.name}.json").read_text())
    iterations = int(about["iterations"][RULE])
    adam, fresh, advanced = measured["adam"], measured["fresh"], measured["advanced"]
    floor = float(annealed_probability(np.array([ADVANCED]))[0])
    update = (fresh - advanced) / (1 - floor)  # u from c + u = fresh, c + floor u = advanced
    plain = fresh - update
    p_mean = float(np.mean(annealed_probability(np.arange(1, max(iterations, 1) + 1))))
    return {
        "scene": entry.name,
        "iterations": iterations,
        "fresh_over_adam": fresh / adam,
        "advanced_over_adam": advanced / adam,
        "update_share": update / fresh,
        "calibration_update_share": measured["calibration_update_share"],
        "mean_probability": p_mean,
        "predicted_wall_ratio": (plain + p_mean * update) / fresh,
        "recorded_wall_ratio": wall_ratios(about).get(RULE),
        "measured_on": measured["machine"],
        "load": measured["load"],
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| scene | PSGD Kron's iterations at the budget | its step over Adam's: fresh (p = 1), at "
        f"step {ADVANCED:,} (p = 0.03) | the update's share of a fresh step: run on, calibration "
        "(counter set) | mean p over the run | wall-clock time over Adam's: predicted, recorded by "
        "the studies |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        recorded = r["recorded_wall_ratio"]
        lines.append(
            f"| {r['scene']} | {r['iterations']:,} | {r['fresh_over_adam']:.2f}, "
            f"{r['advanced_over_adam']:.2f} | {r['update_share']:.0%}, "
            f"{r['calibration_update_share']:.0%} | "
            f"{r['mean_probability']:.2f} | {r['predicted_wall_ratio']:.2f}, "
            f"{'not recorded' if recorded is None else f'{recorded:.2f}'} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(e.name for e in SCENES if RULE in e.rules))
    parser.add_argument("--out", type=Path, default=Path("outputs/psgd_clock.json"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    wanted = args.scenes.split(",")
    entries = [e for e in SCENES if e.name in wanted]
    unknown = set(wanted) - {e.name for e in entries}
    if unknown:
        parser.error(f"unknown scene {sorted(unknown)}: choose from {[e.name for e in SCENES]}")
    rows = []
    for entry in entries:
        rows.append(row(entry, measure(entry, args.seed)))
        print(f"{entry.name}: {json.dumps(rows[-1])}", file=sys.stderr, flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.out, json.dumps(rows, indent=1))
    print(table(rows))


if __name__ == "__main__":
    main()
