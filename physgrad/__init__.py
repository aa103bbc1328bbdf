"""physgrad: which gradient should I train my physics-in-the-loop network with?

From Python (a notebook, a script):

    import physgrad
    run = physgrad.run("task=oscillator", "optim=hig", "trainer.iterations=200")
    run.eval["loss"], run.train["wall_time"]          # numpy arrays
    same = physgrad.read_run(run.path)                # any results.h5, read back the same way
"""

__version__ = "0.2.0"


class UserError(Exception):
    """A mistake in what the user asked for; reported as one line, never as a traceback."""


def run(*overrides: str, out_dir=None, config_dir=None):
    """Train one configuration, given as the overrides `physgrad run` takes (e.g. "task=poisson", "optim=hig",
    "trainer.iterations=100"), and return its results (physgrad.results.Run: attributes and the /train and
    /eval columns as numpy arrays; a list of them, one per seed, with seeds=N > 1).

    out_dir: the run's folder (default: outputs/runs/<date>/<time>_<task>_<optim>_s<seed>, as `physgrad run`);
    config_dir: a folder of your own configs (like `physgrad run -cd DIR`). A configuration that does not apply
    raises UserError with the reason; a run that diverges or is interrupted returns with that status."""
    from physgrad.api import run_one

    return run_one(list(overrides), out_dir=out_dir, config_dir=config_dir)


def compare(*overrides: str, config_dir=None):
    """Which variant trains this scene best, as `physgrad compare` decides it (tuned with equal budgets, paired
    seeds, verdicts with intervals; docs/protocol.md), e.g.
    ``physgrad.compare("task=toy", "optim=adam,hig", "trainer.iterations=300", "compare.trials=8")``.
    Returns physgrad.comparison.Study: .comparisons, .runs and .trials (pandas DataFrames), .verdicts, .text (the
    compare.md table) and .folder. An interrupted study resumes when called again with the same overrides."""
    from physgrad.comparison import run_study

    return run_study(list(overrides), config_dir=config_dir, say=lambda line: None)


def read_runs(paths, threshold=None):
    """Every run under the given results files or folders (LABEL=PATH sets too) as two pandas DataFrames:
    ``runs, curves = physgrad.read_runs(["outputs/multirun/..."])``. runs: one row per run, every setting in a
    column of its own (optim.learning_rate, task.poles, trainer.iterations, ..., seed, status, the machine) and
    the report's numbers (test_loss, time_to_threshold, ...); curves: one row per run, split and iteration with
    the run's id and label, variant, seed, ..., so that e.g. ``seaborn.lineplot(curves.query("split == 'eval'"),
    x="wall_time", y="loss", hue="label")`` needs no merge. See docs/results.md."""
    from physgrad.report import read_runs as read

    return read(paths, threshold)


def read_run(path):
    """One results.h5 read back: attributes (run.attrs) and the /train and /eval columns (run.train["loss"],
    run.eval["wall_time"], ...) as numpy arrays."""
    from physgrad.results import read_run as read

    return read(path)
