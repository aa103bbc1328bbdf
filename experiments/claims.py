"""The papers' claims, each decided from the runs of the claims profile (`make reproduce-figures PROFILE=claims`)
by one verdict rule, into claims.md; and where HIG pays off against Adam (payoff.png).

Usage: python experiments/claims.py RUNS_FOLDER [OUT_FOLDER]
(RUNS_FOLDER holds the profile's sweep folders, e.g. outputs/experiments/claims.)

The verdict rule is physgrad's own (physgrad.verdict; docs/protocol.md), the same as `physgrad compare`'s:
- Seeds are paired (same data and initial network for A and B). The budget X is the shortest end of training
  among the comparison's runs that did not diverge (iterations, or training seconds at equal wall-clock: a run
  stopped by its time budget ends at that budget). Each run's loss at X is its last evaluation at or before X:
  the step that crosses a time budget counts against its variant. A run that diverged by X (or whose held-out
  loss is NaN, or grew past 1e4 times its first value) counts as an infinite loss; both diverged is a tie.
- Per seed log(loss A / loss B): its median with a bootstrap 95% interval and a Wilcoxon signed-rank test
  (each comparison on its own: its runs and budget are its own). **holds**: A better (the interval below 1/1.1 and p < 0.05);
  **does not hold**: B better (above 1.1) or equivalent (within 10%, two one-sided tests); **not settled**
  otherwise, which includes every comparison with fewer than 6 paired seeds (the test cannot reach p < 0.05).
  The verdict at half the budget and the ratio's movement are shown beside it, in both directions.
- A claim made of several comparisons holds if every one holds, does not hold if any does not, and is not
  settled otherwise.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from physgrad.report import run_config
from physgrad.results import Run, find_results, read_run
from physgrad.verdict import A_BETTER, B_BETTER, EQUIVALENT, Curve, compare_variants

HOLDS, FAILS, OPEN = "holds", "does not hold", "not settled"
VERDICT = {A_BETTER: HOLDS, B_BETTER: FAILS, EQUIVALENT: FAILS}  # the package's verdict on "A lower" -> the claim's


@dataclass(frozen=True)
class Decision:
    verdict: str
    pairs: int
    wins: int
    ratio: float  # median loss(A) / loss(B) over the pairs at the budget
    half_ratio: float  # the same at half the budget
    budget: float
    ratios: tuple[float, ...] = ()
    why: str = ""


def decide(better: dict[int, Curve], worse: dict[int, Curve]) -> Decision:
    """The claim that `better` reaches the lower loss, decided by physgrad's verdict rule (module docstring)."""
    ends = [c.end for c in (*better.values(), *worse.values()) if not c.diverged]
    budget = min(ends) if ends else max((c.end for c in (*better.values(), *worse.values())), default=math.nan)
    if not (better and worse) or not math.isfinite(budget):
        return Decision(OPEN, 0, 0, math.nan, math.nan, budget, why="0 paired seeds")
    (result,) = compare_variants({"A": better, "B": worse}, budget)
    p, half = result.at[1.0], result.at[0.5]
    verdict, why = result.verdicts[1.0]
    why = (f"{verdict}: {why}; at half the budget {result.verdicts[0.5][0]}"
           f"{'' if result.stable else ' (not stable)'}, {result.trend}")
    return Decision(VERDICT.get(verdict, OPEN), p.pairs, p.wins_a, p.ratio, half.ratio, budget,
                    tuple(math.exp(r) if abs(r) < 700 else (0.0 if r < 0 else math.inf) for r in p.log_ratios
                          if not math.isnan(r)), why)


def combine(verdicts: list[str]) -> str:
    if verdicts and all(v == HOLDS for v in verdicts):
        return HOLDS
    return FAILS if FAILS in verdicts else OPEN


# --- reading runs ---------------------------------------------------------------------------------------


def facts(run: Run) -> dict[str, str]:
    """What a selector can match: the resolved configuration (dotted keys) and the run's task, variant, seed
    and unroll length, as strings."""
    found = {key: str(value) for key, value in run_config(run).items()}
    found.update({key: str(run.attrs.get(key)) for key in ("task", "seed", "unroll")})
    found["variant"] = run.variant
    return found


