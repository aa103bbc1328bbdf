"""Integration layer of `physgrad compare` at tiny sizes: variants and knobs from the command line,
tuning, validation and equal-time evaluation on the calibrated clock, resumed and extended studies,
the plan's costs, and study folders, journals and calibrations from someone else read as data."""

import math
from pathlib import Path

import numpy as np
import pytest

import physgrad
from physgrad.comparison import (
    build_variants,
    evaluation_jobs,
    halton_points,
    job_yaml,
    split_overrides,
    study_settings,
)
from physgrad.errors import UserError
from physgrad.optim.capabilities import ADAPTIVE, JACOBIAN
from tests.helpers import session_folder


def test_comma_lists_are_variants_and_everything_else_is_common():
    settings, axes, common, hydra_args = split_overrides(
        [
            "task=oscillator",
            "optim=adam,hig",
            "optim.clip=none,norm",
            "trainer.time_budget=30",
            "compare.trials=4",
            "compare.search.tau=[1e-8,1e-4]",
            "hydra/launcher=joblib",
        ]
    )
    assert settings == {"trials": 4, "search": {"tau": (1e-8, 1e-4)}}
    assert axes == [
        ("optim", ["optim=adam", "optim=hig"]),
        ("optim.clip", ["optim.clip=none", "optim.clip=norm"]),
    ]
    assert common == ["task=oscillator", "trainer.time_budget=30"] and hydra_args == [
        "hydra/launcher=joblib"
    ]
    variants = build_variants(axes, common, study_settings(settings), [])
    assert [v.name for v in variants] == [
        "adam clip=none",
        "adam clip=norm",
        "hig clip=none",
        "hig clip=norm",
    ]
    assert variants[0].space == {"learning_rate": ADAPTIVE.search_range}
    assert variants[2].space == {"learning_rate": JACOBIAN.search_range, "tau": (1e-8, 1e-4)}
    assert variants[2].preset == {"learning_rate": 1.0, "tau": 1e-6}  # the oscillator's HIG preset


def test_with_knobs_each_rule_is_tuned_over_its_own_settings_too():
    """compare.knobs=true: each variant's space is its learning rate and its rule's declared knobs
    (Adam's eps, HIG's tau, Levenberg-Marquardt's and K-FAC's damping, PSGD Kron's preconditioner
    step, Muon's Adam step; L-BFGS's memory and SOAP's preconditioning frequency as whole numbers),
    each range spanning the preset by two decades or more on either side (a whole number: from 2 or
    less to ten times the preset); a tuning file's range (the toy's HIG rate) and compare.search
    (damping) still win; a whole-number knob's variant trains one trial per job; without knobs the
    learning rate alone; compare.knobs must be true or false."""
    import math

    from physgrad.comparison.points import is_whole
    from physgrad.comparison.spec import study_settings
    from physgrad.comparison.tuning import trials_together
    from physgrad.optim.capabilities import capabilities

    rules = "adam,hig,levenberg_marquardt,kfac,psgd_kron,muon,lbfgs,soap"
    settings, axes, common, _ = split_overrides(
        ["task=toy", f"optim={rules}", "compare.knobs=true", "compare.search.damping=[1e-4,1e-2]"]
    )
    variants = build_variants(axes, common, study_settings(settings), [])
    spaces = {v.name: v.space for v in variants}
    assert {name: sorted(space) for name, space in spaces.items()} == {
        "adam": ["eps", "learning_rate"],
        "hig": ["learning_rate", "tau"],
        "levenberg_marquardt": ["damping", "learning_rate"],
        "kfac": ["damping", "learning_rate"],
        "psgd_kron": ["learning_rate", "preconditioner_lr"],
        "muon": ["adam_learning_rate", "learning_rate"],
        "lbfgs": ["learning_rate", "memory_size"],
        "soap": ["learning_rate", "precondition_frequency"],
    }
    assert spaces["lbfgs"]["memory_size"] == (2, 100) and is_whole(spaces["lbfgs"]["memory_size"])
    assert spaces["soap"]["precondition_frequency"] == (1, 100)
    assert not is_whole(spaces["adam"]["eps"])
    soap = next(v for v in variants if v.name == "soap")
    assert not trials_together(soap, "iteration")  # the frequency shapes the program
    assert spaces["hig"]["learning_rate"] == (0.01, 100.0)  # conf/tuning/toy_hig.yaml
    assert spaces["kfac"]["damping"] == spaces["levenberg_marquardt"]["damping"] == (1e-4, 1e-2)
    for variant in variants:
        for key, low, high in capabilities(variant.config.optim).knobs:
            preset = float(variant.config.optim[key])
            decades = min(math.log10(preset / low), math.log10(high / preset))
            whole = is_whole((low, high)) and low <= 2 and high >= 10 * preset
            assert decades >= 2 or high == 1.0 or whole, (variant.name, key)
    plain = build_variants(axes, common, study_settings({}), [])
    assert all(list(v.space) == ["learning_rate"] for v in plain)
    with pytest.raises(UserError, match="compare.knobs='yes': use true or false"):
        study_settings({"knobs": "yes"})


def test_a_variant_the_scene_refuses_stops_the_study_before_anything_trains(tmp_path):
    from physgrad.comparison import run_study

    with pytest.raises(UserError, match="variant bptt: optim=bptt needs a closed-loop controller"):
        run_study(["task=toy", "optim=adam,bptt", f"compare.dir={tmp_path}"], say=lambda line: None)
    assert not (tmp_path / "tune").exists()


def build_that_raises(key: object = None, **settings: object) -> None:
    """A user's scene whose own code fails while it builds."""
    raise RuntimeError("the mesh file is missing")


def test_a_scene_whose_build_raises_stops_the_study_in_one_line(tmp_path):
    """The pre-build check of every variant turns an exception of the scene's own code into one line
    that names the variant and the cause (it was a 41-line traceback), before anything trains."""
    from physgrad.comparison import run_study

    target = "task._target_=tests.integration.test_compare.build_that_raises"
    with pytest.raises(UserError) as caught:
        run_study(
            ["task=toy", target, "optim=adam,gd", f"compare.dir={tmp_path}"], say=lambda line: None
        )
    message = str(caught.value)
    assert "\n" not in message and "variant adam" in message
    assert "RuntimeError: the mesh file is missing" in message
    assert not (tmp_path / "tune").exists()


def test_equal_time_evaluations_interleave_the_variants_and_equal_iterations_train_seeds_together():
    settings, axes, common, _ = split_overrides(
        ["task=toy", "optim=adam,gd", "trainer.time_budget=5"]
    )
    s = study_settings({**settings, "seeds": 3})
    variants = build_variants(axes, common, s, [])
    # two tuning studies: each study's own tuned rate and its own seeds (0..2 and 3..5)
    best = [{v.name: {"learning_rate": rate} for v in variants} for rate in (0.01, 0.02)]
    timed = evaluation_jobs(variants, best, s, common, {"task", "optim"}, "wall_time", 5.0)
    assert list(timed) == [
        f"eval_{study}v{v}_s{seed + offset}"
        for seed in range(3)
        for study, offset in (("", 0), ("st1_", 3))
        for v in (0, 1)
    ]
    assert "learning_rate: 0.02" in timed["eval_st1_v0_s5"] and "seed: 5" in timed["eval_st1_v0_s5"]
    counted = evaluation_jobs(variants, best, s, common, {"task", "optim"}, "iteration", 300.0)
    assert list(counted) == ["eval_v0", "eval_v1", "eval_st1_v0", "eval_st1_v1"]
    assert "seeds: 3" in counted["eval_v0"] and "seeds: 3" in counted["eval_st1_v1"]
    assert "seed: 0" in counted["eval_v1"] and "seed: 3" in counted["eval_st1_v1"]
    assert "learning_rate: 0.01" in counted["eval_v1"] and "eval_every: 15" in counted["eval_v1"]
    assert "learning_rate: 0.02" in counted["eval_st1_v1"]
    # on the calibrated clock every seed runs the same steps whatever the load: together, as counted
    calibrated = evaluation_jobs(
        variants, best, s, common, {"task", "optim"}, "calibrated_time", 5.0
    )
    assert list(calibrated) == list(counted)
    assert "seeds: 3" in calibrated["eval_st1_v0"] and "seed: 3" in calibrated["eval_st1_v0"]
    # a rule that searches a line: one job per seed, each of one seed
    settings, axes, common, _ = split_overrides(
        ["task=toy", "optim=adam,lbfgs", "trainer.iterations=300"]
    )
    variants = build_variants(axes, common, s, [])
    best = [{v.name: {"learning_rate": 0.1} for v in variants}]
    counted = evaluation_jobs(variants, best, s, common, {"task", "optim"}, "iteration", 300.0)
    assert list(counted) == ["eval_v0", "eval_v1_s0", "eval_v1_s1", "eval_v1_s2"]
    assert "seeds: 1" in counted["eval_v1_s2"] and "seed: 2" in counted["eval_v1_s2"]


