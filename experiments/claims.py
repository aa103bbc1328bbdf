"""The papers' claims as `physgrad compare` studies: which studies the claims profile runs, how each
claim is read from them, claims.md with tuned and preset verdicts side by side, and the regime map
(payoff.png).

Usage: python experiments/claims.py STUDIES_FOLDER [OUT_FOLDER]
(STUDIES_FOLDER holds the profile's study folders: outputs/experiments/claims, or .../claims-long
or .../claims-gpu for that profile's markdown; or their kept evidence, docs/evidence/claims.)
python experiments/claims.py --keep STUDIES_FOLDER docs/evidence/claims keeps the finished studies'
evidence (experiments/evidence.py).

Every study is a `physgrad compare` (docs/protocol.md): each variant tuned with the same trial
points (8 per variant) in each of 4 independent tuning studies, scored by its validation loss on
the tuning seed, then evaluated at its best trial on 10 paired seeds, the verdicts from the test
loss; its untuned twin (`<study>-preset`, compare.tune=false) evaluates the presets on the same
seeds and clock. Time budgets run on the calibrated clock (iterations x each variant's calibrated
step cost). A claim is read from the studies' evaluation runs with physgrad's own rules
(physgrad.claim: its parts and how each is decided), at X/4, X/2 and X of the budget X (the same
runs, tuned for X, read earlier).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from evidence import (  # experiments/
    CLOCK,
    STUDY_FOLDER,
    commit,
    keep_clock,
    kept_row,
    kept_table,
    merged_rows,
    read_kept,
    write_kept,
)

from physgrad.claim import (
    FAILS,
    HOLDS,
    NOT_RUN,
    OPEN,
    Claim,
    Close,
    Decision,
    Grows,
    Lower,
    Reaches,
    Stalls,
    claim_of_part,
    claim_verdict,
    decide_parts,
    short,
    studies_of,
    tuning_studies,
)
from physgrad.readout import highest_median
from physgrad.verdict import (
    A_BETTER,
    B_BETTER,
    EQUIVALENT,
    FRACTIONS,
    claim_word,
    compare_variants,
    left_start,
    ratio_of,
)

TUNE_SEED = (
    1_000_000  # compare's default tuning seed: a study that continues networks needs one for it too
)
EVIDENCE = Path(__file__).resolve().parent.parent / "docs" / "evidence" / "claims"


# --- the studies
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Start:
    """Networks a study continues from (init_from): one `physgrad run` job per seed, evaluation and
    tuning seeds."""

    name: str
    overrides: tuple[str, ...]
    job_seconds: float  # one job on the 2-core machine, start-up and compilation included


@dataclass(frozen=True)
class Study:
    """One `physgrad compare` of the profile, into <profile folder>/<name> (and <name>-preset,
    untuned)."""

    name: str
    # compare's overrides: variant axes (comma lists) and common settings
    overrides: tuple[str, ...]
    trials: int
    seeds: int
    tune_seconds: float  # one tuning job on the 2-core machine (start-up and compilation included)
    eval_seconds: float  # one evaluation job (all seeds of a variant when they train together)
    start: Start | None = None
    preset: bool | str = (
        True  # also evaluate the presets untuned (a key=value: with that override replaced)
    )
    studies: int = 1  # independent tuning studies (compare.studies); CLAIM_STUDIES for the claims
    # tuning study k of the `studies` as a compare of its own in <name>/study-k (slices); 0: all
    # of them in one compare in <name>
    tuning_study: int = 0

    @property
    def label(self) -> str:
        return self.name + (
            f" (tuning study {self.tuning_study} of {self.studies})" if self.tuning_study else ""
        )

    @property
    def folder(self) -> str:
        """The study's folder under the profile's: <name>/study-k for tuning study k."""
        k = self.tuning_study
        return f"{self.name}/{STUDY_FOLDER.format(k=k)}" if k else self.name

    def variants(self, preset: bool = False) -> int:
        return math.prod(
            len(_values(o)) for o in self.preset_overrides(preset) if len(_values(o)) > 1
        )

    def preset_overrides(self, preset: bool = True) -> list[str]:
        if not preset or not isinstance(self.preset, str):
            return list(self.overrides)
        key = self.preset.partition("=")[0]
        return [self.preset if o.partition("=")[0] == key else o for o in self.overrides]

    @property
    def timed(self) -> bool:
        return any(o.startswith("trainer.time_budget=") for o in self.overrides)

    def eval_jobs(self, preset: bool = False) -> int:
        per_seed = self.timed or self.start is not None
        return self.variants(preset) * (self.seeds if per_seed else 1)

    def clock(self, root: Path) -> Path | None:
        """The calibration a tuning study after the first and the presets' twin run on: the
        study's kept clock (whatever machine ran its first study), else the first study's own in
        root; None (the study calibrates itself) if there is neither."""
        for path in (EVIDENCE / CLOCK.format(name=self.name), root / self.name / "study-1"):
            path = path / "calibration.json" if path.suffix != ".json" else path
            if path.is_file():
                return path
        return None

    def command(self, root: Path, preset: bool = False) -> list[str]:
        overrides = [o.replace("{root}", str(root)) for o in self.preset_overrides(preset)]
        k = self.tuning_study
        folder = f"{self.name}-preset" if preset else self.folder
        settings = [
            f"compare.dir={root / folder}",
            f"compare.seeds={self.seeds}",
            f"compare.trials={self.trials}",
            # repeated tuning studies (docs/protocol.md), each a compare of its own with the
            # tuning seed and evaluation seeds study k has in one compare of all of them; the
            # untuned presets are one study (the first's seeds)
            f"compare.studies={1 if preset or k else self.studies}",
            *(
                (f"compare.seed={(k - 1) * self.seeds}", f"compare.tune_seed={TUNE_SEED + k - 1}")
                if k and not preset
                else ()
            ),
        ]
        if preset:
            settings.append("compare.tune=false")
        clock = self.clock(root) if self.timed and (preset or k > 1) else None
        if clock is not None:  # on the first tuning study's clock
            settings.append(f"compare.calibration={clock}")
        return [*overrides, *settings]

    def start_seeds(self, preset: bool = False) -> list[int]:
        """The seeds a study that continues networks needs a start network for: the evaluation
        seeds and tuning seed of each tuning study it runs (study k: (k - 1) * seeds .. k * seeds
        - 1 and compare's tune_seed + k - 1); the presets' twin, the first study's."""
        ks = [self.tuning_study] if self.tuning_study else range(1, self.studies + 1)
        ks = [1] if preset else ks
        return [
            *(s for k in ks for s in range((k - 1) * self.seeds, k * self.seeds)),
            *(TUNE_SEED + k - 1 for k in ks),
        ]

    def seconds(self) -> float:
        """The expected wall time: tuning, evaluation, the presets' evaluation, the start networks,
        calibration."""
        new = 1 if self.tuning_study else self.studies  # the tuning studies this command runs
        total = new * (
            self.trials * self.variants() * self.tune_seconds + self.eval_jobs() * self.eval_seconds
        )
        total += self.eval_jobs(preset=True) * self.eval_seconds if self.preset else 0.0
        if self.start:
            seeds = set(self.start_seeds()) | set(self.start_seeds(True) if self.preset else ())
            total += len(seeds) * self.start.job_seconds
        kept_clock = (EVIDENCE / CLOCK.format(name=self.name)).is_file()
        calibrates = self.tuning_study <= 1 or not kept_clock
        return total + (30.0 * self.variants() if self.timed and calibrates else 0.0)


def _values(override: str) -> list[str]:
    """The values of a comma-list override (a variant axis); one value otherwise. Quoted values are
    one value."""
    value = override.partition("=")[2]
    if value.startswith(("'", '"', "[")):
        return [value]
    return value.split(",")


def _study(name, overrides, trials, seeds, tune_seconds, eval_seconds, **more) -> Study:
    return Study(name, tuple(overrides.split()), trials, seeds, tune_seconds, eval_seconds, **more)


CART = (
    "task=multicart optim=bptt optim.backprop=R,C optim.clip=none,value,norm "
    "trainer.iterations=1500"
)
GUIDANCE = (
    "task=guidance optim=bptt optim.backprop=R,C optim.clip=none,value,norm trainer.iterations=1500"
)
QUANTUM_CONTROL = "task=quantum_control optim=bptt optim.backprop=R,C trainer.iterations=150"
KS = "task=ks task.zero_output=true trainer.iterations=1000"
KS_START = Start(
    "ks_start",
    (
        "task=ks",
        "task.zero_output=true",
        "task.training=ONE",
        "unroll=1",
        "trainer.iterations=1000",
    ),
    50,
)
POISSON_START = Start("poisson_start", ("task=poisson", "optim=adam", "trainer.time_budget=20"), 30)

# the claims' protocol (docs/protocol.md): every variant tuned with CLAIM_TRIALS trials on the same
# points in each of CLAIM_STUDIES independent tuning studies, evaluated on CLAIM_SEEDS paired seeds:
# enough for a verdict with one seed against it for up to 6 comparisons of a study (verdict.
# seeds_for_one_against: 9), so neither iteration nor equal-time claims need every seed on one side
CLAIM_TRIALS, CLAIM_STUDIES, CLAIM_SEEDS = 8, 4, 10


def _claim_study(study: Study) -> Study:
    """The study under the claims' protocol (its own trials and seeds, the numbers of the earlier
    one-study profile, are replaced; its per-job costs stay)."""
    return replace(study, trials=CLAIM_TRIALS, seeds=CLAIM_SEEDS, studies=CLAIM_STUDIES)


STUDIES = tuple(
    map(
        _claim_study,
        (
            _study(
                "oscillator",
                "task=oscillator optim=adam,gauss_newton,hig trainer.time_budget=15",
                3,
                7,
                25,
                25,
            ),
            _study(
                "quantum",
                "task=quantum optim=adam,hig trainer.time_budget=20",
                2,
                6,
                32,
                32,
            ),
            Study(
                "poisson_continue",
                (
                    "task=poisson",
                    "optim=adam,hig",
                    "trainer.time_budget=30",
                    "init_from='{root}/poisson_start/seed=${seed}/results.h5'",
                ),
                2,
                6,
                43,
                43,
                start=POISSON_START,
            ),
            *(
                _study(
                    f"toy_{scale}",
                    f"task=toy task.scale={scale} optim=adam,gauss_newton,hig "
                    "trainer.time_budget=8",
                    3,
                    7,
                    18,
                    18,
                )
                for scale in ("1", "0.01")
            ),
            _study("cart_2", f"{CART} task.poles=2", 2, 10, 17, 100, preset="optim.clip=none"),
            _study("cart_4", f"{CART} task.poles=4", 2, 10, 17, 120, preset="optim.clip=none"),
            _study("quantum_control_3", f"{QUANTUM_CONTROL} task.target_level=3", 2, 6, 43, 220),
            _study("quantum_control_5", f"{QUANTUM_CONTROL} task.target_level=5", 2, 6, 43, 220),
            _study(
                "guidance_1",
                f"{GUIDANCE} task.control_cost=1",
                2,
                10,
                20,
                115,
                preset="optim.clip=none",
            ),
            _study(
                "guidance_0.001",
                f"{GUIDANCE} task.control_cost=0.001",
                2,
                10,
                20,
                115,
                preset="optim.clip=none",
            ),
            _study(
                "ks_training",
                f"{KS} task.stepper=correct task.training=WIG,NOG,ONE unroll=3",
                3,
                10,
                50,
                270,
            ),
            _study(
                "ks_stepper",
                # the abstract's pair (NOG correcting, WIG predicting) and WIG against WIG
                f"{KS} task.training=NOG,WIG task.stepper=correct,predict unroll=3",
                3,
                10,
                50,
                270,
            ),
            Study(
                "ks_unroll",
                (
                    *KS.split(),
                    "task.stepper=correct",
                    "task.training=WIG",
                    "unroll=1,3,8",
                    "init_from='{root}/ks_start/seed=${seed}/results.h5'",
                ),
                2,
                8,
                50,
                50,
                start=KS_START,
            ),
            # the papers' own central comparisons (their ablations)
            _study(
                "cart_4_modes",
                "task=multicart task.poles=4 optim=bptt optim.backprop=R,M,S,C optim.clip=none "
                "trainer.iterations=1500",
                2,
                10,
                17,
                120,
            ),
            _study(
                "poisson_scratch",
                "task=poisson optim=adam,hig trainer.time_budget=30",
                2,
                6,
                43,
                43,
            ),
            _study(
                "oscillator_kappa",
                "task=oscillator optim=hig optim.kappa=0.5,1,0 trainer.time_budget=15",
                3,
                7,
                25,
                25,
            ),
        ),
    )
)

# The regime map: HIG against Adam per cell, both tuned in the cell with the claims' trials on
# shared points (one tuning study: a map is no claim) and evaluated on 6 paired seeds; the
# conditioning of the physics across, HIG's step cost relative to Adam's (the Jacobian's rows: the
# batch) down. With 2 trials HIG was tried at 1.6e-3 and 0.16 of [0.001, 10] on the oscillators,
# about 30 times below the rate 8 trials find.
MAP_TOY = tuple(
    _study(
        f"map_toy_{scale}_b{batch}",
        f"task=toy optim=adam,hig task.scale={scale} task.batch_size={batch} trainer.time_budget=5",
        CLAIM_TRIALS,
        6,
        15,
        15,
        preset=False,
    )
    for batch in (16, 256)
    for scale in ("1", "0.01", "0.0001")
)
MAP_OSCILLATOR = tuple(
    _study(
        f"map_oscillator_{alpha}",
        f"task=oscillator optim=adam,hig task.alpha={alpha} trainer.time_budget=10",
        CLAIM_TRIALS,
        6,
        20,
        20,
        preset=False,
    )
    for alpha in ("0.25", "1", "4")
)
MAP = MAP_TOY + MAP_OSCILLATOR

# claims-long: the claims whose verdict turned with the budget, run four times as long under the
# same protocol (their own folders): a quarter of the budget is the claims profile's
LONG = tuple(
    map(
        _claim_study,
        (
            _study(
                "oscillator",
                "task=oscillator optim=adam,gauss_newton,hig trainer.time_budget=60",
                2,
                7,
                70,
                70,
                preset=False,
            ),
            _study(
                "quantum_control_3",
                f"{QUANTUM_CONTROL.replace('=150', '=600')} task.target_level=3",
                2,
                6,
                150,
                800,
                preset=False,
            ),
            _study(
                "quantum_control_5",
                f"{QUANTUM_CONTROL.replace('=150', '=600')} task.target_level=5",
                2,
                6,
                150,
                800,
                preset=False,
            ),
        ),
    )
)

# claims-gpu: the claims that need budgets a 2-core machine cannot give, for one GPU. Poisson's
# HIG step (the SVD of a 4,096-row Jacobian) costs about 13 s on 2 CPU cores and about 128 ms on
# an H100: 300 s of continuation are about 2,300 HIG steps there (23 here). A job on the
# calibrated clock costs its budget plus start-up whatever the step costs; the
# Kuramoto-Sivashinsky jobs are costed at the 2-core machine's update (0.21 s for ten networks),
# which was not measured on a GPU.
GPU_POISSON_START = Start(
    "poisson_start", ("task=poisson", "optim=adam", "trainer.time_budget=300"), 330
)
GPU = tuple(
    map(
        _claim_study,
        (
            Study(
                "poisson_continue",
                (
                    "task=poisson",
                    "optim=adam,hig",
                    "trainer.time_budget=300",
                    "init_from='{root}/poisson_start/seed=${seed}/results.h5'",
                ),
                2,
                6,
                330,
                330,
                start=GPU_POISSON_START,
                preset=False,
            ),
            _study(
                "ks_training",
                f"{KS.replace('=1000', '=42500')} task.stepper=correct "
                "task.training=WIG,NOG,ONE unroll=3",
                3,
                10,
                1400,
                9500,
                preset=False,
            ),
        ),
    )
)

PROFILES = {"claims": STUDIES + MAP, "claims-long": LONG, "claims-gpu": GPU}


def starts(studies) -> list[Start]:
    found = []
    for study in studies:
        if study.start is not None and study.start not in found:
            found.append(study.start)
    return found


def slices(study: Study) -> list[Study]:
    """A study with repeated tuning studies as one compare per tuning study, each in a folder of
    its own (<name>/study-k), so that each is kept whatever machine ran the others; the untuned
    presets with the last. A study of one tuning study is itself."""
    if study.studies == 1:
        return [study]
    return [
        replace(study, tuning_study=k, preset=study.preset if k == study.studies else False)
        for k in range(1, study.studies + 1)
    ]


def chunks(studies, limit_seconds: float = 80 * 60) -> list[list[Study]]:
    """The studies in order, each cut into its tuning studies (slices), grouped into parts of at
    most limit_seconds expected; a slice longer than that is a part of its own (it resumes job by
    job)."""
    parts, current, used = [], [], 0.0
    for study in (piece for whole in studies for piece in slices(whole)):
        if current and used + study.seconds() > limit_seconds:
            parts.append(current)
            current, used = [], 0.0
        current.append(study)
        used += study.seconds()
    return parts + ([current] if current else [])


# --- the claims
# -------------------------------------------------------------------------------------------


R_VARIANTS = ("none", "value", "norm")
# the unrolling study's training: about 42,500 updates for WIG and NOG (docs/decisions.md)
KS_UPDATES = 42_500


def _bptt(clip: str, mode: str) -> str:
    return f"backprop={mode} clip={clip}"


# the StableBPTT paper trains 32,000 iterations (guidance: 1,000 epochs of 32 batches of 8)
STABLE_BPTT_ITERATIONS = 32_000


def _stable_bptt(
    name: str,
    paper: str,
    easy: str,
    hard: str,
    note: str,
    budget: str,
    iterations: float = STABLE_BPTT_ITERATIONS,
) -> Claim:
    parts = [Lower(hard, _bptt(c, "C"), _bptt(c, "R")) for c in R_VARIANTS]
    parts += [Grows(easy, hard, _bptt(c, "C"), _bptt(c, "R")) for c in R_VARIANTS]
    return Claim(name, paper, tuple(parts), note, iterations, budget)


CLAIMS = (
    Claim(
        "oscillators: HIG below Adam and Gauss-Newton",
        "HIG paper (Schnell, Holl and Thuerey, ICLR 2022), figure 2b (by the reference "
        "repository's README): on the coupled oscillators HIG reaches a lower test loss than Adam "
        "and Gauss-Newton in the same wall-clock time",
        (Lower("oscillator", "hig", "adam"), Lower("oscillator", "hig", "gauss_newton")),
        paper_budget=3600.0,
        paper_budget_text="3,600 s per method (its run scripts: 60 x 60 s)",
        paper_seconds=True,
    ),
    Claim(
        "quantum dipole: HIG below Adam",
        "HIG paper (figure number unverified): on quantum dipole control HIG beats Adam in "
        "wall-clock time",
        (Lower("quantum", "hig", "adam"),),
        paper_budget=5400.0,
        paper_budget_text="5,400 s per method (its run scripts: 60 x 90 s)",
        paper_seconds=True,
    ),
    Claim(
        "Poisson: HIG after Adam improves further than Adam",
        "HIG paper, Poisson problem (figure number unverified): continuing an Adam-trained network "
        "with HIG lowers the loss further than continuing with Adam",
        (Lower("poisson_continue", "hig", "adam"),),
        "each seed continues its own Adam network (poisson_start: Adam on the measured clock, 20 s "
        "in the claims profile, 300 s in claims-gpu)",
        paper_budget_text="not stated in the run scripts (unverified)",
    ),
    _stable_bptt(
        "cart: C keeps solving as poles are added, R degrades",
        "StableBPTT paper (Schnell and Thuerey, ICLR 2024), Figure 4: on the multi-pole cart the "
        "combined "
        "gradient C keeps its performance as poles are added while regular BPTT (R) degrades",
        "cart_2",
        "cart_4",
        "C against R under each clipping of the reference's sweep (none, value, norm), at 4 poles "
        "and as a trend from 2 to 4 poles",
        "32,000 iterations",
    ),
    Claim(
        "quantum control: C below R at higher target levels",
        "StableBPTT paper, Figure 5: on quantum control C is better than R for the higher target "
        "levels",
        (
            Lower("quantum_control_5", "backprop=C", "backprop=R"),
            Grows("quantum_control_3", "quantum_control_5", "backprop=C", "backprop=R"),
        ),
        "without clipping only (the clipping variants triple a scene whose step costs 0.2 s)",
        STABLE_BPTT_ITERATIONS,
        "32,000 iterations",
    ),
    _stable_bptt(
        "guidance: C below R at small control cost",
        "StableBPTT paper, Figure 8: on guidance by repulsion C is better than R for small "
        "regularisation coefficients rc",
        "guidance_1",
        "guidance_0.001",
        "C against R under each clipping, at rc = 0.001 and as a trend from rc = 1",
        "unverified: 1,000 epochs (32,000 iterations) assumed; the reference's committed run "
        "script trains 10 epochs",
        math.nan,
    ),
    Claim(
        "KS: correction beats prediction",
        "Unrolling study (List et al. 2025), Kuramoto-Sivashinsky: correcting a coarse solver "
        "gives a lower error than predicting the whole step with the network, the correction "
        "trained without gradients through the unroll (NOG), the prediction with them (WIG), as "
        "the abstract compares them (the 4.5x of the study's first version is over all its "
        "systems, not a Kuramoto-Sivashinsky figure: no factor is claimed here)",
        (
            Lower("ks_stepper", "training=NOG stepper=correct", "training=WIG stepper=predict"),
            Lower("ks_stepper", "training=WIG stepper=correct", "training=WIG stepper=predict"),
        ),
        "m = 3; first the abstract's pair (NOG correcting, WIG predicting), then WIG against WIG "
        "(labelled: the pair physgrad measured before); the factor is the median ratio "
        "predict / correct",
        KS_UPDATES,
        "about 42,500 updates",
    ),
    Claim(
        "KS: WIG best, NOG close, ONE worse",
        "Unrolling study, Kuramoto-Sivashinsky: training with gradients through the unroll (WIG) "
        "gives the lowest error, without them (NOG) comes close, one-step training (ONE) is worse",
        (
            Lower("ks_training", "training=WIG", "training=ONE"),
            Lower("ks_training", "training=NOG", "training=ONE"),
            Close("ks_training", "training=NOG", "training=WIG", 1.25),
        ),
        "correction stepper, m = 3; close: NOG within 25% of WIG",
        KS_UPDATES,
        "about 42,500 updates (ONE about 40,700)",
        departs="the study reports average improvements over ONE across its configurations "
        "(about 38% for WIG, 23% for NOG); physgrad tests one configuration and reads 'close' as "
        "NOG within 25% of WIG",
    ),
    Claim(
        "KS: a best unroll length",
        "Not the study's claim: it trains at m = 3 and reports no optimum; physgrad asks whether "
        "m = 3 beats m = 1 and m = 8 on Kuramoto-Sivashinsky",
        (Lower("ks_unroll", "3", "1"), Lower("ks_unroll", "3", "8")),
        "every m continues the same one-step (ONE) network of its seed, as the study starts "
        "longer unrolls",
        KS_UPDATES,
        "about 42,500 updates",
        departs="a question physgrad asks, not a claim of the study (m = 3 is its setting)",
    ),
    Claim(
        "cart (4 poles): C below M and S",
        "StableBPTT paper's ablation: the combined gradient C beats gradient stopping without the "
        "sign combination (M) and the stopped gradient without long-range backpropagation (S)",
        (
            Lower("cart_4_modes", "backprop=C", "backprop=M"),
            Lower("cart_4_modes", "backprop=C", "backprop=S"),
        ),
        "4 poles (the hard end), without clipping (the papers' setting); figure number unverified",
        STABLE_BPTT_ITERATIONS,
        "32,000 iterations",
    ),
    Claim(
        "Poisson: HIG below Adam from the same initial network",
        "HIG paper, Poisson problem (the first half of its figure; number unverified): trained "
        "from the same initial network, HIG reaches a lower loss than Adam",
        (Lower("poisson_scratch", "hig", "adam"),),
        "HIG's step costs 5.9 s calibrated on 2 cores: 30 s are about 5 HIG steps, a test of "
        "the step's cost more than of the claim",
        paper_budget_text="not stated in the run scripts (unverified)",
    ),
    Claim(
        "oscillators: the half inversion beats the full inversion and none",
        "HIG paper, the exponent of the inversion (ablation; figure number unverified): the half "
        "inversion (kappa = 1/2) trains better than the full inversion (kappa = 1, Gauss-Newton's "
        "exponent) and no inversion (kappa = 0)",
        (
            Lower("oscillator_kappa", "kappa=0.5", "kappa=1"),
            Lower("oscillator_kappa", "kappa=0.5", "kappa=0"),
        ),
        "every variant is physgrad's HIG step with another exponent, tuned like the rest",
        paper_budget=3600.0,
        paper_budget_text="3,600 s per method (its run scripts: 60 x 60 s)",
        paper_seconds=True,
    ),
    Claim(
        "toy (lambda = 1): Adam, Gauss-Newton and HIG all converge",
        "PBDL book, HIG chapter, the toy's well-conditioned case: with lambda = 1 all three "
        "methods fare okay, the loss decreasing to around 1e-2 and 1e-3",
        tuple(Reaches("toy_1", variant, 1e-2) for variant in ("adam", "gauss_newton", "hig")),
        "the book's toy (1 -> 7 tanh -> 2, the target not scaled); reaching: the held-out loss "
        "below 1e-2, the upper end of the book's range; the book states no budget, batch or rates",
        paper_budget_text="not stated (the book's figure)",
    ),
    Claim(
        "toy (lambda = 0.01): HIG converges where Adam and Gauss-Newton stall",
        "PBDL book, HIG chapter, the toy's ill-conditioned case: with lambda = 0.01 Adam and "
        "Gauss-Newton do not decrease the loss beyond about 0.2 (Gauss-Newton's neurons "
        "saturated), while HIG converges",
        (
            Lower("toy_0.01", "hig", "adam"),
            Lower("toy_0.01", "hig", "gauss_newton"),
            Stalls("toy_0.01", "adam"),
            Stalls("toy_0.01", "gauss_newton"),
        ),
        "the book's toy (1 -> 7 tanh -> 2, the target not scaled) on the held-out loss: HIG lower, "
        "and Adam's and Gauss-Newton's loss no longer falling from half the budget to the budget; "
        "the book states no budget, batch or rates",
        paper_budget_text="not stated (the book's figure)",
    ),
)


# --- reading a study
# --------------------------------------------------------------------------------------


@dataclass
class StudyRuns:
    """A study's evaluation runs: variant -> seed -> results file, with the budget and its axis."""

    folder: Path
    axis: str
    budget: float
    paths: dict
    machine: str = ""
    # with repeated tuning studies: every study's runs, the first (this one's paths) included
    tuning: tuple = ()
    # read from kept evidence (experiments/evidence.py): {(variant, column): {seed: KeptCurve}}
    kept: dict | None = None
    protocol: tuple | None = None  # kept evidence: (trials, tuning studies, seeds)
    # the tuning studies the study is to have (0: those it has); a part is decided by a majority
    # of them, so that two of four run cannot decide it alone
    planned: int = 0

    def curves(self, variant: str, column: str = "loss") -> dict:
        from physgrad.readout import run_curve
        from physgrad.results import read_run

        if self.kept is not None:
            return dict(self.kept.get((variant, column), {}))

        found, unreadable = {}, []
        for seed, path in self.paths.get(variant, {}).items():
            try:
                found[seed] = run_curve(read_run(Path(path)), self.axis, column)
            except ValueError as error:
                unreadable.append(str(error))
        if unreadable:
            print(
                f"claims: {variant} in {self.folder}: left out {len(unreadable)} runs, e.g. "
                f"{unreadable[0]}",
                file=sys.stderr,
            )
        return found


def read_study(folder: Path) -> StudyRuns | None:
    """The study's runs.csv (written by physgrad compare) as StudyRuns of its first tuning study,
    with every tuning study's in `tuning` where it has several (Lower and Close parts are decided
    over them by the package's rule, physgrad.verdict.across_studies; the trend and stall parts
    are decided in each and over them by the same rule, verdict.over_studies; the regime map reads
    the first); None if the study has not finished. The table is data from a folder
    that may come from someone else: each run's file is looked for in the folder's own eval/ (the
    part of its recorded path from "eval" on), never at the path as written (an absolute path or
    "..": anywhere); a row whose seed, budget or path cannot be read so is a UserError (one
    line)."""
    import pandas as pd

    from physgrad.errors import UserError

    table = folder / "runs.csv"
    if not table.is_file():
        kept = kept_table(folder)
        if kept is not None:
            return _kept_runs(read_kept(kept))
        return _tuning_study_runs(folder)
    try:
        table_runs = pd.read_csv(table, dtype=str)
    except ValueError as error:  # pandas' parse errors, an empty file, bytes that are no text
        why = (str(error).splitlines() or [type(error).__name__])[0][:200]
        raise UserError(f"{table}: not a table of runs ({why})") from None
    if "study" not in table_runs:  # written before repeated tuning studies: one study
        return _study_runs(folder, table, table_runs)
    found = [
        _study_runs(folder, table, table_runs[table_runs["study"].astype(str) == str(k)])
        for k in sorted(set(table_runs["study"].astype(str)), key=lambda k: (len(k), k))
    ]
    if not found or any(study is None for study in found):
        return None
    if len(found) == 1:
        return found[0]
    return replace(found[0], tuning=tuple(found))


def _planned(name: str) -> int:
    """The tuning studies a study of the profiles is to have (0: not one of theirs)."""
    return max((s.studies for p in PROFILES.values() for s in p if s.name == name), default=0)


def _tuning_study_runs(folder: Path) -> StudyRuns | None:
    """A study run one compare per tuning study (<folder>/study-k, slices) as StudyRuns: the
    first finished study's, with every finished one in `tuning`, in the order of k; None if none
    has finished. A study folder that is a link is not read (someone else's)."""
    from physgrad.errors import UserError

    subs = list(folder.iterdir()) if folder.is_dir() and not folder.is_symlink() else []
    found = {}
    numbered = (re.fullmatch(STUDY_FOLDER.format(k=r"([1-9][0-9]{0,5})"), p.name) for p in subs)
    for k in sorted(int(m[1]) for m in numbered if m):
        sub = folder / STUDY_FOLDER.format(k=k)
        if sub.is_symlink():
            raise UserError(f"{sub}: a link: refused (a study may come from someone else)")
        runs = read_study(sub) if (sub / "runs.csv").is_file() else None
        if runs is not None:
            if runs.tuning:
                raise UserError(
                    f"{sub}: {len(runs.tuning)} tuning studies, where a study-k folder holds one"
                )
            found[k] = runs
    if not found:
        return None
    studies = [replace(runs, planned=_planned(folder.name)) for runs in found.values()]
    return replace(studies[0], tuning=tuple(studies) if len(studies) > 1 else ())


def _kept_runs(kept) -> StudyRuns | None:
    """Kept evidence (experiments/evidence.py) as StudyRuns: every tuning study's, the first's
    with the others in `tuning`."""
    found = [
        StudyRuns(
            kept.path,
            kept.axis,
            kept.budget,
            {variant: {seed: str(kept.path) for seed in by} for (variant, _), by in curves.items()},
            kept.machine,
            kept=curves,
            protocol=kept.protocol,
            planned=kept.planned,
        )
        for curves in kept.studies
        if curves  # a tuning study not kept (yet)
    ]
    if not found:
        return None
    if len(found) > 1:
        found[0].tuning = tuple(found)
    return found[0]


def keep_evidence(root: Path, dest: Path) -> list[str]:
    """Every finished study of the claims under root, and its presets' twin, as evidence tables in
    dest (experiments/evidence.py): the columns the claims read of it, at the kept fractions of its
    budget, for every tuning study, variant and seed. A study run one compare per tuning study
    (<name>/study-k) adds each finished one to the kept table, replacing its rows if it was kept
    before and keeping the others' (each is kept whatever machine ran it), and keeps the first's
    calibration as the study's clock; a study run in one compare replaces every study it has.
    Returns the studies kept (<name>, or <name>/study-k)."""
    columns: dict[str, set] = {}
    for claim in CLAIMS:
        for part in claim.parts:
            for name in studies_of(claim_of_part(part)):
                columns.setdefault(name, {"loss"}).add(getattr(part, "column", "loss"))
    kept = []
    for name in sorted(columns):
        for folder in (root / name, root / f"{name}-preset"):
            runs = read_study(folder) if folder.is_dir() and not folder.is_symlink() else None
            if runs is None or runs.kept is not None:
                continue
            split = not (folder / "runs.csv").is_file()  # one compare per tuning study
            finished = {}
            for k, study in enumerate(tuning_studies(runs), 1):
                where = study.folder if split else folder
                k = int(where.name.partition("-")[2]) if split else k
                finished[k] = (
                    [
                        kept_row(k - 1, variant, seed, column, curve, runs.budget)
                        for variant in sorted(study.paths)
                        for column in sorted(columns[name])
                        for seed, curve in sorted(study.curves(variant, column).items())
                    ],
                    _study_record(where, study),
                )
                kept.append(f"{folder.name}/{where.name}" if split else folder.name)
            kept = list(dict.fromkeys(kept))  # a study run in one compare: its name once
            if split:
                rows, by_study = merged_rows(dest, folder.name, finished, runs.budget)
            else:  # one compare: it replaces what was kept
                rows = [row for found, _ in finished.values() for row in found]
                by_study = {str(k): record for k, (_, record) in finished.items()}
            trials, _, seeds = study_protocol(folder)
            about = {
                "study": folder.name,
                "axis": runs.axis,
                "budget": runs.budget,
                "trials": trials,
                "studies": len(by_study),
                "planned": max(_planned(name) if folder.name == name else 1, len(by_study)),
                "seeds": seeds,
                "machine": "; ".join(
                    sorted({str(r.get("machine") or "") for r in by_study.values()} - {""})
                ),
                # of physgrad, as the runs recorded it
                "commits": sorted({c for r in by_study.values() for c in r.get("commits", [])}),
                "kept_by": commit(),
                "overrides": by_study[min(by_study, key=int)].get("overrides", []),
                "tuning_studies": by_study,
            }
            write_kept(dest, folder.name, rows, about)
            if split:
                keep_clock(folder / "study-1" / "calibration.json", dest / CLOCK.format(name=name))
    return kept


def _study_record(folder: Path, runs: StudyRuns) -> dict:
    """What a kept tuning study records of itself: its machine, the physgrad commits its runs
    recorded, the commit that kept it and the compare overrides that ran it."""
    from physgrad.results import read_final

    ran = set()
    for by_seed in runs.paths.values():
        for path in by_seed.values():
            try:
                ran.add(str(read_final(Path(path))[0].get("git_commit", "unknown")))
            except (OSError, ValueError):
                ran.add("unreadable")
    overrides = []
    if (folder / "study.json").is_file():
        overrides = json.loads((folder / "study.json").read_text()).get("overrides", [])
    return {
        "machine": runs.machine,
        "commits": sorted(ran),
        "kept_by": commit(),
        "overrides": overrides,
    }


def _study_runs(folder: Path, table: Path, runs: object) -> StudyRuns | None:
    """One tuning study's rows of runs.csv as StudyRuns (read_study)."""
    from physgrad.errors import UserError

    if not len(runs) or not {"variant", "seed", "axis", "budget", "path"} <= set(runs.columns):
        return None
    if (folder / "eval").is_symlink():  # resolving it would make anywhere "inside"
        raise UserError(f"{folder / 'eval'}: a link: refused (a study may come from someone else)")
    inside = (folder / "eval").resolve()
    paths = {}
    for row in runs.itertuples():
        number = int(row.Index) + 2  # the table's line (a header, then rows from 0)
        parts = Path(str(row.path)).parts
        seed = str(row.seed)
        # a seed as physgrad writes one: ASCII digits below 2^32 ("²" is a digit to str.isdigit)
        if "eval" not in parts or not (seed.isascii() and seed.isdecimal() and len(seed) <= 10):
            raise UserError(f"{table} line {number}: not a run of this study (seed {seed!r})")
        path = folder.joinpath(*parts[len(parts) - 1 - parts[::-1].index("eval") :])
        if ".." in path.relative_to(folder).parts or not path.resolve().is_relative_to(inside):
            raise UserError(f"{table} line {number}: its path leaves {folder / 'eval'}")
        paths.setdefault(str(row.variant), {})[int(seed)] = str(path)
    try:
        budget = float(runs["budget"].iloc[0])
    except ValueError:
        raise UserError(f"{table}: budget {runs['budget'].iloc[0]!r} is not a number") from None
    machines = sorted(set(runs["machine"].astype(str))) if "machine" in runs else []
    return StudyRuns(folder, str(runs["axis"].iloc[0]), budget, paths, "; ".join(machines))


def _budget_text(runs: StudyRuns) -> str:
    return {
        "iteration": f"{runs.budget:g} iterations",
        "wall_time": f"{runs.budget:g} s (measured clock)",
        "calibrated_time": f"{runs.budget:g} s (calibrated clock)",
    }.get(runs.axis, f"{runs.budget:g}")


def decide_claim(
    claim: Claim, root: Path, suffix: str = "", fraction: float = 1.0, profile: tuple = ()
) -> tuple[str, list[tuple[object, Decision]]]:
    """The claim's verdict at `fraction` of its budget from the studies under root (suffix
    "-preset": the untuned twins) and its parts' (physgrad.claim). profile: the studies of the
    profile that ran them (default: the claims profile's)."""
    specs = {s.name: s for s in (profile or STUDIES + MAP)}
    cache: dict[str, object] = {}

    def study(name: str) -> object:
        if name not in cache:
            cache[name] = _twin_runs(root, name, suffix, specs.get(name))
        return cache[name]

    rows = decide_parts(claim, study, fraction)
    if suffix:  # a presets' twin that fixes an axis runs only the papers' value of it: say so
        fixed = {n: specs[n].preset for n in specs if isinstance(specs[n].preset, str)}
        rows = [
            (
                part,
                _fixed_by_twin(
                    d, [fixed[n] for n in sorted(studies_of(claim_of_part(part))) if n in fixed]
                ),
            )
            for part, d in rows
        ]
    return claim_verdict(rows, twin=bool(suffix)), rows


def _twin_runs(root: Path, name: str, suffix: str, spec: Study | None) -> object:
    """The runs of study `name` (suffix "-preset": its presets' twin), or the Decision that says
    why there are none."""
    runs = read_study(root / (name + suffix))
    if runs is None:
        if suffix and spec is not None and spec.preset is False:
            return Decision(NOT_RUN, "-", f"{name} has no presets' twin (cut for time)")
        return Decision(OPEN, "-", f"{root / (name + suffix)} has no finished study")
    if suffix and spec is not None and isinstance(spec.preset, str):
        # the presets' study fixes one value of an axis (optim.clip=none): its variants are also
        # known by the tuned study's names, which carry that value ("backprop=C" is "backprop=C
        # clip=none")
        key, _, value = spec.preset.partition("=")
        token = f"{key.rsplit('.', 1)[-1]}={value}"
        runs.paths.update({f"{v} {token}": by for v, by in list(runs.paths.items())})
    return runs


def _fixed_by_twin(decision: Decision, fixed: list[str]) -> Decision:
    """A part the presets' twin does not run because the twin fixes an axis (optim.clip=none, the
    papers' setting) says that, not which variants are missing."""
    if decision.verdict != NOT_RUN or not fixed:
        return decision
    return Decision(NOT_RUN, "-", f"the presets' twin runs {fixed[0]} only (the papers' setting)")


def _part_study(part) -> str:
    return getattr(part, "study", None) or f"{part.easy} -> {part.hard}"


def claims_table(root: Path, studies=None, only_run: bool = False) -> str:
    """One row per part of every claim whose studies are all among `studies` (default: every
    claim); with only_run, of the claims one of whose studies has finished."""
    names = {s.name for s in studies} if studies is not None else None
    lines = [
        "| claim (paper, where) | part | study, budget | tuned: measured | tuned: verdict | "
        "presets: measured | presets: verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for claim in CLAIMS:
        if names is not None and not studies_of(claim) <= names:
            continue
        if only_run and all(read_study(root / name) is None for name in studies_of(claim)):
            continue
        profile = tuple(studies) if studies is not None else ()
        verdict, rows = decide_claim(claim, root, profile=profile)
        preset_verdict, preset_rows = decide_claim(claim, root, "-preset", profile=profile)
        for i, ((part, d), (_, p)) in enumerate(zip(rows, preset_rows)):
            runs = read_study(root / getattr(part, "study", getattr(part, "hard", "")))
            budget = _budget_text(runs) if runs else "-"
            head = (
                (
                    f"**{claim.name}**: tuned **{verdict}**, presets **{preset_verdict}**. "
                    f"{claim.paper}" + (f" ({claim.note})" if claim.note else "")
                )
                if i == 0
                else ""
            )
            lines.append(
                f"| {head} | {part.text()} | {_part_study(part)}, {budget} | {d.measured} | "
                f"{d.verdict} ({d.why}) | {p.measured} | {p.verdict} ({p.why}) |"
            )
    return "\n".join(lines) + "\n"


def claim_verdicts(
    claim: Claim, root: Path, suffix: str = "", profile: tuple = ()
) -> dict[float, str]:
    """The claim's verdict at each fraction of the budget (FRACTIONS: X/4, X/2, X)."""
    return {f: decide_claim(claim, root, suffix, f, profile)[0] for f in FRACTIONS}


def study_protocol(folder: Path) -> tuple[int, int, int] | None:
    """What a finished study ran: (trials per variant and tuning study, tuning studies, seeds),
    read from its trials.csv and runs.csv (0 trials: untuned); None if it has not finished."""
    import pandas as pd

    runs = read_study(folder)
    if runs is None:
        return None
    if runs.protocol is not None:  # kept evidence says what the study ran
        return runs.protocol
    studies = len(runs.tuning) or 1
    seeds = max((len(by) for by in runs.paths.values()), default=0)
    trials = 0
    # one compare, or one per tuning study (<folder>/study-k)
    for table in [folder / "trials.csv", *(s.folder / "trials.csv" for s in tuning_studies(runs))]:
        if not table.is_file():
            continue
        try:
            rows = pd.read_csv(table)
        except ValueError:  # empty: an untuned study (the presets' twin) tried no trials
            rows = pd.DataFrame()
        if {"variant", "trial"} <= set(rows.columns) and len(rows):
            keys = ["variant", "study"] if "study" in rows.columns else ["variant"]
            trials = max(trials, int(rows.groupby(keys)["trial"].nunique().max()))
    return trials, studies, seeds


def _of_planned(runs: StudyRuns) -> str:
    """ " of N" where fewer of a study's N tuning studies have run (the majority is of N)."""
    ran = len(runs.tuning) or 1
    return f" of {runs.planned}" if runs.planned > ran else ""


def _main_study(claim: Claim) -> str:
    """The study that gives a claim its budget: the first part's (a trend's hard end)."""
    part = claim.parts[0]
    return part.hard if isinstance(part, Grows) else part.study


def _share_text(claim: Claim, runs: StudyRuns) -> str:
    """The budget here against the paper's, e.g. "1500 iterations: 4.7% of the paper's 32,000
    iterations"."""
    here = _budget_text(runs)
    seconds = runs.axis in ("wall_time", "calibrated_time")
    if math.isnan(claim.paper_budget) or seconds != claim.paper_seconds:
        return f"{here}; the paper's: {claim.paper_budget_text}"
    share = 100 * runs.budget / claim.paper_budget
    percent = f"{share:.2g}" if share < 10 else f"{share:.0f}"
    return f"{here}: {percent}% of the paper's {claim.paper_budget_text}"


def _share(claim: Claim, runs: StudyRuns) -> float:
    """The budget here over the paper's (NaN where the paper states none in these units)."""
    seconds = runs.axis in ("wall_time", "calibrated_time")
    if math.isnan(claim.paper_budget) or seconds != claim.paper_seconds:
        return math.nan
    return runs.budget / claim.paper_budget


def _claim_variants(claim: Claim, study: str) -> list[str]:
    names = []
    for part in claim.parts:
        if _part_study(part) == study:
            found = [part.variant] if isinstance(part, (Stalls, Reaches)) else [part.a, part.b]
            names += [n for n in found if n not in names]
    return names


def _left_start(claim: Claim, runs: StudyRuns) -> tuple[bool, str]:
    """Whether every variant of the claim's main study has left its start at X (the median over
    its seeds of loss at X / at its first evaluation, physgrad.verdict.left_start), and each
    variant's factor."""
    said, trained = [], True
    for variant in _claim_variants(claim, _main_study(claim)):
        if variant not in runs.paths:
            continue
        starts, finals = [], []
        for study in tuning_studies(runs):
            for curve in study.curves(variant).values():
                starts.append(float(curve.loss[0]) if len(curve.loss) else math.nan)
                finals.append(curve.at(study.budget))
        trained &= left_start(starts, finals)
        ratios = [f / s for s, f in zip(starts, finals) if s > 0 and not math.isnan(f)]
        factor = 1 / float(np.median(ratios)) if ratios else math.nan
        said.append(f"{variant} {short(factor)}x")
    return trained and bool(said), ", ".join(said)


def _verdicts_text(verdicts: dict[float, str]) -> list[str]:
    return [f"**{verdicts[f]}**" if f == 1.0 else verdicts[f] for f in FRACTIONS]


NOT_YET = "not run yet"


def headline_table(root: Path, profile: tuple, further: tuple = ()) -> str:
    """One row per claim: what its studies ran (trials per variant in each tuning study, tuning
    studies, paired seeds), the budget and its share of the paper's, the tuned verdict at X/4, X/2
    and X, the presets' at X, and, where a profile of longer budgets ran the claim (further:
    (folder, that profile's studies) pairs: claims-long, claims-gpu), its budget and verdicts at
    its X/4, X/2 and X, with what it ran. A claim that holds at one budget and does not at another
    says so first (apart, where one of the two is the GPU profile's: the machine changed too)."""
    lines = [
        "| claim | verdict | trials x tuning studies, seeds | budget here | loss fell from the "
        "start | tuned at X/4 | X/2 | X | presets at X | longer budget: X/4, X/2, X |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    names = {s.name for s in profile}
    for claim in CLAIMS:
        if not studies_of(claim) <= names:
            continue
        main = _main_study(claim)
        runs = read_study(root / main)
        if runs is None:
            lines.append(f"| {claim.name} | {NOT_YET} | | | | | | | | |")
            continue
        trials, studies, seeds = study_protocol(root / main)
        tuned = claim_verdicts(claim, root, profile=profile)
        preset, _ = decide_claim(claim, root, "-preset", 1.0, profile)
        if preset == OPEN and read_study(root / f"{main}-preset") is None:
            preset = NOT_YET  # the twin's study has not finished
        longer, seen, elsewhere = "not in a longer profile", list(tuned.values()), []
        for folder, studies_there in further:
            if not studies_of(claim) <= {s.name for s in studies_there}:
                continue
            long_runs = read_study(folder / main)
            if long_runs is None:
                longer = f"{NOT_YET} ({folder.name})"
                continue
            found = claim_verdicts(claim, folder, profile=studies_there)
            # the GPU's profile changes the machine with the budget: its turns are told apart
            (elsewhere if studies_there == GPU else seen).extend(found.values())
            t, k, n = study_protocol(folder / main)
            ran = f"{t} x {k}{_of_planned(long_runs)}, {n}"
            longer = f"{folder.name}, {_budget_text(long_runs)} ({ran}): " + ", ".join(
                _verdicts_text(found)
            )
        turned = (
            "**reverses with the budget**: "
            if HOLDS in seen and FAILS in seen
            else "**turns with a GPU's budget**: "
            if {HOLDS, FAILS} <= {*seen, *elsewhere}
            else ""
        )
        head = f"{turned}{claim.name}"
        trained, fell = _left_start(claim, runs)
        word, why = claim_word(
            tuned[1.0] == HOLDS,
            tuned[1.0] == FAILS,
            tuned[0.5] == FAILS,
            trained,
            _share(claim, runs),
            claim.departs,
        )
        lines.append(
            f"| {head} | **{word}** ({why}) | {trials} x {studies}{_of_planned(runs)}, {seeds} | "
            f"{_share_text(claim, runs)} | {fell} | "
            + " | ".join(_verdicts_text(tuned))
            + f" | {preset} | {longer} |"
        )
    return "\n".join(lines) + "\n"


# --- the regime map
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Cell:
    study: str
    conditioning: float  # the toy's lambda or the oscillators' coupling
    cost_ratio: float  # HIG's calibrated step cost / Adam's
    ratio: float  # median time-to-target HIG / Adam over the seeds
    low: float
    high: float
    reached: tuple[int, int, int]  # seeds where HIG, Adam reached the target, of n
    verdict: str


def map_cell(root: Path, study: Study) -> Cell | None:
    """One cell: the time each variant's seeds take to reach the cell's target, as per-seed ratios
    HIG / Adam with the verdict rule's median and interval (a seed that never reaches it counts as
    infinite, as a divergence does; a pair where neither does is left out and counted, as a pair
    where both diverged). The target is the higher of
    the two variants' median test loss at the budget (readout.highest_median): what the slower
    variant typically gets to, which the faster one reaches in most seeds. compare's target (the
    lower median) is reached by only about half the better variant's seeds, so with 6 seeds most
    pairs are two misses and no cell can be decided."""
    runs = read_study(root / study.name)
    if runs is None or not {"hig", "adam"} <= set(runs.paths):
        return None
    curves = {v: runs.curves(v) for v in ("hig", "adam")}
    _, target = highest_median(
        {v: [c.at(runs.budget) for c in by.values()] for v, by in curves.items()}
    )
    seeds = sorted(set(curves["hig"]) & set(curves["adam"]))
    times = {
        v: [
            curves[v][s].reaches(target, runs.budget) if math.isfinite(target) else math.inf
            for s in seeds
        ]
        for v in curves
    }
    (result,) = compare_variants(
        {v: {s: _constant(t) for s, t in zip(seeds, times[v])} for v in times},
        1.0,
        fractions=(0.25, 0.5, 1.0),
    )
    p = result.at[1.0]
    cost = math.nan
    calibration = root / study.name / "calibration.json"
    if calibration.is_file():
        try:
            costs = json.loads(calibration.read_text())["costs"]
            cost = float(costs["hig"]["step_seconds"]) / float(costs["adam"]["step_seconds"])
        except (OSError, ValueError, KeyError, TypeError, ZeroDivisionError):
            pass
    conditioning = float(
        re.search(r"task\.(?:scale|alpha)=([0-9.e-]+)", " ".join(study.overrides)).group(1)
    )
    reached = (
        sum(math.isfinite(t) for t in times["hig"]),
        sum(math.isfinite(t) for t in times["adam"]),
        len(seeds),
    )
    if not math.isfinite(target):  # both diverged in most seeds: nothing to reach, not "equivalent"
        return Cell(
            study.name, conditioning, cost, math.nan, math.nan, math.nan, reached, NO_TARGET
        )
    return Cell(
        study.name,
        conditioning,
        cost,
        p.ratio,
        ratio_of(p.low),
        ratio_of(p.high),
        reached,
        result.verdict,
    )


def _constant(value: float):
    """A time to target as a curve whose 'loss' is that time, read at x = 1 (inf: never reached)."""
    from physgrad.readout import Curve

    return Curve(np.array([0.0]), np.array([value]), 1.0, False, None)


NO_TARGET = "no target (both diverged in most seeds)"
MAP_VERDICTS = {A_BETTER: "HIG first", B_BETTER: "Adam first", EQUIVALENT: "within 10%"}


def plot_map(cells: dict[str, list[Cell]], path: Path, machine: str, note: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    panels = [(name, found) for name, found in cells.items() if found]
    fig, axes = plt.subplots(
        1, len(panels), figsize=(6.6 * len(panels), 5.0), squeeze=False, layout="constrained"
    )
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-2.0, vmax=2.0)
    for ax, (name, found) in zip(axes[0], panels):
        xs = sorted({c.conditioning for c in found}, reverse=name == "toy")
        rows = sorted({c.study.rsplit("_b", 1)[-1] if name == "toy" else "" for c in found})
        grid = np.full((len(rows), len(xs)), np.nan)
        for c in found:
            i = rows.index(c.study.rsplit("_b", 1)[-1] if name == "toy" else "")
            j = xs.index(c.conditioning)
            if not math.isnan(c.ratio):  # no target: left blank
                grid[i, j] = math.log10(min(max(c.ratio, 1e-2), 1e2))
            dark = abs(grid[i, j]) > 1.2
            ax.text(
                j,
                i,
                f"{MAP_VERDICTS.get(c.verdict, c.verdict)}\n{short(c.ratio)} [{short(c.low)}, "
                f"{short(c.high)}]\n"
                f"reached: HIG {c.reached[0]}, Adam {c.reached[1]} of {c.reached[2]}",
                ha="center",
                va="center",
                fontsize=7.5,
                color="white" if dark else "black",
            )
        image = ax.imshow(grid, cmap="RdBu_r", norm=norm, aspect="auto", origin="lower")
        costs = {
            r: np.nanmedian(
                [
                    c.cost_ratio
                    for c in found
                    if (c.study.rsplit("_b", 1)[-1] if name == "toy" else "") == r
                ]
                or [np.nan]
            )
            for r in rows
        }
        labels = [
            (f"batch {r}\n" if r else "") + f"HIG step\n= {short(costs[r])} x Adam's" for r in rows
        ]
        ax.set_yticks(range(len(rows)), labels, fontsize=8)
        ax.set_xticks(range(len(xs)), [f"{x:g}" for x in xs])
        ax.set_xlabel(
            "lambda (the second component's scale)\nbadly conditioned to the right"
            if name == "toy"
            else "coupling alpha (the cubic spring)\nstiffer to the right",
            fontsize=9,
        )
        ax.set_title(f"{name}: time to target, HIG / Adam (median [95% interval])", fontsize=9)
    fig.colorbar(image, ax=list(axes[0]), label="log10 HIG / Adam time to target (blue: HIG first)")
    fig.suptitle(
        f"Where HIG pays off: both tuned per cell, equal calibrated training time. {machine}"
        + (f"\n{note}" if note else ""),
        fontsize=8,
    )
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def regime_map(root: Path, out: Path, note: str = "") -> str:
    cells = {
        "toy": [c for s in MAP_TOY if (c := map_cell(root, s))],
        "oscillators": [c for s in MAP_OSCILLATOR if (c := map_cell(root, s))],
    }
    if not any(cells.values()):
        return ""
    machines = {read_study(root / s.name).machine for s in MAP if read_study(root / s.name)}
    machine = "; ".join(sorted(m for m in machines if m))
    plot_map(cells, out / "payoff.png", machine, note)
    lines = [
        "\n## Where HIG pays off: a regime map\n",
        "![payoff](payoff.png)\n",
        "Each cell is a `physgrad compare` of Adam and HIG, both tuned in that cell, at equal "
        "calibrated "
        "training time: the time each seed takes to reach the cell's target (the higher of the "
        "two variants' "
        "median test loss at the budget: what the slower one typically gets to), as the ratio HIG "
        "/ Adam with "
        "its 95% interval (below 1: HIG gets there first; a seed that never reaches the target "
        "counts as "
        "infinite, a pair where neither does as a tie; 0 or inf: in the middle pair one variant "
        f"got there and the other did not). Machine: {machine or '-'}.\n",
        "| study | conditioning | HIG step / Adam step | time to target HIG / Adam [95%] | "
        "reached HIG, Adam of n | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for found in cells.values():
        for c in found:
            lines.append(
                f"| {c.study} | {c.conditioning:g} | {short(c.cost_ratio)} | {short(c.ratio)} "
                f"[{short(c.low)}, {short(c.high)}] | "
                f"{c.reached[0]}, {c.reached[1]} of {c.reached[2]} | "
                f"{MAP_VERDICTS.get(c.verdict, c.verdict)} |"
            )
    return "\n".join(lines) + "\n"


def write(root: Path, out: Path, note: str = "", profile: str = "claims") -> str:
    """<profile>.md (claims.md, claims-long.md) into out from the studies under root, with the
    regime map (payoff.png) where the profile has it; returns the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    rule = __doc__.split("\n\n")[2]
    studies = PROFILES[profile]
    # the claims profile's headline also reads the profiles of longer budgets beside its folder
    further = (
        tuple((root.parent / name, PROFILES[name]) for name in ("claims-long", "claims-gpu"))
        if profile == "claims"
        else ()
    )
    text = (
        f"# The papers' claims, measured\n\n{note + chr(10) + chr(10) if note else ''}"
        + rule
        + "\n\n"
        f"Studies under {root}; each study's own table (variants, tuned settings, every pair, "
        "timing): `<study>/compare.md`. X is a study's budget; a verdict at X/4 or X/2 reads "
        "the same runs (tuned for X) earlier.\n\n"
        + headline_table(root, studies, further)
        + "\n"
        + claims_table(root, studies)
        + (regime_map(root, out, note) if set(MAP) <= set(studies) else "")
    )
    (out / f"{profile}.md").write_text(text)
    return text


GENERATED = (
    "<!-- generated from docs/evidence/claims by `python experiments/claims.py "
    "docs/evidence/claims --doc docs/claims.md`: edit the evidence or experiments/claims.py, "
    "not this block -->",
    "<!-- end of the generated block -->",
)


def evidence_block(root: Path) -> str:
    """The verdicts of every claim of the claims profile from its kept evidence under root: the
    headline table, then every part with its numbers."""
    studies = PROFILES["claims"]
    further = tuple(
        (root.parent / name, PROFILES[name])
        for name in ("claims-long", "claims-gpu")
        if (root.parent / name).is_dir()
    )
    machines = sorted(
        {
            runs.machine
            for s in studies
            for suffix in ("", "-preset")
            if (runs := read_study(root / f"{s.name}{suffix}")) is not None and runs.machine
        }
    )
    return (
        f"Decided from the per-seed tables in `{root}` (one per study and per presets' twin, with "
        "the command, commit and machine that produced it beside it); machines: "
        f"{'; '.join(machines) or '-'}. A claim whose studies have no kept evidence says "
        '"not run yet". X is a study\'s budget; bold, the verdict at X.\n\n'
        + headline_table(root, studies, further)
        + "\nEvery part of the claims run so far (tuned and with the presets):\n\n"
        + claims_table(root, studies, only_run=True)
    )


def write_doc(root: Path, doc: Path) -> str:
    """Replace the generated block of doc (between the GENERATED markers) with evidence_block."""
    from physgrad.errors import UserError

    text = doc.read_text()
    start, end = (text.find(marker) for marker in GENERATED)
    if start < 0 or end < start:
        raise UserError(f"{doc}: no generated block (the two markers {GENERATED[0][:40]}...)")
    block = evidence_block(root)
    text = text[: start + len(GENERATED[0])] + "\n\n" + block + "\n" + text[end:]
    doc.write_text(text)
    return block


def main(argv: list[str] | None = None) -> int:
    """Writes OUT_FOLDER/<profile>.md (claims.md, claims-long.md, claims-gpu.md) from STUDIES."""
    parser = argparse.ArgumentParser(
        prog="claims.py", description=__doc__.split("\n\n")[0].replace("\n", " ")
    )
    parser.add_argument(
        "studies", type=Path, help="the profile's study folders (outputs/experiments/claims)"
    )
    parser.add_argument("out", type=Path, nargs="?", help="where claims.md goes (default: STUDIES)")
    parser.add_argument(
        "--doc",
        type=Path,
        help="write the verdicts into this markdown file's generated block (docs/claims.md)",
    )
    parser.add_argument(
        "--keep",
        action="store_true",
        help="keep the finished studies' evidence tables in OUT (docs/evidence/claims) instead",
    )
    args = parser.parse_args(argv)
    from physgrad.errors import UserError

    if not args.studies.is_dir():  # before anything is written: a typo must not create folders
        print(
            f"claims: error: no study folder {args.studies}: give the profile's folder, "
            "e.g. outputs/experiments/claims",
            file=sys.stderr,
        )
        return 2
    # outputs/experiments/claims-long: that profile's
    profile = args.studies.name if args.studies.name in PROFILES else "claims"
    try:
        if args.keep:
            if args.out is None:
                print("claims: error: --keep needs OUT (docs/evidence/claims)", file=sys.stderr)
                return 2
            kept = keep_evidence(args.studies, args.out)
            print(f"kept {len(kept)} studies in {args.out}: {', '.join(kept) or 'none finished'}")
            return 0
        if args.doc is not None:
            print(write_doc(args.studies, args.doc))
            return 0
        print(write(args.studies, args.out or args.studies, profile=profile))
    except UserError as error:  # a study folder that is not what its tables say: one line
        print(f"claims: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