def curve(run: Run, axis: str) -> Curve:
    """The run's held-out loss on the shared axis (a run started from another's network continues its axis).
    On the time axis a run stopped by its time budget ends at the budget: the budget is checked after each
    step, so its final evaluation, up to one (possibly long) step later, is the loss at the budget."""
    offset = run.offset(axis)
    x = np.asarray(run.eval.get(axis, np.empty(0)), float) + offset
    # a train row's iteration is the step's index, an evaluation's the steps done: the run ends one after
    end = run.final("train", axis) + (1 if axis == "iteration" else 0) + offset
    if not math.isfinite(end):
        end = offset
    budget = run_config(run).get("trainer.time_budget")
    if axis == "wall_time" and run.attrs.get("stopped_by") == "time_budget" and budget is not None:
        end = min(end, float(budget) + offset)  # its evaluation after the crossing step is not read at the budget
    return Curve(x, np.asarray(run.eval.get("loss", np.empty(0)), float), end, run.attrs.get("status") == "diverged")


# --- the claims -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Comparison:
    setting: str  # what the comparison is at, e.g. "4 poles"
    better: dict[str, str]  # selector of the side the claim says is lower
    worse: dict[str, str]
    label: tuple[str, str]  # the two sides' names in the table


@dataclass(frozen=True)
class Claim:
    name: str
    paper: str  # the claim as the paper states it, and where
    figure: str  # the figure of the reproduction it belongs to (outputs/figures/<figure>/)
    image: str
    folders: tuple[str, ...]  # sweep folders under the profile's runs folder
    axis: str  # "iteration" (equal updates) or "wall_time" (equal training seconds, one job at a time)
    comparisons: tuple[Comparison, ...]
    common: dict[str, str] = field(default_factory=dict)  # selector both sides share


def _vs(setting: str, key: str, a: str, b: str, **common) -> Comparison:
    return Comparison(setting, {key: a, **common}, {key: b, **common}, (a, b))


CLAIMS = (
    Claim("oscillators: HIG below Adam and Gauss-Newton",
          "HIG paper (Schnell, Holl and Thuerey, ICLR 2022), Figure 1: on the coupled oscillators HIG "
          "reaches a lower test loss than Adam and Gauss-Newton in the same wall-clock time",
          "fig1_oscillator", "loss_vs_time.png", ("fig1_oscillator",), "wall_time",
          (_vs("2 oscillators", "optim.name", "hig", "adam"),
           _vs("2 oscillators", "optim.name", "hig", "gauss_newton"))),
    Claim("quantum dipole: HIG below Adam",
          "HIG paper, Figure 2: on quantum dipole control HIG beats Adam in wall-clock time",
          "fig2_quantum", "loss_vs_time.png", ("fig2_quantum",), "wall_time",
          (_vs("quantum dipole", "optim.name", "hig", "adam"),)),
    Claim("Poisson: HIG after Adam improves further than Adam",
          "HIG paper, Figure 3: continuing an Adam-trained network with HIG lowers the loss further "
          "than continuing with Adam",
          "fig3_poisson", "loss_vs_time.png", ("fig3_poisson_continue",), "wall_time",
          (_vs("from Adam's network", "optim.name", "hig", "adam"),)),
    Claim("cart: C keeps solving as poles are added, R degrades",
          "StableBPTT paper (Schnell and Thuerey, ICLR 2024), Figure 4: on the multi-pole cart the "
          "combined gradient C keeps its performance as poles are added while regular BPTT (R) degrades",
          "fig4_multicart", "loss_vs_iteration.png", ("fig4_multicart",), "iteration",
          tuple(_vs(f"{n} poles", "optim.backprop", "C", "R", **{"task.poles": str(n)}) for n in (3, 4))),
    Claim("quantum control: C below R at higher target levels",
          "StableBPTT paper, Figure 5: on quantum control C is better than R for the higher target "
          "levels", "fig5_quantum_control", "loss_vs_iteration.png", ("fig5_quantum_control",), "iteration",
          tuple(_vs(f"level {n}", "optim.backprop", "C", "R", **{"task.target_level": str(n)}) for n in (4, 5))),
    Claim("guidance: C below R at small control cost",
          "StableBPTT paper, Figure 8: on guidance by repulsion C is better than R for small "
          "regularisation coefficients rc", "fig8_guidance", "loss_vs_iteration.png", ("fig8_guidance",),
          "iteration",
          tuple(_vs(f"rc {c}", "optim.backprop", "C", "R", **{"task.control_cost": c}) for c in ("0.01", "0.001"))),
    Claim("KS: correction beats prediction",
          "Unrolling study (List et al. 2025), Kuramoto-Sivashinsky: correcting a coarse solver "
          "gives a lower error than predicting the whole step with the network",
          "fig9_ks", "ks_unroll.png", ("fig9_ks", "fig9_ks_predict"), "iteration",
          (_vs("WIG, m = 3", "task.stepper", "correct", "predict", **{"task.training": "WIG", "unroll": "3"}),)),
    Claim("KS: WIG best, NOG close, ONE worse",
          "Unrolling study, Kuramoto-Sivashinsky: training with gradients through the unroll (WIG) gives the "
          "lowest error, without them (NOG) comes close, one-step training (ONE) is worse (read here as the order "
          "WIG < NOG < ONE)",
          "fig9_ks", "ks_unroll.png", ("fig9_ks",), "iteration",
          tuple(_vs("correct, m = 3", "task.training", better, worse, **{"task.stepper": "correct", "unroll": "3"})
                for better, worse in (("WIG", "NOG"), ("WIG", "ONE"), ("NOG", "ONE")))),
    Claim("KS: a best unroll length",
          "Unrolling study, Kuramoto-Sivashinsky: the error has a minimum at an intermediate unroll length (the "
          "study trains at m = 3): longer is not always better",
          "fig9_ks", "ks_unroll.png", ("fig9_ks", "fig9_ks_unroll"), "iteration",
          tuple(_vs("correct, WIG", "unroll", "3", m, **{"task.stepper": "correct", "task.training": "WIG"})
                for m in ("1", "8"))),
    Claim("toy: HIG converges where Adam and Gauss-Newton stall",
          "HIG paper, toy example (also the PBDL book's HIG chapter): on the badly scaled toy with "
          "lambda = 0.01 HIG converges while Adam and Gauss-Newton stall",
          "toy_scaling", "loss_vs_time.png", ("toy_scaling",), "wall_time",
          (_vs("lambda 0.01", "optim.name", "hig", "adam"), _vs("lambda 0.01", "optim.name", "hig", "gauss_newton"))),
)