# make test-long: two toy runs, with and without validation; make test keeps
# test_validation_reads_the_held_out_loss_without_paying_for_the_scene_metrics (the held-out loss
# on sets that are not the test sets, through physgrad.run with trainer.validation=true)
@pytest.mark.long
def test_validation_data_are_held_out_and_evaluated_beside_the_test_set(tmp_path):
    run = physgrad.run(
        "task=toy",
        "optim=adam",
        "trainer.iterations=20",
        "trainer.eval_every=10",
        "trainer.validation=true",
        out_dir=tmp_path,
    )
    loss, validation = run.eval["loss"], run.eval["validation_loss"]
    assert loss.shape == validation.shape == (3,) and not np.allclose(loss, validation)
    assert np.allclose(loss, validation, rtol=0.3)  # the same distribution: close, not equal
    plain = physgrad.run(
        "task=toy", "optim=adam", "trainer.iterations=20", out_dir=tmp_path / "plain"
    )
    assert "validation_loss" not in plain.eval  # nobody pays for what they did not ask


def test_validation_reads_the_held_out_loss_without_paying_for_the_scene_metrics(
    tmp_path, monkeypatch
):
    """The validation sets get the loss only (a KS stability rollout would cost 200 steps per
    state), and it is the loss the full evaluation gives on the same sets."""
    import physgrad.runner

    real, captured = physgrad.runner.compile_training, {}

    def capture(scene, rule, seeds, batch_size):
        captured.update(compiled=real(scene, rule, seeds, batch_size), seeds=seeds)
        return captured["compiled"]

    monkeypatch.setattr(physgrad.runner, "compile_training", capture)
    run = physgrad.run(
        "task=toy",
        "optim=adam",
        "trainer.iterations=5",
        "trainer.validation=true",
        out_dir=tmp_path,
    )
    compiled, seeds = captured["compiled"], captured["seeds"]
    # the toy has metrics: the test sets still get them
    assert {"error_first", "error_second"} <= set(run.eval)
    validated = compiled.validate(compiled.params, seeds.validation_sets)
    assert set(validated) == {"loss"}
    # toy: the same shapes as the test sets
    full = compiled.evaluate(compiled.params, seeds.validation_sets)
    np.testing.assert_allclose(np.asarray(validated["loss"]), np.asarray(full["loss"]), rtol=1e-6)
    assert not np.allclose(
        np.asarray(validated["loss"]),
        np.asarray(compiled.evaluate(compiled.params, seeds.test_sets)["loss"]),
    )


def test_a_loss_that_blows_up_without_nan_ends_the_run_diverged(tmp_path):
    """A training loss past trainer.divergence_factor times its first value ends the run diverged,
    with why."""
    run = physgrad.run(
        "task=toy",
        "optim=gd",
        "optim.learning_rate=3",
        "trainer.iterations=200",
        "trainer.divergence_factor=10",
        out_dir=tmp_path,
    )
    assert run.attrs["status"] == "diverged" and "blow-up without NaN" in run.attrs["reason"]
    assert (
        np.isfinite(run.train["loss"]).all() and run.train["loss"][-1] > 10 * run.train["loss"][0]
    )


# a small finished study that several tests read or copy: two variants, two trials in each of two
# tuning studies, six seeds each, in a folder whose name holds a comma, a space, a quote and letters
# beyond ASCII (quoted as Hydra needs on the command line)
SMALL_STUDY = [
    "task=toy",
    "optim=adam,gd",
    "trainer.iterations=30",
    "compare.trials=2",
    "compare.studies=2",
    "compare.seeds=6",
    # the tables without the figures (matplotlib's layout was half of a resume of this study);
    # tests/e2e/test_compare.py draws them
    "figures=false",
]


