"""`make reproduce-figures [PROFILE=quick|paper|claims|claims-long|claims-gpu|claims-paper|
leaderboard]`: run the figure sweeps of conf/experiment/ and write the figures and one markdown
summary into outputs/figures/; or, for the study profiles, the papers' claims (or the leaderboard)
as `physgrad compare` studies and outputs/figures/<profile>.md.

The experiment configs hold the papers' budgets (PROFILE=paper). The quick profile (the default)
runs the same sweeps with the budgets below, so that everything finishes in about 45 minutes on a
2-core machine; every figure and the summary say so. Runs land in
outputs/experiments/<profile>/<experiment>/<overrides>/results.h5; a second call skips every job
that completed or diverged (so an interrupted reproduction resumes), unless OVERWRITE=1. Each figure
is `physgrad report` of its runs: the same table and figures that command writes for any runs.

The claims profile runs the studies of experiments/conf/studies.yaml (the claims and the regime
map), each a `physgrad compare` (tuned, paired seeds, calibrated clock) and its untuned twin, into
outputs/experiments/claims/<study> (each tuning study a compare of its own, in <study>/study-k, so
that any part can run on any machine and be kept on its own); claims-long runs the claims whose
verdict turned with the budget four times as long, claims-gpu the claims that need budgets for one
GPU. Each resumes study by study and job by job; `--plan` prints the studies, their expected time
and the parts of at most about 80 minutes that `--part K` runs one at a time; the markdown is
written from whatever studies have finished.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import yaml
from study_profiles import INTERRUPTED, STUDY_PROFILES, run_child, study_profile  # experiments/

from physgrad.files import read_own_file, replace_file, write_text
from physgrad.report import write_report
from physgrad.sweeps import sweep_jobs

CONF = Path(__file__).resolve().parent.parent / "conf"


@dataclass(frozen=True)
class Sweep:
    """One sweep of a figure: a named experiment with the profile's overrides."""

    experiment: str
    overrides: tuple[str, ...]


@dataclass(frozen=True)
class Figure:
    name: str
    title: str
    experiments: tuple[str, ...]
    shows: tuple[str, ...]  # which of the report's figures this one is
    # experiment -> quick overrides; None: not in it
    quick: dict[str, list[str]] | None = field(default_factory=dict)
    runs_shown: tuple[
        str, ...
    ] = ()  # globs of job folders whose per-run scene figure (scene.png) is shown too
    # (folders, out folder, note) -> (figure file names, markdown): a study's own figure and table,
    # beside the report
    study: Callable[[list[Path], Path, str], tuple[list[str], str]] | None = None


def ks_study(folders: list[Path], out: Path, note: str) -> tuple[list[str], str]:
    from ks_study import write  # experiments/ is this script's folder

    return write(folders, out, note)


def toy_study(folders: list[Path], out: Path, note: str) -> tuple[list[str], str]:
    from toy_figure import write  # experiments/ is this script's folder

    return write(folders, out, note)


