"""What the line-search rules' runs cost in wall-clock time at the budget, on the calibrated clock
with and without their evaluations charged.

L-BFGS, SSBFGS and SSBroyden end each step with optax's zoom line search, which makes as many
evaluations of the batch loss and its gradient as the step needs. A calibration that charges every
step its calibrated cost s (the leaderboard's kept clocks) lets a run whose line searches need more
evaluations later than in the calibration's steps run longer than Adam at the same budget; a
calibration with the evaluation's cost v and the e evaluations per step within s charges a run of n
steps that made E evaluations n (s - v e) + v E (docs/decisions.md, "Timing").

On each scene this script calibrates Adam and the line-search rules that apply (physgrad's own
calibration, interleaved in one process), then trains each rule at its preset for the scene's
leaderboard budget on the calibrated clock, one seed, twice: charged n s (without the evaluation
cost) and charged its evaluations; Adam once. It reports each run's wall-clock training seconds over
Adam's, its iterations and the mean evaluations per step against the calibration's e.

    python experiments/line_search_clock.py [--scenes ks,ode_control] [--out PATH]

Writes one row per scene and rule to --out (CSV; docs/evidence/line_search_clock.csv) and prints
the markdown table of docs/benchmarks.md ("Line searches on the calibrated clock")."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))

from leaderboard_scenes import SCENES  # noqa: E402  experiments/

from physgrad.files import write_text  # noqa: E402

SEARCHING = ("lbfgs", "ssbfgs", "ssbroyden")
COLUMNS = (
    "scene",
    "rule",
    "charge",
    "status",
    "iterations",
    "wall_seconds",
    "wall_over_adam",
    "evaluations_per_step",
    "calibrated_evaluations_per_step",
    "evaluation_share",
    "machine",
)


def calibration(entry, rules: list[str], seed: int) -> dict:
    """physgrad's calibration of Adam and rules on entry's scene (one process, interleaved)."""
    from omegaconf import OmegaConf

    from physgrad.configs import compose
    from physgrad.timing import calibrate

    dirs = [entry.config_dir] if entry.config_dir else []
    configs = {}
    for rule in ("adam", *rules):
        cfg = compose([*entry.overrides, f"optim={rule}"], dirs)
        plain = OmegaConf.to_container(cfg, resolve=True)
        plain.pop("hydra", None)
        configs[rule] = OmegaConf.create(plain)
    return calibrate(configs, seed)


def trained(entry, rule: str, cost: dict, charged: bool, seed: int, folder: Path) -> dict:
    """One run of rule at its preset for the scene's budget on the calibrated clock (its
    evaluations charged or not): its iterations, training seconds and evaluations per step."""
    import numpy as np

    import physgrad

    clock = [
        f"trainer.step_cost={cost['step_seconds']!r}",
        "trainer.clock=calibrated",
        f"trainer.time_budget={entry.budget:g}",
        "trainer.eval_every=1000000",
    ]
    if charged and "evaluation_seconds" in cost:
        clock += [
            f"trainer.evaluation_cost={cost['evaluation_seconds']!r}",
            f"trainer.step_evaluations={cost['step_evaluations']!r}",
        ]
    run = physgrad.run(
        *entry.overrides,
        f"optim={rule}",
        f"seed={seed}",
        "figures=false",
        *clock,
        config_dir=entry.config_dir,
        out_dir=folder / f"{entry.name}-{rule}-{'charged' if charged else 'plain'}",
        progress=False,
    )
    made = run.train.get("linesearch_evaluations") if hasattr(run.train, "get") else None
    return {
        "status": str(run.attrs["status"]),
        "iterations": int(run.attrs["iterations"]),
        "wall_seconds": float(run.attrs["train_seconds"]),
        "evaluations_per_step": float(np.mean(made)) if made is not None else float("nan"),
    }


def scene_rows(entry, seed: int, folder: Path) -> list[dict]:
    """The rows of one scene: Adam's run and each line-search rule's, charged and not."""
    from physgrad.machine import machine_attributes

    rules = [r for r in SEARCHING if r in entry.rules]
    if entry.config_dir:  # a scene from examples/: its module beside its conf folder
        sys.path.append(str(Path(entry.config_dir).resolve().parent))
    costs = calibration(entry, rules, seed)["costs"]
    machine = machine_attributes()["cpu_model"]
    adam = trained(entry, "adam", costs["adam"], False, seed, folder)
    rows = [{"rule": "adam", "charge": "step", **adam}]
    for rule in rules:
        for charged in (False, True):
            run = trained(entry, rule, costs[rule], charged, seed, folder)
            rows.append({"rule": rule, "charge": "evaluations" if charged else "step", **run})
    for row in rows:
        cost = costs[row["rule"]]
        each, per_step = cost.get("evaluation_seconds"), cost.get("step_evaluations")
        row |= {
            "scene": entry.name,
            "wall_over_adam": row["wall_seconds"] / adam["wall_seconds"],
            "calibrated_evaluations_per_step": per_step if per_step is not None else "",
            "evaluation_share": each * per_step / cost["step_seconds"] if each else "",
            "machine": machine,
        }
    return rows


def table(rows: list[dict]) -> str:
    titles = {e.name: e.title for e in SCENES}
    lines = [
        "| scene | rule | wall-clock time over Adam's: each step charged s, its evaluations "
        "charged | iterations: charged s, evaluations | evaluations per step: calibration, runs "
        "(charged s, evaluations) |",
        "|---|---|---|---|---|",
    ]
    by = {(r["scene"], r["rule"], r["charge"]): r for r in rows}
    for scene, rule in dict.fromkeys((r["scene"], r["rule"]) for r in rows):
        if rule == "adam":
            continue
        plain, charged = by[scene, rule, "step"], by[scene, rule, "evaluations"]
        calibrated = charged["calibrated_evaluations_per_step"]

        def ended(run: dict) -> str:  # a run that did not reach the budget says so
            return "" if run["status"] == "completed" else f" ({run['status']})"

        lines.append(
            f"| {titles.get(scene, scene)} | {rule} | {plain['wall_over_adam']:.2f}{ended(plain)}, "
            f"{charged['wall_over_adam']:.2f}{ended(charged)} | {plain['iterations']:,}, "
            f"{charged['iterations']:,} | {calibrated:.2f}, "
            f"{plain['evaluations_per_step']:.2f}, {charged['evaluations_per_step']:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = ",".join(e.name for e in SCENES if set(SEARCHING) & set(e.rules))
    parser.add_argument("--scenes", default=default)
    parser.add_argument("--out", type=Path, default=Path("outputs/line_search_clock.csv"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    wanted = args.scenes.split(",")
    entries = [e for e in SCENES if e.name in wanted]
    unknown = set(wanted) - {e.name for e in entries}
    if unknown:
        parser.error(f"unknown scene {sorted(unknown)}: choose from {[e.name for e in SCENES]}")
    import pandas as pd

    rows = []
    with tempfile.TemporaryDirectory(prefix="line-search-clock-") as folder:
        for entry in entries:
            rows += scene_rows(entry, args.seed, Path(folder))
            print(f"{entry.name}: done", file=sys.stderr, flush=True)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            frame = pd.DataFrame(rows)[list(COLUMNS)]
            write_text(args.out, frame.to_csv(index=False, float_format="%.6g"))
    print(table(rows))


if __name__ == "__main__":
    main()