@pytest.fixture(scope="session")
def small_study(tmp_path_factory):
    """SMALL_STUDY, run once for the whole test session: the first process of the session to ask
    runs it (under a lock), every other one resumes the finished study, which reads it."""
    import fcntl

    import physgrad.comparison  # noqa: F401 - importing the module leaves the function physgrad.compare in place
    from physgrad.comparison.jobs import hydra_quoted

    root = session_folder(tmp_path_factory)
    folder = root / "small study" / "a,b ü's [x]"
    folder.parent.mkdir(exist_ok=True)
    with open(root / "small study.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return physgrad.compare(*SMALL_STUDY, f"compare.dir={hydra_quoted(str(folder))}")


def copy_of(study, destination: Path) -> list[str]:
    """A copy of a finished study's folder, and the arguments that resume it there."""
    import shutil

    shutil.copytree(study.folder, destination, symlinks=True)
    return [*SMALL_STUDY, f"compare.dir={destination}"]


def test_the_python_call_returns_the_tables(small_study):
    study = small_study
    # two tuning studies of two trials per variant, each on its own seed and points
    assert list(zip(study.trials.study, study.trials.variant)) == [
        (k, v) for k in (0, 1) for v in ("adam", "adam", "gd", "gd")
    ]
    rates = study.trials.groupby(["study", "variant"])["learning_rate"].apply(list)
    assert rates[0, "adam"] != rates[1, "adam"] and rates[0, "gd"] != rates[1, "gd"]
    tuned = {
        physgrad.read_run(p).attrs["seed"] for p in (study.folder / "tune").rglob("results.h5")
    }
    assert tuned == {1_000_000, 1_000_001}
    # each study's best evaluated on six seeds of its own, paired between the variants
    assert len(study.runs) == 24 and set(study.runs.study) == {0, 1}
    seeds = study.runs.groupby(["study", "variant"]).seed.apply(sorted)
    assert seeds[0, "adam"] == seeds[0, "gd"] == list(range(6))
    assert seeds[1, "adam"] == seeds[1, "gd"] == list(range(6, 12))
    # the verdicts over both studies first, then each study's own
    assert list(study.comparisons.study) == ["all"] * 3 + [0] * 3 + [1] * 3
    assert len(study.verdicts) == 1 and len(study.verdicts[0].studies) == 2
    assert study.verdicts[0].verdict == study.comparisons.verdict.iloc[2]
    assert study.verdicts[0].at[1.0].pairs == sum(
        s.at[1.0].pairs for s in study.verdicts[0].studies
    )
    assert (study.folder / "compare.md").read_text() == study.text
    # figures=false: the report's tables, no figure anywhere in the study
    assert (study.folder / "report" / "runs.csv").is_file()
    assert not [p for p in study.folder.rglob("*") if p.suffix in (".png", ".pdf")]
    assert "must hold in 2 of the 2 tuning studies" in study.text
    # two trials per study: said under the variants (physgrad.comparison.coverage)
    variants_part = study.text.split("## Variants")[1]
    assert "warning: 2 trials per tuning study" in variants_part.split("Target:")[0]
    # what the design could detect, from the spread it measured: in the table and the CSV
    assert "| A lower in | detectable |" in study.text
    overall = study.comparisons[study.comparisons.study == "all"]
    assert (overall.detectable_ratio > 1.1).all()
    assert study.comparisons[study.comparisons.study == 0].detectable_ratio.isna().all()
    # an iteration budget still says what a step costs each variant
    assert "| adam | " in study.text.split("step time: median of the runs' p50")[1]


@pytest.mark.long
def test_an_equal_time_study_runs_on_the_calibrated_clock_and_can_reuse_a_calibration(tmp_path):
    """A time budget: the variants are calibrated once (calibration.json), every run stops where
    iterations x its variant's cost reach the budget (PSGD Kron's: where the plain-loop sum of
    s - u + p_t u over its steps does, u its update's cost, which the calibration measures for it
    alone), verdicts read the calibrated clock, and a second
    study given the first's calibration trains exactly as far."""
    import json

    from physgrad.optim.psgd import annealed_probability

    common = [
        "task=toy",
        "optim=adam,gauss_newton,psgd_kron",
        "trainer.time_budget=0.4",
        "compare.trials=1",
        "compare.studies=1",
        "compare.seeds=6",
        "trainer.batch_size=16",
        "figures=false",
    ]
    study = physgrad.compare(*common, f"compare.dir={tmp_path / 'first'}")
    calibration = json.loads((study.folder / "calibration.json").read_text())
    costs = {name: c["step_seconds"] for name, c in calibration["costs"].items()}
    assert costs["gauss_newton"] > costs["adam"] > 0
    assert [n for n, c in calibration["costs"].items() if "update_seconds" in c] == ["psgd_kron"]
    psgd = calibration["costs"]["psgd_kron"]
    assert 0 <= psgd["update_seconds"] <= psgd["step_seconds"] and psgd["advanced_step"] == 4007
    charged = np.cumsum(
        psgd["step_seconds"]
        - psgd["update_seconds"]
        + annealed_probability(np.arange(1, 100_001)) * psgd["update_seconds"]
    )
    # measured by a job of the study, launched like the others (on a cluster: where the jobs run)
    measured = study.folder / "calibration" / "+compare_job=calibration" / "calibration.json"
    assert json.loads(measured.read_text()) == calibration
    assert calibration["machine"]["hostname"]
    for _, row in study.runs.iterrows():
        if row.variant == "psgd_kron":
            expected = int(np.argmax(charged >= 0.4 - 1e-12)) + 1
            assert row.iterations == expected or row.status != "completed", row
            assert row.calibrated_seconds == pytest.approx(charged[row.iterations - 1], rel=1e-9)
            continue
        cost = costs[row.variant]
        assert row.iterations == math.ceil(0.4 / cost - 1e-9) or row.status != "completed", row
        assert row.calibrated_seconds == pytest.approx(row.iterations * cost)
    assert "Clock: calibrated" in study.text and "contended runs A, B" in study.text
    assert "A scheduled update" in study.text and "psgd_kron: " in study.text
    # each variant's 6 evaluation seeds trained together in one job, which their files record
    jobs = sorted(p.name for p in (study.folder / "eval").glob("+compare_job=*"))
    assert jobs == ["+compare_job=eval_v0", "+compare_job=eval_v1", "+compare_job=eval_v2"]
    assert set(study.runs.wall_time_shared_by) == {6}
    again = physgrad.compare(
        *common,
        f"compare.calibration={study.folder / 'calibration.json'}",
        f"compare.dir={tmp_path / 'second'}",
    )
    assert list(again.runs.iterations) == list(study.runs.iterations)
    with pytest.raises(UserError, match="compare.calibration"):
        physgrad.compare(
            "task=toy",
            "optim=adam,gd",
            "trainer.time_budget=0.4",
            "compare.trials=1",
            f"compare.calibration={study.folder / 'calibration.json'}",
            f"compare.dir={tmp_path / 'x'}",
        )


def test_a_learning_rate_schedule_is_tuned_by_its_init_value_and_keeps_its_shape():
    """ks with Adam has the study's staircase decay (conf/tuning/ks_adam.yaml): compare tunes its
    init_value; a tuned job's config keeps the decay, whose Adam step after 2,000 updates is 0.9
    times the first."""
    import jax
    import jax.numpy as jnp
    from omegaconf import OmegaConf

    from physgrad.comparison import split_overrides, study_settings
    from physgrad.optim import build_rule

    given, axes, common, _ = split_overrides(["task=ks", "optim=adam,gd", "trainer.iterations=10"])
    adam, gd = build_variants(axes, common, study_settings(given), [])
    assert list(adam.space) == ["learning_rate.init_value"] and list(gd.space) == ["learning_rate"]
    assert adam.preset == {"learning_rate.init_value": pytest.approx(1e-4)}
    text = job_yaml(
        [*common, *adam.overrides], {"task", "optim"}, {"optim.learning_rate.init_value": 3e-4}
    )
    node = OmegaConf.create(text.split("\n", 2)[2])  # the job file without its package line
    merged = OmegaConf.merge(adam.config, {k: v for k, v in node.items() if k != "defaults"})
    assert merged.optim.learning_rate.init_value == pytest.approx(3e-4)
    assert (
        merged.optim.learning_rate.transition_steps == 2000
        and merged.optim.learning_rate.decay_rate == 0.9
    )
    rule = build_rule(merged.optim)
    params = {"w": jnp.zeros(3)}
    state = rule.transform.init(params)
    update = jax.jit(rule.transform.update)
    grads = {"w": jnp.ones(3)}
    first, state = update(grads, state, params)
    for _ in range(1999):
        later, state = update(grads, state, params)
    step_2000, _ = update(grads, state, params)  # the 2001st update: count 2000, one decay
    assert float(first["w"][0]) == pytest.approx(-3e-4, rel=1e-3)
    assert float(later["w"][0]) == pytest.approx(-3e-4, rel=1e-3)
    assert float(step_2000["w"][0]) == pytest.approx(-3e-4 * 0.9, rel=1e-3)


@pytest.mark.long
def test_a_finished_study_given_more_trials_tunes_on_from_where_it_stopped(tmp_path):
    """trials 1 then 3: the first trial is not run again (its results file is untouched), the two
    new ones are the next Halton points, and the folder is the same study; given a second tuning
    study, it adds that study's trials and evaluation and trains nothing of the first again;
    another budget is still another study."""
    args = [
        "task=toy",
        "optim=adam,gd",
        "trainer.iterations=20",
        "compare.seeds=6",
        f"compare.dir={tmp_path / 's'}",
        "figures=false",
    ]
    said = []
    physgrad.compare(*args, "compare.trials=1", "compare.studies=1", progress=said.append)
    # from Python the progress the console shows, here to a function of one line
    assert any(line.startswith("tune: ") for line in said)
    assert any(line.startswith("eval: ") for line in said)
    # adam's trials train together: trial 0 is member 0 of the first job
    first = tmp_path / "s" / "tune" / "+compare_job=tune_v0_t000" / "trial=0" / "results.h5"
    stamp = first.stat().st_mtime_ns
    study = physgrad.compare(*args, "compare.trials=3", "compare.studies=1")
    assert first.stat().st_mtime_ns == stamp
    assert list(study.trials.variant) == ["adam"] * 3 + ["gd"] * 3
    expected = halton_points({"learning_rate": (1e-4, 10.0)}, 3, 1_000_000)  # conf/tuning/toy_adam
    assert list(study.trials[study.trials.variant == "adam"].learning_rate) == pytest.approx(
        [p["learning_rate"] for p in expected]
    )
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "s").rglob("results.h5")}
    two = physgrad.compare(*args, "compare.trials=3", "compare.studies=2")
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())
    assert list(two.trials.study) == [0] * 6 + [1] * 6 and len(two.runs) == 24
    assert len(two.verdicts[0].studies) == 2
    with pytest.raises(UserError, match="holds another study"):
        physgrad.compare(*args[:2], "trainer.iterations=30", *args[3:], "compare.trials=3")


@pytest.mark.long
def test_two_names_for_one_rule_are_tuned_alike_in_either_order_and_equivalent(
    tmp_path, busy_machine
):
    """A copy of adam.yaml under another name, listed second and then first, on a machine loaded by
    two spinning processes (an iteration budget does not read the clock): the same trial points
    and tuned rate in each of the four tuning studies (the default; the points do not depend on a
    variant's position or name), identical paired runs, and the verdict "equivalent"."""
    # (two tuning studies: each is a study of its own points, and the four of the default add
    # nothing to what is checked here)
    from physgrad.configs import CONF_DIR

    optim = tmp_path / "conf" / "optim"
    optim.mkdir(parents=True)
    (optim / "adam_copy.yaml").write_text(
        (CONF_DIR / "optim" / "adam.yaml").read_text().replace("name: adam", "name: adam_copy")
    )
    # and its tuning file on the toy (the ranges it is tuned over there), as a copy would have
    (optim.parent / "tuning").mkdir()
    (optim.parent / "tuning" / "toy_adam_copy.yaml").write_text(
        (CONF_DIR / "tuning" / "toy_adam.yaml").read_text()
    )
    common = [
        "task=toy",
        "trainer.iterations=30",
        "compare.trials=2",
        "compare.studies=2",
        "compare.seeds=6",
        "figures=false",
    ]
    studies = [
        physgrad.compare(
            *common, f"optim={order}", f"compare.dir={tmp_path / str(k)}", config_dir=optim.parent
        )
        for k, order in enumerate(("adam,adam_copy", "adam_copy,adam"))
    ]
    for study in studies:
        tried = study.trials.groupby("variant")["learning_rate"].apply(list)
        assert len(tried["adam"]) == 4  # two trials in each of two tuning studies
        assert tried["adam"] == tried["adam_copy"]
        losses = study.runs.pivot(
            index=["study", "seed"], columns="variant", values="test_loss_at_1"
        )
        assert (losses["adam"] == losses["adam_copy"]).all()
        assert [v.verdict for v in study.verdicts] == ["equivalent"]
    assert list(studies[0].trials.sort_values(["variant", "learning_rate"]).learning_rate) == list(
        studies[1].trials.sort_values(["variant", "learning_rate"]).learning_rate
    )