QUICK_POISSON = ["seed=0", "trainer.time_budget=45"]
FIGURES = (
    Figure(
        "oscillator_wallclock",
        "Oscillators: Adam, Gauss-Newton and HIG, test loss against training wall-clock",
        ("oscillator_wallclock",),
        ("loss_vs_time.png",),
        {"oscillator_wallclock": ["seed=0,1", "trainer.time_budget=60"]},
    ),
    Figure(
        "fig2_quantum",
        "Quantum dipole (HIG preset): Adam and HIG against training wall-clock",
        ("fig2_quantum",),
        ("loss_vs_time.png",),
        {"fig2_quantum": ["seed=0,1", "trainer.time_budget=75"]},
    ),
    Figure(
        "fig3_poisson",
        "Poisson: Adam and HIG, then both continuing from the Adam-trained network",
        ("fig3_poisson", "fig3_poisson_continue"),
        ("loss_vs_time.png",),
        {
            "fig3_poisson": QUICK_POISSON,
            "fig3_poisson_continue": [
                *QUICK_POISSON,
                "init_from='outputs/experiments/quick/fig3_poisson/"
                "optim=adam,seed=${seed},trainer.time_budget=45/results.h5'",
            ],
        },
    ),
    Figure(
        "fig4_multicart",
        "Multicart: backprop modes R, M, S, C for 1 to 4 poles, test loss against iteration",
        ("fig4_multicart",),
        ("loss_vs_iteration.png",),
        {"fig4_multicart": ["seed=0", "trainer.iterations=1500", "trainer.eval_every=100"]},
    ),
    Figure(
        "fig5_quantum_control",
        "Quantum control (StableBPTT preset): modes R, M, S, C for target levels 3, 4, 5",
        ("fig5_quantum_control",),
        ("loss_vs_iteration.png",),
        {"fig5_quantum_control": ["seed=0", "trainer.iterations=250", "trainer.eval_every=50"]},
    ),
    Figure(
        "fig6_unroll",
        "Unroll length: final test loss and seconds per iteration",
        ("fig6_unroll_bptt", "fig6_unroll_hig"),
        ("unroll.png",),
        {
            "fig6_unroll_bptt": [
                "seed=0",
                "unroll=16,32,64,128,256",
                "trainer.iterations=1000",
                "trainer.eval_every=250",
            ],
            "fig6_unroll_hig": ["seed=0", "unroll=16,32,64,128,256", "trainer.time_budget=15"],
        },
    ),
    Figure(
        "fig8_guidance",
        "Guidance by repulsion: modes R, M, S, C for control costs 1 to 0.001",
        ("fig8_guidance",),
        ("loss_vs_iteration.png",),
        {
            "fig8_guidance": [
                "seed=0",
                "optim.clip=none",
                "trainer.iterations=1000",
                "trainer.eval_every=100",
            ]
        },
        runs_shown=(
            "*optim.backprop=R,*seed=0,task.control_cost=0.001*",
            "*optim.backprop=C,*seed=0,task.control_cost=0.001*",
        ),
    ),
    Figure(
        "fig9_ks",
        "Kuramoto-Sivashinsky neural simulator: ONE, NOG, WIG x predict, correct x unroll length",
        ("fig9_ks",),
        ("unroll.png",),
        {"fig9_ks": ["unroll=1,2,4", "trainer.iterations=200", "trainer.eval_every=200"]},
        runs_shown=("*task.stepper=correct,task.training=WIG,*unroll=4/seed=0",),
        study=ks_study,
    ),
    Figure(
        "toy_scaling",
        "The PBDL book's badly scaled toy (lambda = 1 and 0.01): Adam, Gauss-Newton and HIG, loss, "
        "hidden activations and one sample's path",
        ("toy_scaling",),
        ("loss_vs_time.png",),
        {"toy_scaling": ["seed=0,1", "trainer.time_budget=15"]},
        study=toy_study,
    ),
    Figure(
        "hig_payoff",
        "Where HIG pays off: Adam and HIG on longer oscillator chains against training wall-clock",
        ("hig_payoff",),
        ("loss_vs_time.png",),
        None,
    ),
)
TRADEOFF = "fig7_tradeoff"


def profile_sweeps(figure: Figure, profile: str) -> list[Sweep]:
    """The sweeps a figure runs in a profile (none: the figure is not part of it)."""
    if profile == "quick" and figure.quick is None:
        return []
    return [
        Sweep(e, tuple(figure.quick.get(e, []) if profile == "quick" else []))
        for e in figure.experiments
    ]


def planned_jobs(sweep: Sweep) -> list[list[str]]:
    """The sweep's jobs as Hydra's basic sweeper will launch them: the experiment's sweep
    parameters, then the profile's overrides."""
    config = yaml.safe_load((CONF / "experiment" / f"{sweep.experiment}.yaml").read_text())
    params = ((config.get("hydra") or {}).get("sweeper") or {}).get("params") or {}
    return sweep_jobs([f"{key}={value}" for key, value in params.items()] + list(sweep.overrides))


def print_plan(figures: list[Figure], profile: str) -> None:
    """Every job of a figure profile."""
    count = 0
    for figure in figures:
        for sweep in profile_sweeps(figure, profile):
            jobs = planned_jobs(sweep)
            count += len(jobs)
            print(
                f"{figure.name}: +experiment={sweep.experiment} -> "
                f"outputs/experiments/{profile}/{sweep.experiment} ({len(jobs)} jobs)"
            )
            for job in jobs:
                print("    " + " ".join(job))
    print(f"{count} jobs, one at a time (jobs that completed or diverged before are skipped)")


def run_sweep(sweep: Sweep, profile: str, overwrite: bool) -> tuple[Path, int]:
    """One named sweep through `physgrad run -m`; returns its folder and the exit code."""
    folder = Path("outputs/experiments") / profile / sweep.experiment
    command = [
        sys.executable,
        "-m",
        "physgrad.cli",
        "run",
        "-m",
        f"+experiment={sweep.experiment}",
        f"hydra.sweep.dir={folder}",
        *sweep.overrides,
        *(["overwrite=true"] if overwrite else []),
    ]
    print("reproduce:", " ".join(command[2:]), flush=True)
    return folder, run_child(command)


