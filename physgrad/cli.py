"""`physgrad run [hydra overrides]` and `physgrad report PATH...`.

`run` checks the overrides against the configs first (unknown task or optim, misspelt keys, sweeps
without -m) so that a user mistake is one line on stderr, then hands the untouched argument list to
the Hydra app: every Hydra feature (-m, --cfg, --help, launchers) keeps working.
"""

from __future__ import annotations

import argparse
import errno
import os
import signal
import sys
from collections.abc import Iterable
from pathlib import Path

from physgrad.errors import LauncherRefused, UserError
from physgrad.interrupts import (
    ABANDONED,
    SignalInterrupt,
    composing,
    install,
    keeping_lost_interrupts,
    raise_interrupt,
    signals_held,
    take_lost,
)

USAGE = """usage: physgrad {run,compare,report,check} ...

  physgrad run [HYDRA FLAGS] [key=value ...]
      train one configuration, or sweep with -m
  physgrad compare [-cd DIR] task=T optim=A,B,C [key=value ...] [compare.KEY=VALUE ...]
      which variant is better on this scene: tuned with equal budgets, paired seeds, a verdict with
      intervals (compare.md)
  physgrad report [LABEL=]PATH... [--out DIR] [--threshold LOSS] [--note TEXT] [--logx auto|on|off]
      tables, CSV and figures from the results.h5 files under PATH
  physgrad check [--small]
      stiff and extreme cases: what each variant does with them
  physgrad check [-cd DIR] task=NAME [k=v ...]
      a scene's gradients, rollout and Jacobian against references

Examples:
  physgrad compare task=toy optim=adam,gauss_newton,hig trainer.iterations=300
  physgrad run task=poisson optim=hig
  physgrad run -m task=poisson optim=adam,hig seed=0,1
  physgrad report outputs/multirun/<date>/<time>
  physgrad run -cd myconf task=pendulum        a scene (or optimiser) from your own config folder
  physgrad run --help                          Hydra's help: config groups and every key
  eval "$(physgrad run -sc install=bash)"      tab completion of overrides in bash
"""

INFO_FLAGS = {"-h", "--help", "-hh", "--hydra-help", "-i", "--info"}


def main(argv: list[str] | None = None) -> int:
    if (
        argv is None
    ):  # the console script: SIGINT and SIGTERM before a job handles them end the start-up alike
        return _console_main()
    return _main(argv)


def _console_main() -> int:
    install(raise_interrupt)
    try:
        with keeping_lost_interrupts():
            return _main(None)
    finally:
        # the files are final: a signal now would only interrupt the interpreter's shutdown
        install(signal.SIG_IGN)


def _main(argv: list[str] | None) -> int:
    try:
        if argv is None and not INFO_FLAGS & set(sys.argv[2:]):  # help needs no JAX
            import_holding_signals(HEAVY_IMPORTS.get(sys.argv[1] if len(sys.argv) > 1 else "", ()))
        code = dispatch(sys.argv[1:] if argv is None else argv)
        lost = take_lost()
        if (
            lost is not None
        ):  # dropped inside a garbage-collector callback or finaliser: act on it now
            raise SignalInterrupt(lost)
    except KeyboardInterrupt as interrupt:  # start-up, composing, a sweep's launcher: no traceback
        name = (
            interrupt.args[0] if interrupt.args and isinstance(interrupt.args[0], str) else "SIGINT"
        )
        print(f"physgrad: stopped by {name}", file=sys.stderr)
        code = 130
        if argv is not None:
            return code
    except LauncherRefused as refused:
        from physgrad.files import clean_text

        print(f"physgrad: error: {clean_text(str(refused), None)}", file=sys.stderr)
        code = 2
        if argv is not None:
            return code
    except SystemExit as leaving:
        code = leaving.code if isinstance(leaving.code, int) else (0 if leaving.code is None else 1)
        if argv is not None or not abandoned_steps():
            raise
    if (
        argv is None and abandoned_steps()
    ):  # the results are written: leave the step that was cut short
        import logging
        import os

        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


HEAVY_IMPORTS = {
    "run": ("jax", "physgrad.app"),
    "compare": ("jax", "physgrad.comparison"),
    "check": ("jax", "physgrad.check"),
    "report": ("physgrad.report",),
}