class AmbiguousRuns(ValueError):
    """Two runs of one seed match one side of a comparison (e.g. runs of an earlier budget left in the folder)."""


def select(runs: list[Run], selector: dict[str, str]) -> dict[int, Run]:
    """Completed or diverged runs matching every key of the selector, by seed; AmbiguousRuns if a seed has two."""
    chosen = {}
    for run in runs:
        known = facts(run)
        if run.attrs.get("status") in ("completed", "diverged") and all(known.get(k) == v for k, v in selector.items()):
            seed = int(run.attrs["seed"])
            if seed in chosen:
                raise AmbiguousRuns(f"seed {seed} matches {chosen[seed].path.parent} and {run.path.parent}: "
                                    "move the one that does not belong to this profile out of the folder")
            chosen[seed] = run
    return chosen


def load(root: Path, folders) -> list[Run]:
    """Every readable run under the folders (an unreadable file is named on stderr and left out)."""
    existing = [root / name for name in folders if (root / name).exists()]
    runs = []
    for path in find_results(existing) if existing else []:
        try:
            runs.append(read_run(path))
        except ValueError as error:
            print(f"claims: left out {path}: {error}", file=sys.stderr)
    return runs


# --- writing ----------------------------------------------------------------------------------------------


def _g(value: float) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.3g}"


def _ratio(value: float, a: str, b: str) -> str:
    """A median ratio A / B, saying which side's divergence made it 0 or infinite."""
    return {0.0: f"0 ({b} diverged)", math.inf: f"inf ({a} diverged)"}.get(value, _g(value))


def _spread(values: list[float]) -> str:
    """median (min-max) over the seeds that did not diverge, and how many diverged."""
    if not values:
        return "no runs"
    finite = [v for v in values if math.isfinite(v)]
    text = ""
    if finite:
        text = _g(float(np.median(finite))) + (f" ({_g(min(finite))}-{_g(max(finite))})" if len(finite) > 1 else "")
    if len(finite) < len(values):
        text = (text + "; " if finite else "") + f"{len(values) - len(finite)} of {len(values)} diverged"
    return text


def _budget(axis: str, value: float) -> str:
    if not math.isfinite(value):
        return "-"
    return f"{value:.0f} s" if axis == "wall_time" else f"{value:.0f} iterations"


def measure(claim: Claim, runs: list[Run]) -> tuple[str, list[dict]]:
    """The claim's verdict and one row per comparison."""
    rows = []
    for comparison in claim.comparisons:
        try:
            better, worse = ({s: curve(r, claim.axis) for s, r in select(runs, {**claim.common, **side}).items()}
                             for side in (comparison.better, comparison.worse))
        except AmbiguousRuns as error:
            rows.append({"comparison": comparison, "better": [], "worse": [],
                         "decision": Decision(OPEN, 0, 0, math.nan, math.nan, math.nan, why=str(error))})
            continue
        decision = decide(better, worse)
        rows.append({"comparison": comparison, "decision": decision,
                     "better": [c.at(decision.budget) for c in better.values()],
                     "worse": [c.at(decision.budget) for c in worse.values()]})
    return combine([row["decision"].verdict for row in rows]), rows