@pytest.fixture
def busy_machine():
    """Two processes that spin for the length of a test: the machine's load the calibration and
    the runs share (injected, not hoped for)."""
    import subprocess
    import sys

    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    yield
    for spinner in spinners:
        spinner.kill()
        spinner.wait()


@pytest.mark.long
def test_twins_at_equal_time_are_never_better_under_load_in_either_order(tmp_path, busy_machine):
    """A copy of adam.yaml under another name against adam at a time budget on the calibrated
    clock, on a machine loaded by two spinning processes, listed in both orders, each calibrated
    anew: the copies are one compiled program, so they get one step cost by construction, train as
    far and are never "better"; their runs are identical. (The same twins at an iteration budget:
    test_two_names_for_one_rule_...)"""
    import json

    from physgrad.configs import CONF_DIR
    from physgrad.verdict import A_BETTER, B_BETTER

    optim = tmp_path / "conf" / "optim"
    optim.mkdir(parents=True)
    (optim / "adam_copy.yaml").write_text(
        (CONF_DIR / "optim" / "adam.yaml").read_text().replace("name: adam", "name: adam_copy")
    )
    # and its tuning file on the toy (the ranges it is tuned over there), as a copy would have
    (optim.parent / "tuning").mkdir()
    (optim.parent / "tuning" / "toy_adam_copy.yaml").write_text(
        (CONF_DIR / "tuning" / "toy_adam.yaml").read_text()
    )
    common = ["task=toy", "trainer.time_budget=0.4", "compare.trials=2", "compare.studies=1"]
    common += ["compare.seeds=6", "figures=false"]
    for order in ("adam,adam_copy", "adam_copy,adam"):
        folder = tmp_path / order.replace(",", "-")
        study = physgrad.compare(
            *common, f"optim={order}", f"compare.dir={folder}", config_dir=optim.parent
        )
        verdicts = [v.verdicts[f][0] for v in study.verdicts for f in v.verdicts] + [
            s.verdicts[f][0] for v in study.verdicts for s in v.studies for f in s.verdicts
        ]
        assert A_BETTER not in verdicts and B_BETTER not in verdicts, order
        losses = study.runs.pivot(
            index=["study", "seed"], columns="variant", values="test_loss_at_1"
        )
        assert (losses["adam"] == losses["adam_copy"]).all()
        costs = json.loads((folder / "calibration.json").read_text())["costs"]
        assert costs["adam"] == costs["adam_copy"]
        iterations = study.runs.pivot(
            index=["study", "seed"], columns="variant", values="iterations"
        )
        assert (iterations["adam"] == iterations["adam_copy"]).all()


def test_a_tuned_value_at_the_edge_of_its_range_is_warned_about():
    """The outer tenth of the log range on either side is the edge (1.6e-05 and 0.08 of
    [1e-05, 0.1]), the middle is not (0.001); a variant evaluated as configured has nothing
    tuned."""
    from physgrad.comparison import Variant
    from physgrad.comparison.coverage import edge_lines

    space = {"learning_rate": (1e-5, 1e-1)}
    variants = [Variant(name, [f"optim={name}"], None, dict(space)) for name in "abcd"]
    best = {
        "a": {"learning_rate": 1.6e-5},
        "b": {"learning_rate": 1e-3},
        "c": {"learning_rate": 0.08},
        "d": {},
    }
    lines = [line for line in edge_lines(variants, [best]) if line]
    assert len(lines) == 2
    assert lines[0].startswith("warning: a's tuned learning_rate=1.6e-05 lies in the lowest tenth")
    assert lines[1].startswith("warning: c's tuned learning_rate=0.08 lies in the highest tenth")
    assert "compare.search.learning_rate=[low,high]" in lines[1]
    assert edge_lines(variants[1:2] + variants[3:], [best]) == []
    # a plateau: a's trials in the lowest fifth (below 6.3e-05) scored within 1.25x of each other
    # (the toy's Gauss-Newton barely moving at any small rate): a note, not the advice to widen
    flat = [
        {"variant": "a", "learning_rate": rate, "validation_loss": score}
        for rate, score in ((1.6e-5, 0.46), (3e-5, 0.52), (5e-5, 0.49), (1e-3, 5.0))
    ]
    (line,) = [x for x in edge_lines(variants[:1], [best], flat) if x]
    assert line.startswith("note: a's tuned learning_rate=1.6e-05 lies in the lowest tenth")
    assert "on a plateau: its trials in the lowest fifth scored 0.46 to 0.52" in line
    # two trials, or scores 2x apart, are no plateau
    for rows in (flat[:2], [{**flat[0], "validation_loss": 0.2}, *flat[1:]]):
        assert edge_lines(variants[:1], [best], rows)[1].startswith("warning: a's tuned")


def test_the_plan_costs_every_job_of_a_study_from_compile_and_step_times():
    """variant_cost's arithmetic on given costs: tuning = trials x studies runs of (budget x step +
    the held-out evaluations) and a start-up and compile per job (one per study where the trials
    train together, one per trial otherwise); an iteration budget evaluates a vectorised
    variant in one job per study (seeds x budget x step of training and seeds x evaluations; the
    Jacobian rules too, their float64 retry batching), a time budget in one job per seed. The
    evaluations: at the start and every eval_every iterations (100 here), and with a time budget
    also every budget / 20 seconds."""
    from physgrad.comparison.plan import Measured, run_config, variant_cost
    from physgrad.comparison.spec import StudyPlan

    settings, axes, common, _ = split_overrides(
        ["task=toy", "optim=adam,gauss_newton", "compare.trials=4", "compare.studies=2"]
    )
    s = study_settings({**settings, "seeds": 6})
    adam, gauss_newton = build_variants(axes, common, s, [])
    assert run_config(adam).trainer.eval_every == 100
    plan = StudyPlan([adam, gauss_newton], s, common, {"task", "optim"}, "iteration", 100.0)
    # compile 2 s, step 0.01 s, first evaluation 0.5 s (its compile), later ones 0.1 s; start-up 3 s
    measured = Measured(2.0, 0.01, 0.5, 0.1)
    cost = variant_cost(plan, adam, measured, start_up=3.0)
    # 2 evaluations a run (start, iteration 100): 0.5 + 0.1; a study's 4 trials train together in
    # one job (start-up and compile once per study), each trial's training and evaluations counted
    assert (cost.tuning_runs, cost.tuning_seconds) == (8, pytest.approx(2 * 5.0 + 8 * (1.0 + 0.6)))
    assert (cost.evaluation_jobs, cost.evaluation_seconds) == (
        2,
        pytest.approx(2 * 5.0 + 12 * (1.0 + 0.6)),
    )
    retrying = variant_cost(plan, gauss_newton, measured, start_up=3.0)  # float64 retry batches
    assert (retrying.evaluation_jobs, retrying.evaluation_seconds) == (
        2,
        pytest.approx(2 * 5.0 + 12 * (1.0 + 0.6)),
    )
    timed = StudyPlan([adam, gauss_newton], s, common, {"task", "optim"}, "wall_time", 5.0)
    cost = variant_cost(timed, adam, measured, start_up=3.0)
    # 1 + 500 iterations / 100 + 20 (every 5 / 20 s) = 26 evaluations: 0.5 + 25 x 0.1 = 3 s; the
    # trials, and each study's seeds, train together on the calibrated clock
    assert cost.tuning_seconds == pytest.approx(2 * 5.0 + 8 * (5.0 + 3.0))
    assert cost.evaluation_jobs == 2
    assert cost.seconds == pytest.approx(2 * 5.0 + 8 * 8.0 + 2 * 5.0 + 12 * (5.0 + 3.0))
    # on the measured clock each trial is a job of its own
    measured_clock = study_settings({**settings, "seeds": 6, "clock": "measured"})
    alone = StudyPlan([adam], measured_clock, common, {"task", "optim"}, "wall_time", 5.0)
    alone_cost = variant_cost(alone, adam, measured, start_up=3.0)
    assert alone_cost.tuning_seconds == pytest.approx(8 * (5.0 + 5.0 + 3.0))
    # and each evaluation seed too
    assert alone_cost.evaluation_jobs == 12
    # without start-up and evaluations: compile and training alone
    bare = variant_cost(timed, adam, Measured(2.0, 0.01, 0.0, 0.0))
    assert bare.seconds == pytest.approx(2 * 2.0 + 8 * 5.0 + 2 * 2.0 + 12 * 5.0)
    # building the scene and data: once per job, like the compile
    built = variant_cost(timed, adam, Measured(2.0, 0.01, 0.0, 0.0, build_seconds=1.5))
    assert built.seconds == pytest.approx(bare.seconds + (2 + 2) * 1.5)


