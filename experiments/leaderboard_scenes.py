"""The leaderboard's scenes (docs/leaderboard.md): each scene's compare overrides, the rules that
apply to it (the others with why not), its budget in calibrated seconds, and each of its tuning
studies as a compare of its own in <scene>/study-k, on the scene's kept clock.

The profile runs the current protocol: LEADERBOARD_STUDIES tuning studies, each rule tuned on its
own knobs beside its learning rate (compare.knobs=true), line searches charged per evaluation and
a knob that shapes a step's cost charged at its value (the scenes' clocks in RERUN measure both).
Its studies are kept in RERUN until every scene has all of them; the page shows the published
evidence (EVIDENCE, an earlier protocol) and the re-run's progress beside it
(docs/evidence/leaderboard/README.md).
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from evidence import CLOCK, clock_rules  # experiments/
from studies import STUDY_FOLDER, TUNE_SEED, Study, rule_config

from physgrad.bench_tables import OPTIMS as BENCH_OPTIMS

BASELINE = "adam"
LEADERBOARD_TRIALS, LEADERBOARD_STUDIES, LEADERBOARD_SEEDS = 8, 4, 10
# a rule whose step costs more than EXPENSIVE of Adam's (at its preset or at a value of its tuned
# knobs the clock timed: a tuning study may choose it) gets few steps in the budget: its verdict is
# also read at LONGER times the budget, at the settings tuned at the budget (compare.tuned_in)
EXPENSIVE, LONGER = 10.0, 4
LONGER_FOLDER, LONGER_SUFFIX = "longer-{k}", "_longer"  # its folders; its evidence: <scene>_longer
# every rule of make bench's list (conf/optim) but Adam and its backprop modes, in that order
RULES = tuple(o for o in BENCH_OPTIMS if o not in (BASELINE, "bptt", "stable_bptt"))
NO_FACTORS = "no layer factors (the controller or convolution runs many times per sample)"
JACOBIAN_OF_ALL = (
    "on 2 cores a step takes 17-19 s (the Jacobian of 256 samples' fields, 7,000 of Adam's "
    "steps): none ends within the 10 s budget, and 100 take about 1,700 s"
)


def _timed(costs: dict, rule: str) -> list[float]:
    """A rule's step costs on a clock: at its preset and at each knob value timed (rule@knob=v)."""
    return [c["step_seconds"] for name, c in costs.items() if name.split("@")[0] == rule]