def import_holding_signals(modules: Iterable[str]) -> None:
    """Import modules with SIGINT and SIGTERM held back until they are loaded: an exception landing
    inside a C extension's initialisation (jaxlib's, numpy's) turns into an ImportError traceback or
    a crash. A signal that came meanwhile is handled right after (about a second later at most)."""
    import importlib

    with signals_held():
        for name in modules:
            importlib.import_module(name)


def abandoned_steps() -> bool:
    """A training step left computing by a second signal is still running
    (physgrad.interrupts.ABANDONED)."""
    return any(thread.is_alive() for thread in ABANDONED)


def dispatch(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE, end="")
        return 0
    command, rest = argv[0], argv[1:]
    if command in ("-sc", "--shell-completion"):  # what the installed completion script asks
        command, rest = "run", argv
    try:
        if command == "run":
            return run_command(rest)
        if command == "report":
            return report_command(rest)
        if command == "compare":
            from physgrad.comparison import main as compare_main

            return compare_main(rest)
        if command == "check":
            from physgrad.check import main as check_main

            return check_main(rest)
        raise UserError(
            f"unknown command '{command}': use 'physgrad run ...', 'physgrad compare ...', "
            "'physgrad report PATH...' or 'physgrad check'"
        )
    except UserError as error:
        from physgrad.files import clean_text

        print(f"physgrad: error: {clean_text(str(error), None)}", file=sys.stderr)
        return 2
    except MemoryError:
        print(
            "physgrad: error: out of memory: free some, or give fewer or smaller runs; the files "
            "written so far are kept",
            file=sys.stderr,
        )
        return 1
    except OSError as error:
        from physgrad.files import LinkedFolder, clean_text

        if isinstance(error, LinkedFolder):  # a link planted at a folder physgrad creates
            print(f"physgrad: error: {clean_text(str(error), None)}", file=sys.stderr)
            return 2
        if error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise

        where = clean_text(os.fspath(error.filename), 300) if error.filename else "a file"
        print(
            f"physgrad: error: no space left writing {where}: free some and run the same command "
            "again (finished runs are kept; a study resumes where it stopped)",
            file=sys.stderr,
        )
        return 1


def run_command(args: list[str]) -> int:
    from hydra._internal.utils import get_args_parser

    parsed = get_args_parser().parse_args(args)
    if parsed.shell_completion:
        return shell_completion(args)
    with composing():  # Hydra composes before the job and after it (physgrad.interrupts)
        return run_app(args, parsed)


def run_app(args: list[str], parsed: argparse.Namespace) -> int:
    """The overrides checked, then the Hydra app run on the untouched argument list."""
    if (
        not INFO_FLAGS.intersection(args)
        and parsed.config_path is None
        and parsed.config_name is None
    ):
        from physgrad.configs import check_overrides

        check_overrides(
            parsed.overrides,
            multirun=parsed.multirun,
            config_dirs=[parsed.config_dir] if parsed.config_dir else [],
        )
        check_writable(parsed.overrides, multirun=parsed.multirun)
        if members_asked(parsed.overrides):  # before JAX starts its CPU client
            from physgrad.machine import members_environment

            os.environ.update(members_environment(os.environ))
    from physgrad.app import job
    from physgrad.sweep_hooks import FAILED_JOBS, INTERRUPTED_BY_SIGNAL

    sys.argv = ["physgrad run", *args]
    job()
    if parsed.multirun and INTERRUPTED_BY_SIGNAL:
        return 130
    return 1 if parsed.multirun and any(FAILED_JOBS) else 0