def test_the_plan_times_a_tuning_job_at_the_trial_points_it_will_train(monkeypatch):
    """A variant whose trials train together is timed as its tuning job trains them: the first
    tuning study's trial points (those the tuning will try, key by key) as the job's trial_values,
    all on the tuning seed, the step divided among them; without tuning, a variant whose seeds
    train together is timed on the study's seeds."""
    from omegaconf import OmegaConf

    import physgrad.timing
    from physgrad.comparison import plan as planning
    from physgrad.comparison.points import halton_points, point_dimensions
    from physgrad.comparison.spec import StudyPlan

    settings, axes, common, _ = split_overrides(["task=toy", "optim=adam,gd", "compare.trials=4"])
    s = study_settings({**settings, "seeds": 6})
    adam, gd = build_variants(axes, common, s, [])
    study = StudyPlan([adam, gd], s, common, {"task", "optim"}, "iteration", 100.0)
    points = halton_points(adam.space, 4, s.tune_seed, point_dimensions([adam.space, gd.space]))
    count, values = planning.members(study, adam)
    assert count == 1 and values == {k: [p[k] for p in points] for k in sorted(adam.space)}
    assert len(set(values["learning_rate"])) == 4
    seen = {}

    def compiled_step(cfg, seeds):
        seen.update(values=OmegaConf.to_container(cfg.trial_values), seeds=seeds)
        raise StopIteration  # what it was asked to build is all this test reads

    monkeypatch.setattr(physgrad.timing, "compiled_step", compiled_step)
    with pytest.raises(StopIteration):
        planning.measure(adam, 7, *planning.members(study, adam))
    assert seen == {"values": values, "seeds": [7] * 4}
    untuned = study_settings({**settings, "seeds": 6, "tune": False})
    plain = StudyPlan([adam, gd], untuned, common, {"task", "optim"}, "iteration", 100.0)
    assert planning.members(plain, adam) == (6, None)


def test_a_studys_jobs_share_a_compilation_cache_in_the_users_cache_unless_they_name_one(
    tmp_path, monkeypatch
):
    """The cache holds compiled code, so it is the user's (PHYSGRAD_CACHE/jax), never the study
    folder's, which may come from someone else."""
    from physgrad.comparison.jobs import job_environment

    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.delenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", raising=False)
    env = job_environment()
    assert env["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "cache" / "jax")
    assert env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "/elsewhere")
    env = job_environment()
    assert env["JAX_COMPILATION_CACHE_DIR"] == "/elsewhere"
    assert "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in env


def test_a_study_folder_from_someone_else_runs_no_code_and_its_links_are_not_followed(
    tmp_path, small_study
):
    """A study folder holds configs of the jobs as a record only: a tuning option planted in its
    configs/ (here one that would change the budget and build a logger whose _target_ runs a shell
    command, or a function of a module in the working folder, which the target policy accepts
    from the user's own command line or config folder) is never on the jobs' config search path,
    nor is a finished job's .hydra/config.yaml read back; a link planted where a job's record is
    written is replaced, not written through, and a phase log that is a link is refused in one
    line. The folder is a finished study's, one of whose evaluation jobs must run again."""
    study, outside, marker = tmp_path / "study", tmp_path / "outside.yaml", tmp_path / "ran"
    args = copy_of(small_study, study)
    for job in (study / "eval").glob("+compare_job=eval_st1_*"):  # tuning study 1's runs again
        job.rename(tmp_path / job.name)
    (study / "configs" / "tuning").mkdir(exist_ok=True)
    working_folder = (  # tests.helpers.plant: a FIFO at the marker, were it ever called
        f"    _target_: tests.helpers.plant\n    path: {marker}\n    kind: fifo\n"
        f"    other: {marker}\n"
    )
    for planted, target in (
        ("tuning/toy_gd.yaml", f"    _target_: os.system\n    command: touch {marker}\n"),
        ("tuning/toy_adam.yaml", working_folder),
    ):
        (study / "configs" / planted).write_text(
            f"# @package _global_\ntrainer:\n  iterations: 7\nlogger:\n  evil:\n{target}"
        )
    records = list((study / "eval").glob("+compare_job=eval_v*/.hydra/config.yaml"))
    assert records  # tuning study 0's finished jobs: their records stay
    for hydra in records:
        hydra.write_text(f"task:\n  name: toy\n{working_folder}")
    outside.write_text("theirs\n")
    record = study / "configs" / "compare_job" / "eval_st1_v0.yaml"
    record.unlink()
    record.symlink_to(outside)
    result = physgrad.compare(*args)
    assert not marker.exists() and outside.read_text() == "theirs\n"
    assert result.runs.iterations.tolist() == small_study.runs.iterations.tolist()
    assert result.runs.test_loss_at_1.tolist() == small_study.runs.test_loss_at_1.tolist()
    assert not record.is_symlink() and "seeds: 6" in record.read_text()

    (study / "eval.log").unlink()
    (study / "eval.log").symlink_to(outside)
    (study / "eval").rename(tmp_path / "older_eval")  # the evaluation must run again
    with pytest.raises(UserError, match="eval.log: a link: refused"):
        physgrad.compare(*args)
    assert outside.read_text() == "theirs\n"


def test_which_variants_train_their_trials_together():
    """One vectorised job per study where the tuned learning rate can be an input of the rule's
    optax transformation (Gauss-Newton and HIG too, their float64 retry included) and members stop
    together (iterations, calibrated clock); one job per trial for Levenberg-Marquardt (its gain
    ratio takes the loss function), for the rules that search a line (trained together, every
    member would wait for the slowest one's evaluations at every step; their evaluation seeds too)
    and on the measured clock."""
    from physgrad.comparison.tuning import seeds_together, trials_together

    rules = "adam,gd,gauss_newton,hig,levenberg_marquardt,lbfgs,ssbfgs"
    settings, axes, common, _ = split_overrides(
        ["task=toy", f"optim={rules}", "trainer.iterations=30"]
    )
    variants = build_variants(axes, common, study_settings(settings), [])
    together = {v.name: trials_together(v, "iteration") for v in variants}
    assert together == {
        "adam": True,
        "gd": True,
        "gauss_newton": True,
        "hig": True,
        "levenberg_marquardt": False,
        "lbfgs": False,
        "ssbfgs": False,
    }
    assert {v.name for v in variants if not seeds_together(v, "iteration")} == {"lbfgs", "ssbfgs"}
    assert {v.name for v in variants if not seeds_together(v, "calibrated_time")} == {
        "lbfgs",
        "ssbfgs",
    }
    assert not any(seeds_together(v, "wall_time") for v in variants)
    assert trials_together(variants[0], "calibrated_time")
    assert not trials_together(variants[0], "wall_time")