def claim_rows(claim: Claim, runs: list[Run]) -> list[str]:
    """The claim's rows of the claims table, one per comparison."""
    lines = []
    verdict, rows = measure(claim, runs)
    metric = ("held-out loss at equal training wall-clock (one seed per job, one job at a time)"
              if claim.axis == "wall_time" else "held-out loss at equal iterations")
    for i, row in enumerate(rows):
        c, d = row["comparison"], row["decision"]
        step = d.verdict
        if d.why:
            step += f": {d.why}"
        first = i == 0
        lines.append(
            f"| {f'**{claim.name}: {verdict}**. {claim.paper}' if first else ''} "
            f"| {metric + ' at ' + _budget(claim.axis, d.budget) if first else _budget(claim.axis, d.budget)} "
            f"| {c.setting} | {c.label[0]}: {_spread(row['better'])} | {c.label[1]}: {_spread(row['worse'])} "
            f"| {d.wins} of {d.pairs}, {_ratio(d.ratio, *c.label)}; {_ratio(d.half_ratio, *c.label)} | {step} "
            f"| {f'[{claim.figure}]({claim.figure}/{claim.image})' if first else ''} |")
    return lines


def claims_table(root: Path) -> str:
    lines = ["| claim (paper, where) | metric | setting | A: median (min-max) | B: median (min-max) | "
             "paired: A lower in k of n, median A/B; the same at half the budget | verdict | figure |",
             "|---|---|---|---|---|---|---|---|"]
    for claim in CLAIMS:
        lines += claim_rows(claim, load(root, claim.folders))
    return "\n".join(lines) + "\n"


# --- where HIG pays off -----------------------------------------------------------------------------------

PAYOFF_FOLDERS = ("fig1_oscillator", "hig_payoff")
# on the evaluation grid of a time-budget run (one every budget / 20: physgrad.runner.EVALUATIONS_PER_BUDGET), so
# that a slow variant's reading is not an evaluation made long before the cut
PAYOFF_FRACTIONS = (1 / 10, 1 / 4, 1 / 2, 1)


def step_costs(root: Path) -> dict[int, dict[str, float]]:
    """Median training seconds per step of HIG and Adam on the oscillators, per chain length."""
    runs = [r for r in load(root, PAYOFF_FOLDERS) if r.attrs.get("task") == "oscillator"]
    costs = {}
    for run in runs:
        n, name = int(facts(run).get("task.oscillators", 0)), facts(run).get("optim.name")
        costs.setdefault(n, {}).setdefault(name, []).append(run.seconds_per_iteration)
    return {n: {v: float(np.nanmedian(c)) for v, c in by.items()} for n, by in costs.items()}


def payoff(root: Path) -> dict[tuple[int, float], Decision]:
    """HIG against Adam on the oscillators: the decision (median ratio HIG / Adam, wins) per chain length and
    time budget, the budgets being fractions of the shortest run."""
    runs = load(root, PAYOFF_FOLDERS)
    table = {}
    sizes = sorted({int(facts(r).get("task.oscillators", 0)) for r in runs if r.attrs.get("task") == "oscillator"})
    for n in sizes:
        try:
            side = {v: {s: curve(r, "wall_time")
                        for s, r in select(runs, {"task.oscillators": str(n), "optim.name": v}).items()}
                    for v in ("hig", "adam")}
        except AmbiguousRuns as error:
            print(f"claims: pay-off map without n = {n}: {error}", file=sys.stderr)
            continue
        full = decide(side["hig"], side["adam"]).budget
        for fraction in PAYOFF_FRACTIONS:
            cut = {v: {s: _cut(c, full * fraction) for s, c in curves.items()} for v, curves in side.items()}
            table[(n, full * fraction)] = decide(cut["hig"], cut["adam"])
    return table


def _cut(c: Curve, x: float) -> Curve:
    """The curve as if training had stopped at x."""
    keep = c.x <= x * (1 + 1e-9)
    return Curve(c.x[keep], c.loss[keep], min(c.end, x), c.diverged and c.end <= x)


def _seconds(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value * 1e3:.3g} ms" if value < 1 else f"{value:.3g} s"


