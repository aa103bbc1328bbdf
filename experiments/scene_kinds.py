"""What kind of problem each scene of the claims and the leaderboard is, so that a reader can match
it to their own: whether a network acts inside an unrolled loop, the batch against the training
set, the network's parameters (measured by building the scene, kept in
docs/evidence/scenes.csv), and what a step costs (Adam's, and the Jacobian rules' in Adam steps,
from the calibration kept beside the page's evidence).

python experiments/scene_kinds.py --keep docs/evidence/scenes.csv builds every scene (a minute on 2
cores, no training) and writes the table; the pages read it.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from physgrad.readout import fmt

KINDS = Path(__file__).resolve().parent.parent / "docs" / "evidence" / "scenes.csv"
JACOBIAN_RULES = ("gauss_newton", "hig")  # a step through the network-through-physics Jacobian
COLUMNS = ("scene", "loop", "unroll", "batch", "train_size", "parameters")


@dataclass(frozen=True)
class SceneKind:
    """A scene as both pages name it: its key, its title and the overrides (and config folder) that
    build it."""

    key: str
    title: str
    overrides: tuple[str, ...]
    config_dir: str | None = None
    # where the Scene interface cannot tell it: a solver library's own loop
    loop: str = ""


SCENES = (
    SceneKind("toy", "toy", ("task=toy",), loop="no solver"),
    SceneKind("oscillator", "coupled oscillators", ("task=oscillator",)),
    SceneKind("quantum", "quantum dipole", ("task=quantum",)),
    SceneKind("poisson", "Poisson inverse", ("task=poisson",)),
    SceneKind("cart_4", "multi-pole cart (4 poles)", ("task=multicart", "task.poles=4")),
    SceneKind("quantum_control", "quantum control", ("task=quantum_control",)),
    SceneKind("guidance", "guidance by repulsion", ("task=guidance",)),
    SceneKind("ks", "KS (the claims' network)", ("task=ks", "task.zero_output=true")),
    SceneKind(
        "ks_small",
        "KS correction (small)",
        ("task=ks", "task.zero_output=true", "task.channels=8", "task.blocks=2"),
    ),
    SceneKind(
        "ode_control",
        "pendulum control (diffrax)",
        ("task=ode_control",),
        "examples/library_scenes/conf",
        "closed, inside diffrax's solve",
    ),
    SceneKind(
        "burgers_inverse",
        "Burgers inverse (exponax)",
        ("task=burgers_inverse",),
        "examples/library_scenes/conf",
        "open: the network sets the start of exponax's stepping",
    ),
)


def measure(kind: SceneKind) -> dict:
    """The scene's row: its loop (closed: a network acts on the state at every step; open: its
    controls or start are set before the unroll; one solve: no time stepping; or the kind's own
    words), unroll length, batch, training-set size (empty: a fresh sample every batch) and
    parameters."""
    import jax

    from physgrad.configs import compose
    from physgrad.job_spec import checked
    from physgrad.tasks import build_scene

    dirs = [kind.config_dir] if kind.config_dir else []
    if kind.config_dir and str(Path(kind.config_dir).parent) not in sys.path:
        sys.path.insert(0, str(Path(kind.config_dir).parent))  # its scenes' modules
    cfg = compose(list(kind.overrides), dirs)
    spec = checked(cfg)
    scene = build_scene(spec.task, jax.random.PRNGKey(0), spec.unroll)
    params = scene.init_params(jax.random.PRNGKey(1))
    loop = "one solve" if scene.dynamics is None else "closed" if scene.closed_loop else "open"
    return {
        "scene": kind.key,
        "loop": kind.loop or loop,
        "unroll": scene.unroll or "",
        "batch": int(spec.task["batch_size"]),
        "train_size": scene.train_size or "",
        "parameters": sum(int(leaf.size) for leaf in jax.tree_util.tree_leaves(params)),
    }


def keep(path: Path) -> None:
    import pandas as pd

    from physgrad.files import replace_file

    rows = [measure(kind) for kind in SCENES]
    buffer = io.StringIO()
    pd.DataFrame(rows, columns=list(COLUMNS)).to_csv(buffer, index=False)
    replace_file(path, buffer.getvalue().encode())


def read_kinds(path: Path) -> dict[str, dict]:
    """The kept table as scene -> row (text values); {} where there is none. The file is data:
    read through the read door's bounds (evidence.read_table) and checked column by column."""
    from evidence import read_table

    from physgrad.errors import UserError

    if not path.is_file():
        return {}
    table = read_table(path, dtype=str, keep_default_na=False)
    if list(table.columns) != list(COLUMNS):
        raise UserError(f"{path}: columns {list(table.columns)}, not {list(COLUMNS)}")
    for column in ("batch", "parameters"):
        if not table[column].str.fullmatch(r"\d{1,12}").all():
            raise UserError(f"{path}: a {column} that is not a whole number")
    return {row["scene"]: row for row in table.to_dict("records")}