def test_a_calibration_is_used_only_whole_and_within_a_physical_step_cost(tmp_path):
    """Every field of calibration.json is checked (it may come from someone else): a missing
    field, a step faster than a microsecond or slower than an hour, a non-number: not used
    (compare calibrates again, or refuses a given one in one line)."""
    import json
    import os

    from physgrad.comparison.calibration import read_calibration

    whole = {
        "quantile": 0.2,
        "load_start": 0.5,
        "load_end": 0.6,
        "machine": {"cpu_count": 2},
        "costs": {"adam": {"step_seconds": 1e-4, "median_seconds": 1.2e-4, "rounds": 30}},
    }
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(whole))
    assert read_calibration(path, ["adam"]) == whole
    assert read_calibration(path, ["adam", "hig"]) is None
    scheduled = {
        "update_seconds": 5e-5,
        "advanced_seconds": 5.2e-5,
        "advanced_step": 4007,
        "floor_probability": 0.03,
    }
    with_update = {**whole, "costs": {"adam": {**whole["costs"]["adam"], **scheduled}}}
    path.write_text(json.dumps(with_update))
    assert read_calibration(path, ["adam"]) == with_update
    for broken in (
        {k: v for k, v in whole.items() if k != "quantile"},
        {**whole, "machine": "x"},
        {**whole, "machine": {"cpu_count": "many"}},
        {**whole, "load_start": "high"},
        {**whole, "costs": {"adam": {**whole["costs"]["adam"], "step_seconds": 1e-300}}},
        {**whole, "costs": {"adam": {**whole["costs"]["adam"], "step_seconds": 1e9}}},
        {**whole, "costs": {"adam": {"step_seconds": 1e-4}}},
        # a scheduled update dearer than the step it is part of, or without its measurements
        {
            **whole,
            "costs": {"adam": {**whole["costs"]["adam"], **scheduled, "update_seconds": 2e-4}},
        },
        {
            **whole,
            "costs": {"adam": {**whole["costs"]["adam"], **scheduled, "update_seconds": -1e-6}},
        },
        {**whole, "costs": {"adam": {**whole["costs"]["adam"], "update_seconds": 5e-5}}},
        *(
            {**whole, "costs": {"adam": {**whole["costs"]["adam"], **scheduled, key: value}}}
            for key, value in (
                ("floor_probability", 1),
                ("advanced_step", "x"),
                ("advanced_step", True),
                ("advanced_step", 0),
                ("advanced_seconds", None),
            )
        ),
        [1, 2],
    ):
        path.write_text(json.dumps(broken))
        assert read_calibration(path, ["adam"]) is None, broken
    path.write_text('{"quantile": 0.2, "costs": ')  # cut short
    assert read_calibration(path, ["adam"]) is None
    path.write_text("[" * 200_000 + "]" * 200_000)  # deeper than the parser recurses
    assert read_calibration(path, ["adam"]) is None
    # never read through a link or from a FIFO (which would block), unless a user's path links
    path.unlink()
    (tmp_path / "elsewhere.json").write_text(json.dumps(whole))
    path.symlink_to(tmp_path / "elsewhere.json")
    assert read_calibration(path, ["adam"]) is None
    assert read_calibration(path, ["adam"], given=True) == whole
    path.unlink()
    os.mkfifo(path)
    assert read_calibration(path, ["adam"]) is None
    assert read_calibration(path, ["adam"], given=True) is None


def test_a_step_cost_faster_than_a_microsecond_is_refused(tmp_path):
    from physgrad.experiment import run_experiment
    from tests.helpers import load

    outcome, _ = run_experiment(
        load(
            "task=toy",
            "trainer.time_budget=0.5",
            "trainer.clock=calibrated",
            "trainer.step_cost=1e-300",
        ),
        tmp_path,
    )
    assert outcome.status == "refused" and "trainer.step_cost" in outcome.reason


@pytest.mark.long
def test_a_study_tuned_under_another_read_out_is_read_again_without_training(tmp_path):
    """A study whose journal holds values another read-out gave (forged here: the same points,
    the opposite ranking, no version) is read again from its runs when resumed: the same trial
    values and tuned settings as read the first time, no tuning job trained again, also where the
    trials were added in pieces (1, then 3: adam's trained together in two jobs)."""
    import optuna

    from physgrad.comparison import run_study

    args = [
        "task=toy",
        "optim=adam,gd",
        "trainer.iterations=20",
        "compare.studies=1",
        "compare.seeds=2",
        f"compare.dir={tmp_path / 's'}",
        "figures=false",
    ]
    physgrad.compare(*args, "compare.trials=1")
    args.append("compare.trials=3")
    first = physgrad.compare(*args)
    jobs = sorted(p.name for p in (tmp_path / "s" / "tune").iterdir())
    assert "+compare_job=tune_v0_t000" in jobs and "+compare_job=tune_v0_t001-002" in jobs
    journal = tmp_path / "s" / "tuning.journal"
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))
    )
    told = {
        name: [t.params for t in optuna.load_study(study_name=name, storage=storage).trials]
        for name in optuna.get_all_study_names(storage)
    }
    journal.unlink()
    forged = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))
    )
    rate = {"learning_rate": optuna.distributions.FloatDistribution(1e-5, 0.1, log=True)}
    for name, points in told.items():
        study = optuna.create_study(study_name=name, storage=forged)
        for k, point in enumerate(points):
            study.enqueue_trial(point)
            study.tell(study.ask(rate), -float(k))  # the last trial "best"
    runs = sorted((tmp_path / "s" / "tune").rglob("results.h5"))
    stamps = [p.stat().st_mtime_ns for p in runs]
    notes = []
    again = run_study(args, config_dir=None, say=notes.append)
    assert sum("scored by another read-out (version unrecorded" in n for n in notes) == 1
    assert "tune: 6 trials read again from the runs that trained them" in notes
    assert sorted((tmp_path / "s" / "tune").rglob("results.h5")) == runs
    assert sorted(p.name for p in (tmp_path / "s" / "tune").iterdir()) == jobs
    assert [p.stat().st_mtime_ns for p in runs] == stamps
    assert list(again.trials.validation_loss) == list(first.trials.validation_loss)
    assert list(again.runs.test_loss_at_1) == list(first.runs.test_loss_at_1)
    assert len(list((tmp_path / "s").glob("tuning.journal.read-out-unrecorded-*"))) == 1


def test_only_the_runs_an_evaluation_asked_for_make_a_verdict():
    """An evaluation file counts only if it ran to its end on an evaluation seed with the study's
    tuned values: a failed, interrupted or running job, a foreign seed, or a file left by another
    run (another learning rate: a job skipped because its folder was held) is named."""
    from physgrad.comparison.evaluation import _not_asked_for
    from physgrad.results import Run

    settings = study_settings({"seeds": 6}).study_seeds(0)
    tuned = {"learning_rate": 0.00165}

    def run(status="completed", seed=2, rate=0.00165, reason=None):
        attrs = {"status": status, "seed": seed, **({"reason": reason} if reason else {})}
        return Run(Path("x"), attrs, {}, {}, config={"optim": {"learning_rate": rate}})

    assert _not_asked_for(run(), tuned, settings) is None
    assert _not_asked_for(run("diverged"), tuned, settings) is None
    assert _not_asked_for(run("failed", reason="boom"), tuned, settings) == "failed (boom)"
    assert _not_asked_for(run("running"), tuned, settings) == "running"
    assert "not one of the study's evaluation seeds 0..5" in _not_asked_for(
        run(seed=1_000_000), tuned, settings
    )
    # another study's seed (study 1 evaluates on 6..11)
    assert "not one of the study's" in _not_asked_for(run(seed=6), tuned, settings)
    assert "not the tuned 0.00165" in _not_asked_for(run(rate=1.65e-5), tuned, settings)
    assert _not_asked_for(run(rate=1.65e-5), {}, settings) is None  # untuned: as configured


def test_a_crafted_tuning_journal_runs_no_code_and_its_trials_are_set_aside(tmp_path, small_study):
    """A finished study whose tuning.journal someone else extended: a best trial whose params would
    build a `_target_` that runs a shell command (as a resumed evaluation would have instantiated
    it), one without the learning rate, one with a rate outside its range, and a point enqueued as
    an interpolation string. On resume nothing runs, each is set aside with one line, the verdict
    comes from the study's own trials, and trials.csv lists them without their params."""
    import optuna

    from physgrad.comparison import run_study
    from physgrad.comparison.journal import journal_storage

    marker, first = tmp_path / "ran", small_study
    args = copy_of(small_study, tmp_path / "s")
    storage = journal_storage(tmp_path / "s" / "tuning.journal")
    adam = optuna.load_study(study_name="adam", storage=storage)
    text = optuna.distributions.CategoricalDistribution
    crafted = {
        "learning_rate._target_": "asyncio.run",
        "learning_rate.main._target_": "asyncio.create_subprocess_shell",
        "learning_rate.main.cmd": f"touch {marker}",
    }
    adam.add_trial(
        optuna.trial.create_trial(
            params=crafted,
            distributions={key: text([value]) for key, value in crafted.items()},
            value=-3.0,  # the lowest: without the check it would be the tuned setting
        )
    )
    adam.add_trial(
        optuna.trial.create_trial(
            params={"beta": 0.5},
            distributions={"beta": optuna.distributions.FloatDistribution(0.1, 1.0)},
            value=-2.0,
        )
    )
    adam.add_trial(
        optuna.trial.create_trial(
            params={"learning_rate": 50.0},
            distributions={"learning_rate": optuna.distributions.FloatDistribution(1.0, 100.0)},
            value=-1.0,
        )
    )
    adam.enqueue_trial({"learning_rate": "${oc.env:HOME}"})
    notes = []
    again = run_study(args, config_dir=None, say=notes.append)
    assert not marker.exists()
    set_aside = [n for n in notes if "is set aside" in n]
    assert len(set_aside) >= 4 and all("\n" not in n for n in set_aside)
    assert again.runs.test_loss_at_1.tolist() == first.runs.test_loss_at_1.tolist()
    assert [v.verdict for v in again.verdicts] == [v.verdict for v in first.verdicts]
    listed = again.trials[again.trials.variant == "adam"]
    assert (listed.state == "SET_ASIDE").sum() == 4
    assert not any("_target_" in column for column in again.trials.columns)