def plot_payoff(table: dict, costs: dict, path: Path, note: str = "") -> None:
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    sizes = sorted({n for n, _ in table})
    budgets = {n: sorted(t for m, t in table if m == n) for n in sizes}
    ratios = np.array([[table[(n, t)].ratio for t in budgets[n]] for n in sizes])
    finite = ratios[(ratios > 0) & np.isfinite(ratios)]
    bound = max(float(np.max(np.abs(np.log10(finite)), initial=0.0)), 0.1)
    # a side that diverged gets the end of the scale: a diverged HIG is as bad as the map shows
    grid = np.log10(np.clip(ratios, 10.0 ** -bound, 10.0 ** bound), where=~np.isnan(ratios),
                    out=np.full(ratios.shape, np.nan))
    fig, ax = plt.subplots(figsize=(8.5, 1.6 + 1.1 * len(sizes)))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-bound, vmax=bound)
    image = ax.imshow(grid, cmap="RdBu_r", norm=norm, aspect="auto", origin="lower")
    ax.set_yticks(range(len(sizes)), [f"n = {n}: HIG {_seconds(costs.get(n, {}).get('hig', math.nan))}/step,\n"
                                      f"Adam {_seconds(costs.get(n, {}).get('adam', math.nan))}/step" for n in sizes],
                  fontsize=8)
    ax.set_xticks(range(len(PAYOFF_FRACTIONS)), [f"{t:.0f} s" for t in budgets[sizes[0]]])
    for i, n in enumerate(sizes):
        for j, t in enumerate(budgets[n]):
            d = table[(n, t)]
            label = {0.0: "Adam diverged", math.inf: "HIG diverged"}.get(d.ratio, _g(d.ratio))
            dark = np.isfinite(grid[i, j]) and abs(grid[i, j]) > 0.6 * bound
            ax.text(j, i, f"{label}  ({d.wins}/{d.pairs})", ha="center", va="center", fontsize=8,
                    color="white" if dark else "black")
    ax.set_xlabel("training wall-clock, the same for both (one job at a time)")
    ax.set_ylabel("chain length n (2n states)")
    ax.set_title("test loss HIG / Adam, median over seeds (HIG lower in k of n seeds)", fontsize=9)
    fig.colorbar(image, ax=ax, label="log10 ratio (blue: HIG ahead)")
    title = "Where HIG pays off on the coupled oscillators" + (f"\n{note}" if note else "")
    fig.suptitle(textwrap.fill(title, 110, replace_whitespace=False), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def payoff_table(table: dict, costs: dict) -> str:
    lines = ["| chain length n | HIG s/step | Adam s/step | training seconds "
             "| HIG / Adam test loss: median (HIG lower in k of n) | verdict |", "|---|---|---|---|---|---|"]
    for (n, t), d in sorted(table.items()):
        hig, adam = (_seconds(costs.get(n, {}).get(v, math.nan)) for v in ("hig", "adam"))
        lines.append(f"| {n} | {hig} | {adam} | {t:.0f} | {_ratio(d.ratio, 'HIG', 'Adam')} ({d.wins} of {d.pairs}) "
                     f"| {d.verdict} |")
    return "\n".join(lines) + "\n"


def write(root: Path, out: Path, note: str = "") -> str:
    """claims.md (and payoff.png) into out; returns the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    rule = __doc__.split("\n\n")[2]
    text = (f"# The papers' claims, measured\n\n{note + chr(10) + chr(10) if note else ''}"
            "A is the side the paper says reaches the lower held-out loss, B the other; budgets and seeds are "
            "those of the runs found. Verdicts follow one rule:\n\n" + rule + "\n\n" + claims_table(root))
    table = payoff(root)
    if table:
        costs = step_costs(root)
        plot_payoff(table, costs, out / "payoff.png", note)
        text += ("\n## Where HIG pays off (coupled oscillators)\n\n![payoff](payoff.png)\n\n"
                 "HIG's test loss over Adam's at equal training wall-clock, per chain length n (the Jacobian has "
                 "2n rows per sample; HIG's step grows with it) and time budget; below 1 HIG is ahead. Each cell "
                 "is the verdict rule on the runs cut at that time. HIG runs with the settings of the paper's "
                 "two-oscillator figure (learning rate, truncation) at every n: a ratio above 1 at larger n says "
                 "those settings do not carry over at that step cost, not that no HIG setting could.\n\n"
                 + payoff_table(table, costs))
    (out / "claims.md").write_text(text)
    return text


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        sys.exit(2)
    source = Path(sys.argv[1])
    print(write(source, Path(sys.argv[2]) if len(sys.argv) == 3 else source))