def _step_costs(calibration: Path) -> tuple[str, str]:
    """(Adam's step in ms, the Jacobian rules' step in Adam steps) from a kept calibration."""
    try:
        costs = json.loads(calibration.read_text())["costs"]
        adam = float(costs["adam"]["step_seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return "-", "-"
    jacobian = [
        float(costs[r]["step_seconds"]) / adam
        for r in JACOBIAN_RULES
        if isinstance(costs.get(r), dict) and "step_seconds" in costs[r]
    ]
    ratio = f"{fmt(min(jacobian))}-{fmt(max(jacobian))}" if jacobian else "-"
    if jacobian and fmt(min(jacobian)) == fmt(max(jacobian)):
        ratio = fmt(jacobian[0])
    return fmt(adam * 1e3), ratio


CONF = Path(__file__).resolve().parent.parent / "conf"


def rule_batches(kind: SceneKind, batch: int) -> str:
    """ " (gauss_newton, hig: 16)": the rules whose preset on this scene
    (conf/tuning/<task>_<rule>.yaml, applied to every run of the rule there) sets another batch
    than the scene's (the HIG paper's quantum dipole: HIG at 16 where Adam is at 256); "" where
    none does."""
    from omegaconf import OmegaConf

    task = _task(kind.overrides)
    folders = [Path(kind.config_dir) if kind.config_dir else CONF]
    rules = {p.stem for f in (*folders, CONF) for p in (f / "optim").glob("*.yaml")}
    by_batch: dict[int, list[str]] = {}
    for folder in folders:
        for path in sorted((folder / "tuning").glob(f"{task}_*.yaml")):
            rule = path.stem[len(task) + 1 :]
            if rule not in rules:  # quantum_control_adam is quantum_control's, not quantum's
                continue
            found = OmegaConf.select(OmegaConf.load(path), "task.batch_size")
            if found is not None and int(found) != batch:
                by_batch.setdefault(int(found), []).append(rule)
    said = "; ".join(f"{', '.join(r)}: {b:,}" for b, r in sorted(by_batch.items()))
    return f" ({said})" if said else ""


def kinds_table(rows: list[tuple[str, str, Path | None]], kinds: dict[str, dict]) -> str:
    """A page's table of its scenes' kinds: rows are (scene key, the page's name for it, the
    calibration kept for it or None)."""
    lines = [
        "| scene | loop (steps) | batch of the training set | parameters | Adam's step (ms, "
        "calibrated) | a Jacobian rule's step (Gauss-Newton, HIG, at their own settings), in "
        "Adam steps |",
        "|---|---|---|---|---|---|",
    ]
    for key, name, calibration in rows:
        row = kinds.get(key)
        if row is None:
            continue
        loop = row["loop"] + (f" ({row['unroll']})" if row["unroll"] else "")
        size = row["train_size"]
        batch = f"{int(row['batch']):,} of {f'{int(size):,}' if size else 'fresh samples'}"
        kind = next((k for k in SCENES if k.key == key), None)  # None: a table's own scene
        batch += rule_batches(kind, int(row["batch"])) if kind else ""
        adam, jacobian = _step_costs(calibration) if calibration else ("-", "-")
        lines.append(
            f"| {name} | {loop} | {batch} | {int(row['parameters']):,} | {adam} | {jacobian} |"
        )
    return "\n".join(lines) + "\n"


def _task(overrides) -> str:
    return next((o.partition("=")[2] for o in overrides if o.startswith("task=")), "")


def _budget(overrides) -> str:
    for o in overrides:
        key, _, value = o.partition("=")
        if key == "trainer.time_budget":
            return f"{value} s"
        if key == "trainer.iterations":
            return f"{int(value):,} iterations"
    return "?"


def both_pages_line(page: str) -> str:
    """One line, for the claims page or the leaderboard (page), on the scenes both show and why
    their verdicts may differ: the question, the rules compared, the tuning studies, the budgets."""
    from leaderboard_scenes import SCENES
    from studies import PROFILES

    claims = {}
    for study in PROFILES["claims"]:
        if study.studies > 1:
            claims.setdefault(_task(study.overrides), []).append(_budget(study.overrides))
    shared = [(e, claims[_task(e.overrides)]) for e in SCENES if _task(e.overrides) in claims]
    if not shared:
        return ""
    budgets = "; ".join(
        f"{e.title}: {' and '.join(dict.fromkeys(b))} in the claims, {e.budget:g} s on the "
        "leaderboard"
        for e, b in shared
    )
    other = "docs/claims.md" if page == "leaderboard" else "docs/leaderboard.md"
    return (
        f"Scenes on both this page and {other} ({budgets}): the claims ask a paper's question "
        "with the rules the paper compares, in 4 tuning studies, at budgets set from the paper's "
        "and with the scene's settings the paper uses, which may differ from the leaderboard's "
        "(a network's size, a control cost: the same scene, not the same problem); the "
        "leaderboard compares every rule with "
        "Adam in its own tuning studies (the leaderboard says how many) at its own calibrated "
        "budgets, with Holm's "
        "correction over a scene's comparisons. A verdict may differ between the pages by budget, "
        "by the scene's settings, by the number of studies and by the correction, without either "
        "being wrong."
    )


# the claims' scenes (experiments/scene_kinds.py) and the study whose kept clock gives their step
# costs (none: the claims' budgets there are iterations)
CLAIM_SCENES = (
    ("toy", "toy_0.01"),
    ("oscillator", "oscillator"),
    ("quantum", "quantum"),
    ("poisson", "poisson_continue"),
    ("cart_4", None),
    ("quantum_control", None),
    ("guidance", None),
    ("ks", None),
)


def scene_kinds_block(root: Path) -> str:
    """The claims' scenes by kind, so that a reader can match them to their own problem, and the
    line on the scenes the leaderboard shows too."""
    kinds = read_kinds(KINDS)
    rows = [
        (
            key,
            next(k.title for k in SCENES if k.key == key),
            clock and root / f"{clock}.calibration.json",
        )
        for key, clock in CLAIM_SCENES
    ]
    return (
        "\nThe scenes by kind (a step cost only where a budget is a time; "
        "docs/evidence/scenes.csv):\n\n"
        + kinds_table(rows, kinds)
        + "\n"
        + both_pages_line("claims")
        + "\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, required=True, help="the table to write")
    keep(parser.parse_args(argv).keep)
    return 0


if __name__ == "__main__":
    sys.exit(main())