def test_a_study_folder_of_any_name_runs(small_study):
    """A compare.dir with a comma, a space, a quote and letters beyond ASCII (quoted as Hydra needs
    on the command line) reaches the phases' multiruns as one value: every phase runs there. It
    was passed unquoted, and every phase failed."""
    folder = small_study.folder
    assert folder.name == "a,b ü's [x]" and (folder / "compare.md").is_file()
    assert all(folder / "eval" in Path(p).parents for p in small_study.runs.path)
    assert any((folder / "tune").rglob("results.h5"))


def test_a_study_writes_its_files_itself_and_never_through_a_link(tmp_path, small_study):
    """A study folder from someone else: compare's tables and compare.md planted as links to files
    elsewhere are replaced, not written through; a study.json or a tuning.journal that is a link
    (dangling too: it would create the file it names), has a second name (a hard link) or is a
    FIFO (a read would wait for ever) or a folder, and a lock file that is a link, a second name
    or a folder, are refused in one line; nothing elsewhere is created or changed."""
    import os

    study, outside = tmp_path / "study", tmp_path / "outside"
    args = copy_of(small_study, study)
    outside.mkdir()
    tables = ("compare.md", "trials.csv", "runs.csv", "comparisons.csv")
    for name in tables:
        (outside / name).write_text("theirs\n")
        (study / name).unlink()
        (study / name).symlink_to(outside / name)
    result = physgrad.compare(*args)
    assert all((outside / name).read_text() == "theirs\n" for name in tables)
    assert not any((study / name).is_symlink() for name in tables)
    assert (study / "compare.md").read_text() == result.text

    def planted(name, how):
        """The study with `name` replaced by a link to, or a second name of, a file elsewhere."""
        own, theirs = study / name, outside / f"their {name}"
        kept = own.with_name(f"{name}.kept")
        own.rename(kept)
        if how == "hard link":
            theirs.write_bytes(kept.read_bytes())
            os.link(theirs, own)
        elif how == "FIFO":  # reading it would wait for a writer for ever
            os.mkfifo(own)
        elif how == "folder":
            own.mkdir()
        else:  # a link to nothing: writing through it would create their file
            theirs.unlink(missing_ok=True)
            own.symlink_to(theirs)
        return kept, theirs

    for name, how in (
        ("study.json", "link"),
        ("tuning.journal", "link"),
        ("tuning.journal", "hard link"),
        (".physgrad-study", "hard link"),
        (".physgrad-study", "link"),
        (".physgrad-study", "folder"),
        ("tuning.journal", "folder"),
        ("study.json", "FIFO"),
        ("tuning.journal", "FIFO"),
    ):
        kept, theirs = planted(name, how)
        before = theirs.read_bytes() if theirs.exists() else None
        with pytest.raises(UserError, match="a link|another name|not a file|lock") as refused:
            physgrad.compare(*args)
        assert "\n" not in str(refused.value) and name in str(refused.value), (name, how)
        assert (theirs.read_bytes() if theirs.exists() else None) == before, (name, how)
        if how == "folder":
            (study / name).rmdir()
        else:
            (study / name).unlink()
        kept.rename(study / name)


def test_a_job_folder_that_is_a_link_is_neither_read_nor_written_through(tmp_path, small_study):
    """A study folder from someone else in which an evaluation job's folder, or the whole eval/,
    is a link to runs elsewhere: their runs never enter the verdicts and no job writes through
    the link; the study is refused in one line naming it. A member folder that is a link is not
    read, nor written through, and the study stops in one line that names it."""
    import shutil

    from physgrad.comparison.jobs import job_runs

    study = tmp_path / "study"
    args = copy_of(small_study, study)
    job = study / "eval" / "+compare_job=eval_st1_v0"
    shutil.move(job, tmp_path / "theirs")
    job.symlink_to(tmp_path / "theirs")
    with pytest.raises(UserError, match="eval_st1_v0: a link: refused") as refused:
        physgrad.compare(*args)
    assert "\n" not in str(refused.value)
    assert job_runs(study / "eval", "eval_st1_v0") == []
    job.unlink()
    shutil.move(tmp_path / "theirs", job)
    members = sorted(p.parent.name for p in job.glob("*/results.h5"))
    member = sorted(job.glob("*/results.h5"))[0].parent
    shutil.move(member, tmp_path / "their member")
    member.symlink_to(tmp_path / "their member")
    assert len(members) == 6
    assert [Path(r.path).parent.name for r in job_runs(study / "eval", "eval_st1_v0")] == [
        m for m in sorted(members, key=lambda m: int(m.split("=")[1])) if m != member.name
    ]
    before = sorted(p.name for p in (tmp_path / "their member").iterdir())
    with pytest.raises(UserError, match=f"{member.name} is a link, not a folder: .* remove it"):
        physgrad.compare(*args)  # the link named: resuming alone would fail the same way
    assert sorted(p.name for p in (tmp_path / "their member").iterdir()) == before
    shutil.move(study / "eval", tmp_path / "their eval")
    (study / "eval").symlink_to(tmp_path / "their eval")
    with pytest.raises(UserError, match="eval: a link: refused"):
        physgrad.compare(*args)


def test_a_results_file_copied_from_another_seed_or_cut_short_is_trained_again(
    tmp_path, small_study
):
    """Resume and the evaluation check a run alike: a member's file copied from another seed of its
    job (the stored config is the job's, the same for every seed), or cut to two rows while still
    marked completed, is not a finished run: the job trains again and the verdicts and losses are
    the study's own. (The copy made resume skip the job and the evaluation ask for it again, for
    ever; the cut file was used, changing 3 of 12 median ratios.)"""
    import shutil

    import h5py

    from physgrad.results import read_run

    study = tmp_path / "study"
    args = copy_of(small_study, study)
    copied = study / "eval" / "+compare_job=eval_st1_v0"
    shutil.copy(copied / "seed=7" / "results.h5", copied / "seed=6" / "results.h5")
    cut = study / "eval" / "+compare_job=eval_st1_v1" / "seed=9" / "results.h5"
    with h5py.File(cut, "r+") as f:
        for group in ("train", "eval"):
            for key in list(f[group]):
                kept = f[group][key][:2]
                del f[group][key]
                f[group].create_dataset(key, data=kept)
    assert read_run(cut).attrs["status"] == "completed"
    again = physgrad.compare(*args)
    assert read_run(copied / "seed=6" / "results.h5").attrs["seed"] == 6
    assert read_run(cut).train["loss"].size == 30
    assert again.runs.test_loss_at_1.tolist() == small_study.runs.test_loss_at_1.tolist()
    assert [v.verdict for v in again.verdicts] == [v.verdict for v in small_study.verdicts]


def test_variants_that_differ_in_their_rule_alone_build_their_scene_once(monkeypatch):
    """compare's check before anything trains builds each distinct scene once: three rules on the
    toy, one scene; a variant with another task setting, a second; a batch larger than the
    training set is still refused for the variant that asks for it."""
    import physgrad.experiment
    from physgrad.comparison.spec import check_variants_build

    built = []
    real = physgrad.experiment.build_scene
    monkeypatch.setattr(
        physgrad.experiment, "build_scene", lambda *a, **k: built.append(1) or real(*a, **k)
    )
    settings, axes, common, _ = split_overrides(["task=toy", "optim=adam,gd,hig"])
    check_variants_build(build_variants(axes, common, study_settings(settings), []), 1_000_000)
    assert len(built) == 1
    settings, axes, common, _ = split_overrides(["task=toy", "optim=adam,gd", "task.scale=1,0.01"])
    check_variants_build(build_variants(axes, common, study_settings(settings), []), 1_000_000)
    assert len(built) == 1 + 2
    settings, axes, common, _ = split_overrides(
        ["task=oscillator", "task.train_size=16", "task.test_size=8", "optim=adam,gd"]
        + ["trainer.batch_size=8,32"]
    )
    with pytest.raises(UserError, match="trainer.batch_size=32 is larger than the training set"):
        check_variants_build(build_variants(axes, common, study_settings(settings), []), 1_000_000)