NOTES = {
    "quick": "QUICK PROFILE: budgets scaled down from the papers' (see experiments/reproduce.py)",
    "paper": "paper profile: the papers' budgets",
    "claims": "CLAIMS PROFILE: physgrad compare studies (tuned, paired seeds, calibrated clock), "
    "budgets sized for a 2-core machine (experiments/conf/studies.yaml)",
    "claims-long": "CLAIMS-LONG PROFILE: the claims whose verdict turned with the budget, run "
    "four times as long (experiments/conf/studies.yaml)",
    "claims-gpu": "CLAIMS-GPU PROFILE: the claims that need budgets a 2-core machine cannot give, "
    "for one GPU (experiments/conf/studies.yaml)",
    "claims-paper": "CLAIMS-PAPER PROFILE: the papers' own settings, untuned, at the papers' "
    "budgets (experiments/conf/studies.yaml)",
    "leaderboard": "LEADERBOARD PROFILE: every rule against Adam, physgrad compare studies at "
    "equal calibrated time (experiments/leaderboard.py)",
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="make reproduce-figures", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--profile", choices=tuple(NOTES), default="quick")
    parser.add_argument("--only", default="", help="comma-separated figure names (default: all)")
    parser.add_argument(
        "--overwrite", action="store_true", help="rerun jobs that completed or diverged before"
    )
    parser.add_argument(
        "--plan", action="store_true", help="print every job and the expected time; run nothing"
    )
    parser.add_argument(
        "--part",
        default="",
        help="claims profiles: comma-separated part numbers (--plan lists them)",
    )
    parser.add_argument("--out", default="outputs/figures")
    options = parser.parse_args(argv)
    if options.profile in STUDY_PROFILES:
        return study_profile(
            options.profile, options.part, options.plan, Path(options.out), NOTES[options.profile]
        )
    wanted = [
        f
        for f in FIGURES
        if (not options.only or f.name in options.only.split(","))
        and profile_sweeps(f, options.profile)
    ]
    if options.only and len(wanted) != len(options.only.split(",")):
        names = ", ".join(f.name for f in FIGURES if profile_sweeps(f, options.profile))
        print(
            f"reproduce: error: --only takes names from {names} (the {options.profile} profile's "
            "figures)",
            file=sys.stderr,
        )
        return 2
    if options.plan:
        print_plan(wanted, options.profile)
        return 0
    return run_figures(wanted, options.profile, options.overwrite, Path(options.out))


def run_figures(wanted: list[Figure], profile: str, overwrite: bool, out: Path) -> int:
    """The figures' sweeps (each resumes), their reports, the error-against-time report of them
    all, and summary.md in out."""
    note = NOTES[profile]
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    sections, all_folders, failed = [], [], []
    for figure in wanted:
        folders = []
        for sweep in profile_sweeps(figure, profile):
            folder, code = run_sweep(sweep, profile, overwrite)
            if code == 130:
                print(INTERRUPTED, file=sys.stderr)
                return 130
            if code != 0:
                failed.append(f"{sweep.folder or sweep.experiment} (exit {code})")
            if folder.exists():
                folders.append(folder)
        all_folders += folders
        if not folders:
            sections.append(
                f"## {figure.name}: {figure.title}\n\nno results (the sweep did not start)\n"
            )
            continue
        write_report(
            [str(f) for f in folders], out_dir=out / figure.name, note=f"{figure.title}\n{note}"
        )
        shown = list(figure.shows)
        for pattern in figure.runs_shown:  # e.g. the agents' paths of one run per variant
            found = sorted(
                (p, f) for f in folders for p in f.glob(pattern) if (p / "scene.png").exists()
            )
            for job, folder in found[:1]:
                name = f"scene_{'_'.join(job.relative_to(folder).parts)}.png"
                # through the reading door: a sweep's scene.png may be a link to anything
                replace_file(out / figure.name / name, read_own_file(job / "scene.png", 1 << 26))
                shown.append(name)
        table = (out / figure.name / "report.md").read_text()
        if figure.study is not None:
            drawn, study_table = figure.study(folders, out / figure.name, f"{figure.title}\n{note}")
            shown = drawn + shown
            table = f"{study_table}\n{table}"
        images = "\n".join(f"![{figure.name}]({figure.name}/{image})" for image in shown)
        sections.append(f"## {figure.name}: {figure.title}\n\n{images}\n\n{table}")
    if all_folders:
        title = (
            "Error against run time: final test loss against seconds per iteration and total "
            "training time"
        )
        write_report([str(f) for f in all_folders], out_dir=out / TRADEOFF, note=f"{title}\n{note}")
        sections.append(
            f"## {TRADEOFF}: {title}\n\n![{TRADEOFF}]({TRADEOFF}/tradeoff.png)\n\n"
            f"(its table is the union of the tables above: {TRADEOFF}/report.md)\n"
        )
    minutes = (time.perf_counter() - start) / 60
    header = [
        f"# physgrad figures ({profile} profile)",
        "",
        note + ".",
        f"Wall time of this reproduction: {minutes:.1f} min (jobs that completed or diverged "
        "before were skipped, not rerun).",
        *(["", "Sweeps that did not finish cleanly: " + ", ".join(failed)] if failed else []),
        "",
    ]
    write_text(out / "summary.md", "\n".join(header) + "\n" + "\n".join(sections))
    print(f"reproduce: wrote {out / 'summary.md'} in {minutes:.1f} min")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