@dataclass(frozen=True)
class Entry:
    """One scene of the leaderboard: its compare overrides, the rules that apply (the others with
    why not), its budget in calibrated seconds and what a job costs besides (start-up,
    compiling)."""

    name: str
    title: str
    overrides: tuple[str, ...]
    budget: float
    overhead: float
    refused: dict = field(default_factory=dict)  # rule -> why it does not apply
    config_dir: str | None = None  # a scene from examples/: its conf folder (modules beside it)

    @property
    def rules(self) -> tuple[str, ...]:
        return tuple(r for r in RULES if r not in self.refused)

    def expensive(self, clock: Path | None) -> tuple[str, ...]:
        """The scene's rules whose calibrated step costs more than EXPENSIVE of Adam's on its kept
        clock (none without one), at the rule's preset or at any value of its knobs the clock
        timed (`rule@knob=value`: a range's ends, a route's break), since a tuning study may pick
        that value (HIG's SVD below tau 1e-6 costs 16 of Adam's steps on the full-batch pendulum,
        its preset's Gram route 6.6)."""
        if clock is None:
            return ()
        costs = json.loads(clock.read_text())["costs"]
        adam = costs[BASELINE]["step_seconds"]
        # a rule the clock lacks (added since an older clock) is not known to be expensive
        return tuple(r for r in self.rules if max(_timed(costs, r), default=0) > EXPENSIVE * adam)

    def beyond_reach(self, clock: Path | None) -> dict[str, float]:
        """The expensive rules that get fewer than FEW_STEPS steps even at LONGER times the
        budget at the cheapest step the clock timed for them (any knob value), each with the
        budget FEW_STEPS of those steps take: reading them at LONGER times the budget would again
        decide a step's cost, so they are not (17-19 s a Jacobian step on the full-batch Burgers
        scene, 7,000 of Adam's: 2 end within 40 s)."""
        from physgrad.comparison.coverage import FEW_STEPS

        if clock is None:
            return {}
        costs = json.loads(clock.read_text())["costs"]
        cheapest = {r: min(_timed(costs, r), default=0.0) for r in self.expensive(clock)}
        return {
            rule: FEW_STEPS * step
            for rule, step in cheapest.items()
            if FEW_STEPS * step > LONGER * self.budget
        }

    def longer(self, k: int, clock: Path | None, costs: Path | None = None) -> Study | None:
        """Tuning study k's expensive rules and Adam at LONGER times the budget, each at the
        settings study k tuned (compare.tuned_in: its folder in the profile's root, else its
        trials kept in RERUN), on study k's evaluation seeds and clock (the scene's kept clock,
        else the one study k ran on, in its folder), as a compare of its own in
        <root>/<scene>/longer-k, without the rules beyond_reach; None where no rule is
        expensive and within reach on `costs` (a clock of the
        scene's that may lack a knob's points: the presets' costs tell which rules get few
        steps), by default the kept clock."""
        out_of_reach = self.beyond_reach(costs or clock)
        rules = tuple(r for r in self.expensive(costs or clock) if r not in out_of_reach)
        if not rules:
            return None
        if clock is None:  # study k calibrated itself: the same clock, from its folder
            clock = f"{{root}}/{self.name}/{STUDY_FOLDER.format(k=k)}/calibration.json"
        overrides = (
            *(("-cd", self.config_dir) if self.config_dir else ()),
            *self.overrides,
            f"optim={','.join((BASELINE, *rules))}",
            f"trainer.time_budget={LONGER * self.budget:g}",
            f"compare.baseline={BASELINE}",
            "compare.knobs=true",
            f"compare.seed={(k - 1) * LEADERBOARD_SEEDS}",
            f"compare.tune_seed={TUNE_SEED + k - 1}",
            f"compare.calibration={clock}",
            f"compare.tuned_in={{root}}/{self.name}/{STUDY_FOLDER.format(k=k)}",
        )
        job = LONGER * self.budget + self.overhead
        name = f"{self.name}/{LONGER_FOLDER.format(k=k)}"
        # no tuning (tune_seconds 0: the settings are study k's)
        # where study k's folder has gone with its machine, the trials kept of it stand for it
        kept = (RERUN / f"{self.name}.json", k)
        return Study(
            name,
            overrides,
            LEADERBOARD_TRIALS,
            LEADERBOARD_SEEDS,
            0.0,
            job,
            preset=False,
            tuned_from=kept,
        )

    def study(self, k: int, calibration: Path | None = None) -> Study:
        """Tuning study k (1, 2, ...) of the scene as a compare of its own, in
        <root>/<scene>/study-k: the tuning seed, trial points and evaluation seeds that study has
        in one compare of LEADERBOARD_STUDIES (compare.tune_seed + k - 1, compare.seed + (k - 1) *
        seeds), so that each part keeps its evidence whatever machine ran the others; on the
        scene's kept clock (calibration) where one was kept."""
        overrides = (
            *(("-cd", self.config_dir) if self.config_dir else ()),
            *self.overrides,
            f"optim={','.join((BASELINE, *self.rules))}",
            f"trainer.time_budget={self.budget:g}",
            f"compare.baseline={BASELINE}",
            "compare.knobs=true",
            f"compare.seed={(k - 1) * LEADERBOARD_SEEDS}",
            f"compare.tune_seed={TUNE_SEED + k - 1}",
            *((f"compare.calibration={calibration}",) if calibration else ()),
        )
        job = self.budget + self.overhead
        return Study(
            f"{self.name}/{STUDY_FOLDER.format(k=k)}",
            overrides,
            LEADERBOARD_TRIALS,
            LEADERBOARD_SEEDS,
            job,
            job,
            preset=False,
        )


