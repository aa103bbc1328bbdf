"""`physgrad run [hydra overrides]` and `physgrad report PATH...`.

`run` checks the overrides against the configs first (unknown task or optim, misspelt keys, sweeps without
-m) so that a user mistake is one line on stderr, then hands the untouched argument list to the Hydra app:
every Hydra feature (-m, --cfg, --help, launchers) keeps working.
"""

from __future__ import annotations

import argparse
import difflib
import itertools
import sys
from pathlib import Path

from physgrad import UserError

USAGE = """usage: physgrad {run,report,check} ...

  physgrad run [HYDRA FLAGS] [key=value ...]   train one configuration, or sweep with -m
  physgrad report PATH... [--out DIR] [--threshold LOSS] [--note TEXT]
                                              table and figures from the results.h5 files under PATH
  physgrad check [--small]                    stiff and extreme cases: what each variant does with them

Examples:
  physgrad run task=poisson optim=hig
  physgrad run -m task=poisson optim=adam,hig seed=0,1
  physgrad report outputs/multirun/<date>/<time>
  physgrad run --help                          Hydra's help: config groups and every key
"""

INFO_FLAGS = {"-h", "--help", "-hh", "--hydra-help", "-i", "--info", "-sc", "--shell-completion"}
_ABSENT = object()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE, end="")
        return 0
    command, rest = argv[0], argv[1:]
    try:
        if command == "run":
            return run_command(rest)
        if command == "report":
            return report_command(rest)
        if command == "check":
            from physgrad.check import main as check_main

            return check_main(rest)
        raise UserError(f"unknown command '{command}': use 'physgrad run ...', 'physgrad report PATH...' or "
                        "'physgrad check'")
    except UserError as error:
        print(f"physgrad: error: {error}", file=sys.stderr)
        return 2


def run_command(args: list[str]) -> int:
    from hydra._internal.utils import get_args_parser

    parsed = get_args_parser().parse_args(args)
    if not INFO_FLAGS.intersection(args):
        check_overrides(parsed.overrides, multirun=parsed.multirun)
        check_writable(parsed.overrides, multirun=parsed.multirun)
    from physgrad.app import job

    sys.argv = ["physgrad run", *args]
    job()
    return 0


def check_writable(overrides: list[str], multirun: bool) -> None:
    """UserError (one line) if the output folder cannot be created and written to. Checked before Hydra
    starts, which would otherwise fail with a traceback; creates the folder's fixed part (up to the first
    interpolation), which Hydra would create anyway."""
    import os
    import tempfile

    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    target = next((o.split("=", 1)[1] for o in overrides if o.startswith(key + "=")), "outputs")
    fixed = Path(target.split("${", 1)[0] or ".")
    try:
        fixed.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=fixed):
            pass
    except OSError as error:
        why = error.strerror or type(error).__name__
        raise UserError(f"cannot write results to {target}: {why} ({os.fspath(error.filename or fixed)}): "
                        f"set {key}=<a writable folder>") from None


def _config_options(conf_dir: Path, group: str) -> list[str]:
    return sorted(p.stem for p in (conf_dir / group).glob("*.yaml"))


def check_overrides(overrides: list[str], multirun: bool) -> None:
    """Raise UserError (one line) for an unknown group option, a key no config has, or a sweep without -m."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob
    from hydra.errors import HydraException

    from physgrad.app import CONF_DIR

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as error:
        raise UserError(f"cannot read the overrides: {str(error).splitlines()[0]}") from None

    group_names = [p.name for p in CONF_DIR.iterdir() if p.is_dir() and not p.name.startswith("_")]
    group_values: dict[str, list[str]] = {}
    keys = []
    for override in parsed:
        key, value = override.key_or_group, override.value()
        if override.is_sweep_override() and not multirun:
            raise UserError(f"'{override.input_line}' sweeps several values: add -m (--multirun) to run them all")
        if key.startswith("hydra") or override.is_delete():
            continue
        if key in group_names and override.package is None:
            options = _config_options(CONF_DIR, key)
            if not options:  # e.g. `+experiment=...` before any experiment exists
                raise UserError(f"no {key} configs in {CONF_DIR / key}")
            if isinstance(value, Glob):
                values = value.filter(options)
            elif override.is_sweep_override():
                values = list(override.sweep_string_iterator())
            else:
                values = [override.get_value_element_as_str()]
            for choice in values:
                if choice not in options:
                    raise UserError(f"unknown {key} '{choice}': choose one of {', '.join(options)}")
            group_values[("+" if override.is_add() else "") + key] = values
        elif not override.is_add() and not override.is_force_add():
            keys.append(key)

    combos = [dict(zip(group_values, combo)) for combo in itertools.product(*group_values.values())]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for combo in combos:
            try:
                cfg = compose("config", overrides=[f"{g}={v}" for g, v in combo.items()])
            except HydraException as error:
                raise UserError(str(error).strip().splitlines()[0]) from None
            for key in keys:
                _check_key(cfg, key, combo)


def _check_key(cfg, key: str, combo: dict) -> None:
    from omegaconf import DictConfig, OmegaConf

    if OmegaConf.select(cfg, key, default=_ABSENT) is not _ABSENT:
        return
    parent_key, _, leaf = key.rpartition(".")
    parent = OmegaConf.select(cfg, parent_key, default=_ABSENT) if parent_key else cfg
    if not isinstance(parent, DictConfig):
        raise UserError(f"unknown key '{key}': '{parent_key}' is not a section of the config")
    siblings = [k for k in parent.keys() if k != "_target_"]
    close = difflib.get_close_matches(leaf, siblings, n=1)
    where = f"{parent_key} has" if parent_key else "the top level has"
    scope = "".join(f" with {g}={v}" for g, v in combo.items() if key.startswith(g + "."))
    hint = f": did you mean {'.'.join(filter(None, [parent_key, close[0]]))}?" if close else ""
    raise UserError(f"unknown key '{key}'{scope}{hint} ({where}: {', '.join(map(str, siblings))})")


def report_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="physgrad report",
                                     description="Table and figures from results.h5 files (never re-runs training).")
    parser.add_argument("paths", nargs="+", help="results.h5 files or folders searched for them")
    parser.add_argument("--out", help="folder for report.md and the figures (default: the first PATH folder)")
    parser.add_argument("--threshold", type=float, default=None,
                        help="test loss for the time-to-reach column (default: per task, the worst final test "
                             "loss among the runs, so every run that finished has a time)")
    parser.add_argument("--note", default="", help="a line printed on every figure (e.g. the budget profile)")
    options = parser.parse_args(args)
    from physgrad.report import write_report

    try:
        print(write_report(options.paths, out_dir=options.out, threshold=options.threshold, note=options.note),
              end="")
    except FileNotFoundError as error:
        raise UserError(str(error)) from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