def test_a_search_key_no_variant_has_is_refused_and_a_scene_s_tuning_file_sets_ranges():
    """compare.search.<key> that none of the variants' rules has (a misspelt key) is refused in one
    line; a scene's tuning file (conf/tuning/toy_hig.yaml) sets the range its rule is tuned over
    there, and compare.search overrides it."""
    from physgrad.comparison.spec import build_variants, split_overrides, study_settings
    from physgrad.errors import UserError

    def space(*extra):
        settings, axes, common, _ = split_overrides(["task=toy", "optim=adam,hig", *extra])
        return {v.name: v.space for v in build_variants(axes, common, study_settings(settings), [])}

    with pytest.raises(UserError, match="compare.search.learnin_rate is a setting of none"):
        space("compare.search.learnin_rate=[1e-4,1]")
    found = space()
    assert found["hig"] == {"learning_rate": (0.01, 100.0)}
    assert found["adam"] == {"learning_rate": (1e-4, 10.0)}
    assert space("compare.search.learning_rate=[1e-3,1]")["hig"] == {"learning_rate": (1e-3, 1.0)}


def test_a_study_folder_that_cannot_be_written_is_one_line(tmp_path):
    """A study whose folder cannot be made (here under a plain file; a read-only or full disk alike)
    stops in one line that names the folder, before anything trains."""
    (tmp_path / "plain").write_text("a file")
    with pytest.raises(UserError, match="cannot write the study folder .*plain/study") as caught:
        physgrad.compare(
            "task=toy",
            "optim=adam,gd",
            "trainer.iterations=5",
            f"compare.dir={tmp_path}/plain/study",
        )
    assert "\n" not in str(caught.value)


def test_a_run_from_python_shows_the_console_s_progress_or_none(tmp_path, capsys):
    """physgrad.run without a terminal or a logging set-up: the lines `physgrad run` logs (its
    compile, then one every trainer.log_seconds) go to a function, to stderr, or nowhere."""
    import physgrad

    args = (
        "task=toy",
        "trainer.time_budget=0.6",
        "trainer.flush_seconds=0.1",
        "trainer.log_seconds=0.001",
        "figures=false",
    )
    import re

    said = []
    physgrad.run(*args, out_dir=tmp_path / "a", progress=said.append)
    assert any("compiled in" in line for line in said), said
    assert any("iteration" in line and "loss" in line for line in said), said
    # the line as said (a handler another test of the same process left on the root logger may
    # print logging's own error, which quotes the format string, not the line)
    compiled = re.compile(r"toy/adam seed 0 compiled in [\d.]+ s")
    physgrad.run(*args, out_dir=tmp_path / "b")
    assert compiled.search(capsys.readouterr().err)
    physgrad.run(*args, out_dir=tmp_path / "c", progress=False)
    assert not compiled.search(capsys.readouterr().err)


@pytest.mark.long
def test_a_knob_that_shapes_the_step_cost_charges_each_trial_and_evaluation_its_own_cost(
    tmp_path,
):
    """compare.knobs=true with SOAP (preconditioning frequency [1, 100]) and L-BFGS (memory
    [2, 100]) on the calibrated clock: the calibration times each rule at its range's two ends
    as well, every tuning and evaluation job is charged the step cost at its own value
    (its own part through the calibrated points around it, the ends and the preset, plus the
    preset's line-search evaluations: physgrad.optim.capabilities.knob_step_cost), and compare.md
    says so. (The measured costs
    themselves are the machine's: on the toy the frequency barely changes a step's, the memory
    does.)"""
    import json

    from omegaconf import OmegaConf

    from physgrad.optim.capabilities import knob_cost

    study = physgrad.compare(
        "task=toy",
        "optim=soap,lbfgs",
        "compare.knobs=true",
        "trainer.time_budget=0.3",
        "compare.trials=3",
        "compare.studies=1",
        "compare.seeds=2",
        "trainer.batch_size=16",
        "figures=false",
        f"compare.dir={tmp_path}",
    )
    costs = json.loads((study.folder / "calibration.json").read_text())["costs"]
    ends = {
        "soap": ("precondition_frequency", "inverse", 1, 100),
        "lbfgs": ("memory_size", "linear", 2, 100),
    }
    names = {f"{rule}@{key}={v}" for rule, (key, _, *vs) in ends.items() for v in vs}
    assert set(costs) == {"soap", "lbfgs"} | names
    jobs = sorted((study.folder / "tune").glob("+compare_job=*")) + sorted(
        (study.folder / "eval").glob("+compare_job=*")
    )
    assert len(jobs) == 6 + 3  # one trial a job; SOAP's 2 seeds together, L-BFGS's one a job

    def own(cost: dict) -> float:  # a step less its line search's evaluations
        return cost["step_seconds"] - cost.get("evaluation_seconds", 0) * cost.get(
            "step_evaluations", 0
        )

    values = set()
    for job in jobs:
        config = OmegaConf.load(job / ".hydra" / "config.yaml")
        rule = config.optim.name
        key, shape, low, high = ends[rule]
        value = config.optim[key]
        # the points around the value: an end and the preset (10 for both rules)
        a, b = (low, 10) if value <= 10 else (10, high)
        at = [own(costs[f"{rule}@{key}={v}"] if v != 10 else costs[rule]) for v in (a, b)]
        expected = knob_cost(shape, value, a, at[0], b, at[1])
        expected += costs[rule].get("evaluation_seconds", 0) * costs[rule].get(
            "step_evaluations", 0
        )
        assert config.trainer.step_cost == pytest.approx(expected, rel=1e-12), job.name
        values.add((rule, value))
    assert len(values) >= 4  # the trials tried other frequencies and memories than the preset's
    assert "each trial and evaluation is charged the cost at its own value" in study.text


@pytest.mark.long
def test_a_study_evaluates_another_studys_tuned_settings_at_a_longer_budget(tmp_path):
    """compare.tuned_in: a study at three times another's budget, on its clock and seeds, tunes
    nothing (no tuning folder, no trials) and evaluates each variant at the settings the other
    chose by its validation loss (its trials.csv); its runs go three times as far, and compare.md
    says where the settings were tuned. A folder without a finished study is one line."""
    import pandas as pd

    common = [
        "task=toy",
        "optim=adam,gd",
        "compare.trials=3",
        "compare.studies=1",
        "compare.seeds=2",
        "trainer.batch_size=16",
        "figures=false",
    ]
    first = physgrad.compare(*common, "trainer.time_budget=0.2", f"compare.dir={tmp_path / 'a'}")
    longer = physgrad.compare(
        *common,
        "trainer.time_budget=0.6",
        f"compare.calibration={first.folder / 'calibration.json'}",
        f"compare.tuned_in={first.folder}",
        f"compare.dir={tmp_path / 'b'}",
    )
    assert not (longer.folder / "tune").exists()
    trials = pd.read_csv(first.folder / "trials.csv")
    jobs = list((longer.folder / "eval").glob("+compare_job=*"))
    for name in ("adam", "gd"):
        mine = trials[(trials.variant == name) & (trials.state == "COMPLETE")]
        rate = mine.loc[mine.validation_loss.idxmin(), "learning_rate"]
        rates = {
            physgrad_config(job).optim.learning_rate
            for job in jobs
            if physgrad_config(job).optim.name == name
        }
        assert len(rates) == 1 and rates.pop() == pytest.approx(rate)
    for name in ("adam", "gd"):
        short = first.runs[first.runs.variant == name].iterations.median()
        long = longer.runs[longer.runs.variant == name].iterations.median()
        assert long == pytest.approx(3 * short, rel=0.02)
    assert f"settings tuned in {first.folder}" in longer.text
    with pytest.raises(UserError, match="no finished study's trials.csv"):
        physgrad.compare(
            *common,
            "trainer.time_budget=0.6",
            f"compare.tuned_in={tmp_path}",
            f"compare.dir={tmp_path / 'c'}",
        )


def physgrad_config(job: Path):
    from omegaconf import OmegaConf

    return OmegaConf.load(job / ".hydra" / "config.yaml")