def shell_completion(args: list[str]) -> int:
    """Hydra's tab completion for `physgrad run`: `eval "$(physgrad run -sc install=bash)"` installs
    it; the shell then asks `physgrad -sc query=bash` with the whole line, from which the subcommand
    is removed here (Hydra completes overrides of one application; `run` is that application)."""
    import os
    import re

    from physgrad.app import job

    line = os.environ.get("COMP_LINE")
    if line is not None:
        words = line.split()
        if len(words) < 2 or (
            len(words) == 2 and not line.endswith(" ")
        ):  # completing the subcommand itself
            prefix = words[1] if len(words) == 2 else ""
            print(" ".join(c for c in ("run", "report", "check") if c.startswith(prefix)))
            return 0
        if words[1] != "run":
            return 0
        # a config folder on the line (-cd DIR) joins the search path, so its options complete too
        folder = re.search(r"\s(?:-cd|--config-dir)[\s=]+(\S+)\s", line)
        if folder:
            args = ["-cd", folder[1], *args]
            line = line[: folder.start()] + line[folder.end() - 1 :]
        os.environ["COMP_LINE"] = re.sub(r"^(\s*\S+)\s+run\b", r"\1", line)
    sys.argv = ["physgrad", *args]
    job()
    return 0


def members_asked(overrides: list[str]) -> bool:
    """Whether the command line trains members together: seeds above 1 (in any value of a sweep)
    or trial_values (physgrad.machine.MEMBERS_XLA_FLAG)."""
    from physgrad.configs import _parse_overrides

    for override in _parse_overrides(overrides):
        key = override.get_key_element().lstrip("+~")
        if key == "trial_values" and not override.is_delete():
            return True
        if key == "seeds":
            values = override.sweep_string_iterator() if override.is_sweep_override() else None
            found = list(values) if values is not None else [override.value()]
            if any(str(v).isdigit() and int(v) > 1 for v in found):
                return True
    return False


def check_writable(overrides: list[str], multirun: bool) -> None:
    """UserError (one line) if the output folder cannot be created and written to. Checked before
    Hydra starts, which would otherwise fail with a traceback; creates the folder's fixed part (up
    to the first interpolation), which Hydra would create anyway."""
    import os
    import tempfile

    from physgrad.configs import _parse_overrides

    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    # the value as Hydra reads it: a quoted folder (as compare writes it) without its quotes
    target = next(
        (str(o.value()) for o in _parse_overrides(overrides) if o.get_key_element() == key),
        "outputs",
    )
    fixed = Path(target.split("${", 1)[0] or ".")
    try:
        fixed.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=fixed):
            pass
    except OSError as error:
        why = error.strerror or type(error).__name__
        raise UserError(
            f"cannot write results to {target}: {why} ({os.fspath(error.filename or fixed)}): "
            f"set {key}=<a writable folder>"
        ) from None


def report_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="physgrad report",
        description="Tables, CSV files and figures from results.h5 files (never re-runs "
        "training). Runs that differ in anything but the seed are kept apart and labelled by what "
        "differs.",
    )
    parser.add_argument(
        "paths",
        nargs="+",
        metavar="[LABEL=]PATH",
        help="results.h5 files or folders searched for them; LABEL=PATH names a set of runs (e.g. "
        "old=outputs/multirun/2026-11-15 new=outputs/multirun/2026-11-22), kept apart and "
        "labelled in tables and legends",
    )
    parser.add_argument(
        "--out",
        help="folder for report.md, runs.csv, curves.csv and the figures (default: the "
        "first PATH folder)",
    )
    parser.add_argument(
        "--threshold",
        type=positive_loss,
        default=None,
        help="test loss for the time-to-reach column (default: per scene, the median final test "
        "loss of its best group, the target physgrad compare uses)",
    )
    parser.add_argument(
        "--note", default="", help="a line printed on every figure (e.g. the budget profile)"
    )
    parser.add_argument(
        "--logx",
        choices=("auto", "on", "off"),
        default="auto",
        help="log time/iteration axis: auto where the curves' ends span a decade or more",
    )
    options = parser.parse_args(args)
    from physgrad.files import clean_text
    from physgrad.report import write_report

    body = write_report(
        options.paths,
        out_dir=options.out,
        threshold=options.threshold,
        note=options.note,
        logx=options.logx,
    )
    # paths of others' folders may hold terminal escapes
    print(clean_text(body, None, lines=True), end="")
    return 0


def positive_loss(text: str) -> float:
    """A loss given on the command line: a finite number above 0 (argparse's one-line error
    otherwise: 0, a negative, nan or inf reaches no run or every run)."""
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text} is not a loss: give a finite number above 0")
    return value


if __name__ == "__main__":
    sys.exit(main())