DENSE = "a dense inverse Hessian of {n} parameters, above max_parameters=8192"
SCENES = (
    Entry(
        "toy",
        "toy, lambda 0.01",
        ("task=toy", "task.scale=0.01"),
        10,
        6,
    ),
    Entry("oscillator", "oscillators", ("task=oscillator",), 15, 10),
    Entry(
        "ks",
        "KS correction (small)",
        ("task=ks", "task.zero_output=true", "task.channels=8", "task.blocks=2"),
        20,
        20,  # measured: 110 evaluation jobs of 20 s in 70 min, 38 s a job
        refused={"kfac": NO_FACTORS},
    ),
    Entry(
        "guidance",
        "guidance, regular gradient",
        ("task=guidance",),
        20,
        15,
        refused={
            "kfac": NO_FACTORS,
            "ssbfgs": DENSE.format(n="13,004"),
            "ssbroyden": DENSE.format(n="13,004"),
        },
    ),
    Entry(
        "ode_control",
        "pendulum control (diffrax)",
        ("task=ode_control",),
        10,
        8,
        config_dir="examples/library_scenes/conf",
    ),
    Entry(
        "burgers_inverse",
        "Burgers inverse (exponax)",
        ("task=burgers_inverse",),
        10,
        8,
        config_dir="examples/library_scenes/conf",
    ),
    # the quasi-Newton rules' own regime: the whole training set at every step (256 of 256), so
    # that their curvature pairs and line searches see one loss throughout
    Entry(
        "ode_control_full",
        "pendulum control (diffrax), full batch",
        ("task=ode_control", "task.batch_size=256"),
        10,
        8,
        config_dir="examples/library_scenes/conf",
    ),
    Entry(
        "burgers_inverse_full",
        "Burgers inverse (exponax), full batch",
        ("task=burgers_inverse", "task.batch_size=256"),
        10,
        8,
        config_dir="examples/library_scenes/conf",
        # measured on its first clock: 17.0-18.7 s a step, at every tau the clock timed
        refused={rule: JACOBIAN_OF_ALL for rule in ("gauss_newton", "hig", "levenberg_marquardt")},
    ),
)
EVIDENCE = Path(__file__).resolve().parent.parent / "docs" / "evidence" / "leaderboard"
# the current protocol's studies and clocks, kept apart until every scene has all of its studies
RERUN = EVIDENCE / "rerun"

# what the rules' papers report on problems the leaderboard has, and the cells of the same rules in
# physgrad's setting on the scenes whose equations the papers name (the table has the rules on every
# scene; each citation checked against its arXiv abstract)
LITERATURE = (
    (
        "Self-scaled BFGS and Broyden: Kiyani et al. 2025 (arXiv 2501.16371) report orders-of-"
        "magnitude accuracy improvements over Adam and L-BFGS for physics-informed networks on "
        "Burgers, Allen-Cahn, Kuramoto-Sivashinsky and Ginzburg-Landau equations; Jnini et al. "
        "2026 (arXiv 2604.05230) apply them, with natural gradient, to Helmholtz, Stokes, inviscid "
        "Burgers, Euler and stiff ODE problems, and address scaling them to batched training.",
        (
            ("ks", "ssbfgs"),
            ("ks", "ssbroyden"),
            ("burgers_inverse", "ssbfgs"),
            ("burgers_inverse", "ssbroyden"),
            ("ode_control_full", "ssbfgs"),
            ("ode_control_full", "ssbroyden"),
            ("burgers_inverse_full", "ssbfgs"),
            ("burgers_inverse_full", "ssbroyden"),
        ),
    ),
    (
        "SOAP (Vyas et al. 2024, arXiv 2409.11321): Wang et al. 2025 (arXiv 2502.00604, "
        "gradient alignment in physics-informed networks) report 2-10x accuracy improvements over "
        "Adam and other methods on 10 PDE benchmarks.",
        (
            ("ks", "soap"),
            ("burgers_inverse", "soap"),
            ("ode_control_full", "soap"),
            ("burgers_inverse_full", "soap"),
        ),
    ),
)
WHY_IT_MAY_DIFFER = (
    "These cells are the same rules in physgrad's setting, on the scenes whose equations the "
    "papers name (the table above has them on every scene); the literature's setting is not tested "
    "here, so they neither confirm nor contradict it. The papers train physics-informed residuals "
    "over collocation points for tens of thousands of iterations (Kiyani et al. full-batch; Jnini "
    "et al. also batched); here the physics is in the loop (a solver between the network and the "
    "loss: the Burgers scene's network proposes the start that exponax's stepper carries to an "
    "observed field), every scene but the re-run's two full-batch ones draws a small minibatch "
    "of its training set afresh each step (Burgers and guidance 8 of 256 samples, the pendulum "
    "16 of 256, Kuramoto-Sivashinsky 16, the oscillators 512 of 4,096; the toy new samples): a "
    "quasi-Newton rule's curvature pairs and line search see another batch at every step, a "
    "regime in which gradients dominated by noise undo a line search and quasi-Newton updating "
    "(Bollapragada et al., ICML 2018, arXiv 1802.05374); the re-run's full-batch pendulum and "
    "Burgers scenes train on all 256 samples at every step, the quasi-Newton rules' own regime, "
    "and their cells are listed beside the mini-batch ones), and the budget is seconds of "
    "calibrated "
    "time on 2 cores (a quasi-Newton step and its line search cost several of Adam's: the "
    "iterations above)."
)


def planned_studies(runs) -> int:
    """The tuning studies a scene's kept evidence is to have (its record's `planned`, the protocol
    it was run under), or the current protocol's for evidence that does not say."""
    return runs.planned or LEADERBOARD_STUDIES


def kept_clock(entry: Entry, evidence: Path = RERUN) -> Path | None:
    """The scene's kept calibration (its step costs, measured once on a quiet machine) if it has a
    cost for every rule the scene runs now and for the cost-shaping knobs' ends (a rule added
    since, or a clock from before the knobs, calibrates the study again)."""
    path = evidence / CLOCK.format(name=entry.name)
    needed = {BASELINE, *entry.rules, *knob_ends(entry.rules)}
    return path if path.is_file() and needed <= clock_rules(path) else None


def scene_clock(entry: Entry, evidence: Path = RERUN) -> Path | None:
    """The scene's kept clock whatever costs it holds (kept_clock: only one that has them all),
    for what its presets' costs tell: which rules get few steps in the budget."""
    path = evidence / CLOCK.format(name=entry.name)
    return path if path.is_file() else None


def knob_ends(rules: tuple[str, ...]) -> set[str]:
    """The calibration's names of the rules' cost-shaping knobs at their ranges' ends
    (`soap@precondition_frequency=1`, ...: physgrad.comparison.calibration.knob_ends), which a
    clock for the profile's knob-tuning studies must have."""
    from physgrad.optim.capabilities import capabilities, cost_points

    names = set()
    for rule in rules:
        kind = capabilities(rule_config(rule))
        for key, low, high in kind.knobs if kind.cost_knob else ():
            if key == kind.cost_knob[0]:
                names |= {f"{rule}@{key}={value}" for value in cost_points(kind, low, high)}
    return names


def scene_studies(entry: Entry) -> tuple[Study, ...]:
    """A scene's parts in the order they run: its tuning studies, then each one's expensive rules
    at the longer budget (which read the tuning study's folder)."""
    clock, costs = kept_clock(entry), scene_clock(entry)
    studies = tuple(entry.study(k, clock) for k in range(1, LEADERBOARD_STUDIES + 1))
    longer = (entry.longer(k, clock, costs) for k in range(1, LEADERBOARD_STUDIES + 1))
    return studies + tuple(s for s in longer if s is not None)


# the profile's studies: every tuning study of every scene, each a compare of its own
LEADERBOARD = tuple(study for entry in SCENES for study in scene_studies(entry))


def leaderboard_parts() -> list[list[Study]]:
    """The profile's parts: one study each, in LEADERBOARD's order. A longer study evaluates what
    its tuning study chose, so it may start only once that study has finished (a part of several
    runs them one after the other, whatever their state), and each finished study is kept alone."""
    from studies import chunks

    return chunks(LEADERBOARD, limit_seconds=0)


def environment(study: Study) -> dict | None:
    """The environment a study's command runs in: a scene from examples/ imports its modules from
    the folder above its conf/ (as from that folder: examples/library_scenes/README.md)."""

    entry = next((e for e in SCENES if e.name == study.name.split("/")[0]), None)
    if entry is None or entry.config_dir is None:
        return None
    modules = str(Path(entry.config_dir).resolve().parent)
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "PYTHONPATH": modules + (os.pathsep + path if path else "")}


def where_scene_runs(entry: Entry) -> str:
    """The leaderboard profile's parts that run a scene's studies, and their expected hours on 2
    cores (an estimate, as the plan's)."""
    used = [
        (k, seconds) for k, by_scene in _part_seconds() if (seconds := by_scene.get(entry.name))
    ]
    if not used:
        return "no part runs it"
    which = ", ".join(str(k) for k, _ in used)
    hours = sum(seconds for _, seconds in used) / 3600
    return f"leaderboard part{'s' if len(used) > 1 else ''} {which}, about {hours:.1f} h on 2 cores"


@functools.lru_cache(maxsize=1)
def _part_seconds() -> tuple[tuple[int, dict[str, float]], ...]:
    """Each part of the profile (its number) with its expected seconds per scene, planned once."""
    found = []
    for k, part in enumerate(leaderboard_parts(), 1):
        by_scene: dict[str, float] = {}
        for study in part:
            scene = study.name.split("/")[0]
            by_scene[scene] = by_scene.get(scene, 0.0) + study.seconds()
        found.append((k, by_scene))
    return tuple(found)
