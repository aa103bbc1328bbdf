"""Where physgrad's configs live, and how a command line becomes a config.

The built-in configs are the package physgrad.conf (the repository's conf/, mapped into the package
when it is built), so an installed physgrad finds them from any folder. A user's own folders join
the search path with Hydra's ``-cd DIR`` (``--config-dir``) or ``hydra.searchpath=[...]``: their
task/, optim/ and tuning/ YAML files are options like the built-in ones (a built-in file of the same
name wins, as in Hydra).
"""

from __future__ import annotations

import difflib
import importlib.resources
import itertools
import os
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from physgrad.errors import UserError
from physgrad.interrupts import composing
from physgrad.validate import allowed_target

if TYPE_CHECKING:  # omegaconf (Hydra's) is loaded where a config is composed, not on import
    from omegaconf import DictConfig

CONF_DIR = Path(str(importlib.resources.files("physgrad.conf")))
_ABSENT = object()
# keys that had other names in earlier physgrad versions, suggested when the old name is given
RENAMED = {"lr": "learning_rate", "steps": "unroll", "controller": "closed_loop"}


@contextmanager
def initialized(config_dirs: Iterable[str | os.PathLike] = ()) -> Iterator[Any]:
    """Hydra's global state set up as `physgrad run -cd DIR` would: the built-in configs, then every
    folder of config_dirs (searched after them, as Hydra searches -cd). Restores the previous state
    on exit."""
    from hydra._internal.hydra import Hydra
    from hydra._internal.utils import create_config_search_path
    from hydra.core.config_search_path import SearchPathQuery
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup
    from hydra.version import setbase

    backup = get_gh_backup()
    setbase("1.3")
    search_path = create_config_search_path(str(CONF_DIR))
    for folder in config_dirs:
        path = folder if "://" in str(folder) else f"file://{os.path.abspath(folder)}"
        if path.startswith("file://") and not os.path.isdir(path[len("file://") :]):
            raise UserError(f"config folder {folder} not found: give -cd an existing folder")
        search_path.prepend(
            provider="command-line", path=path, anchor=SearchPathQuery(provider="schema")
        )
    try:
        GlobalHydra.instance().clear()
        Hydra.create_main_hydra2(task_name="physgrad", config_search_path=search_path)
        yield GlobalHydra.instance().config_loader()
    finally:
        restore_gh_from_backup(backup)


def compose(
    overrides: Iterable[str] = (),
    config_dirs: Iterable[str | os.PathLike] = (),
    return_hydra_config: bool = False,
) -> DictConfig:
    """The config of one run (the compose API: no output folder, no launcher); UserError (one line)
    for an unknown option or key."""
    from hydra import compose as hydra_compose
    from hydra.errors import HydraException
    from omegaconf import open_dict

    with composing(), initialized(config_dirs):
        try:
            cfg = hydra_compose("config", overrides=list(overrides), return_hydra_config=True)
        except HydraException as error:
            raise UserError(str(error).strip().splitlines()[0]) from None
        name_options(cfg, cfg.hydra.runtime.choices)
    if not return_hydra_config:
        with open_dict(cfg):
            del cfg["hydra"]
    return cfg


def name_options(cfg: DictConfig, choices: Mapping) -> None:
    """A task or optim YAML without `name:` is named after its option (task=heat: heat), as it was
    chosen."""
    from omegaconf import open_dict

    for section in ("task", "optim"):
        node, chosen = cfg.get(section), choices.get(section)
        if node is not None and node.get("name") is None and chosen:
            with open_dict(node):
                node.name = str(chosen).rpartition("/")[2]


def searchpath_entries(overrides: Iterable[str]) -> list[str]:
    """The folders a `hydra.searchpath=[...]` override adds."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    for override in OverridesParser.create().parse_overrides(list(overrides)):
        if override.get_key_element() == "hydra.searchpath":
            value = override.value()
            return [str(v) for v in value] if isinstance(value, list) else []
    return []


def unknown_option(group: str, value: str, options: list[str]) -> UserError:
    close = difflib.get_close_matches(value, options, n=1)
    hint = f": did you mean {close[0]}?" if close else ""
    return UserError(f"unknown {group} '{value}'{hint} (choose one of {', '.join(options)})")


def check_overrides(
    overrides: list[str],
    multirun: bool,
    config_dirs: Iterable[str | os.PathLike] = (),
    combinations: dict | None = None,
) -> DictConfig | None:
    """Raise UserError (one line) for an unknown option of a config group (the built-in ones and
    those in the user's folders), a key no config has, a sweep without -m, or a target of the
    hydra section physgrad does not allow. Returns the first job's config as composed for that
    check (hydra section included; None where Hydra could not compose it, or where
    hydra.searchpath adds folders). combinations: the
    group choices' configs composed so far, by search path and choices (filled in; a caller
    checking several runs over the same folders passes one to compose each choice once)."""
    parsed = _parse_overrides(overrides)
    sweeper = _sweeper(parsed)
    added = searchpath_entries(overrides)
    folders = [*config_dirs, *added]
    with composing(), initialized(folders) as loader:
        group_values, keys = _group_choices_and_keys(parsed, loader, multirun, sweeper)
        known = (
            {} if combinations is None else combinations.setdefault(tuple(map(str, folders)), {})
        )
        _check_combinations(group_values, keys, known)
        cfg = _check_hydra_targets(overrides)
    # hydra.searchpath's folders stand ahead of Hydra's own order here: compose says what runs
    return None if added else cfg


def checked_config(
    overrides: list[str],
    config_dirs: Iterable[str | os.PathLike] = (),
    combinations: dict | None = None,
) -> DictConfig:
    """One run's overrides checked (check_overrides) and its config, hydra section included, as
    compose gives it, composed once for both."""
    cfg = check_overrides(overrides, False, config_dirs, combinations)
    if cfg is None:  # Hydra's own error, in one line
        return compose(overrides, config_dirs, return_hydra_config=True)
    name_options(cfg, cfg.hydra.runtime.choices)
    return cfg


def _parse_overrides(overrides: list[str]) -> list[Any]:
    """Hydra's parse of the overrides; UserError (one line) for one it cannot read."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        return OverridesParser.create().parse_overrides(overrides)
    except HydraException as error:
        hint = ""
        # e.g. init_from=<sweep>/optim=adam,seed=0/results.h5
        if "mismatched input '='" in str(error):
            hint = (
                ": a value that holds '=' or ',' (a sweep's job folder in a path) must be quoted, "
                "e.g. init_from='outputs/multirun/.../optim=adam,seed=0/results.h5'"
            )
        raise UserError(f"cannot read the overrides: {str(error).splitlines()[0]}{hint}") from None


def _sweeper(parsed: list[Any]) -> str:
    """The hydra/sweeper chosen (basic unless set); UserError for optuna without its plugin."""
    sweeper = next((str(o.value()) for o in parsed if o.key_or_group == "hydra/sweeper"), "basic")
    if sweeper == "optuna":
        try:
            import hydra_plugins.hydra_optuna_sweeper  # noqa: F401
        except ImportError:
            raise UserError(
                "hydra/sweeper=optuna is not installed (its plugin needs optuna < 3, which cannot "
                "sit beside physgrad's optuna): tune with 'physgrad compare' (docs/protocol.md)"
            ) from None
    return sweeper


def _group_choices_and_keys(
    parsed: list[Any], loader: Any, multirun: bool, sweeper: str
) -> tuple[dict[str, list[str]], list[str]]:
    """The options chosen per config group (each checked against the group's options) and the keys
    to look up in every combination of them; UserError for a sweep without -m or an interval the
    basic sweeper cannot sample."""
    from hydra.core.override_parser.types import Glob

    groups = set(loader.list_groups(""))
    group_values: dict[str, list[str]] = {}
    keys = []
    for override in parsed:
        key, value = override.key_or_group, override.value()
        _check_sweep(override, multirun, sweeper)
        if key.startswith("hydra") or override.is_delete():
            continue
        if key in groups and override.package is None:
            options = sorted(loader.get_group_options(key))
            if isinstance(value, Glob):
                values = value.filter(options)
            elif override.is_sweep_override():
                values = list(override.sweep_string_iterator())
            else:
                values = [override.get_value_element_as_str()]
            for choice in values:
                if choice not in options:
                    raise unknown_option(key, choice, options)
            group_values[("+" if override.is_add() else "") + key] = values
        elif not override.is_add() and not override.is_force_add():
            keys.append(key)
        elif not key.startswith(("task.", "optim.", "logger.")):
            # `+key` adds a keyword to the factory of a scene, a rule or a tracker; elsewhere
            # nothing reads it
            keys.append(key)
    return group_values, keys


def _check_sweep(override: Any, multirun: bool, sweeper: str) -> None:
    """A sweep of several values needs -m; a search interval needs a sweeper that samples one."""
    if override.is_sweep_override() and not multirun:
        raise UserError(
            f"'{override.input_line}' sweeps several values: add -m (--multirun) to run them all"
        )
    if override.is_interval_sweep() and sweeper == "basic":
        raise UserError(
            f"'{override.input_line}' is a search interval, which Hydra's basic sweeper cannot "
            "sample: tune with 'physgrad compare' (it searches each variant's learning rate, "
            "docs/protocol.md), or list values: choice(a,b,c) or a,b,c"
        )


def _check_combinations(
    group_values: dict[str, list[str]], keys: list[str], known: dict | None = None
) -> None:
    """Every combination of the chosen options composed (or taken from `known`, filled in), and
    each key looked up in it."""
    from hydra import compose as hydra_compose
    from hydra.errors import HydraException, MissingConfigException

    known = {} if known is None else known
    for combo in itertools.product(*group_values.values()):
        combo = dict(zip(group_values, combo))
        chosen = tuple(f"{g}={v}" for g, v in combo.items())
        try:
            cfg = known.get(chosen) or hydra_compose("config", overrides=list(chosen))
        except MissingConfigException as error:
            group, _, choice = (error.missing_cfg_file or "").rpartition("/")
            if group and error.options is not None:
                raise unknown_option(group, choice, sorted(error.options)) from None
            raise UserError(str(error).strip().splitlines()[0]) from None
        except HydraException as error:
            raise UserError(str(error).strip().splitlines()[0]) from None
        known[chosen] = cfg
        for key in keys:
            _check_key(cfg, key, combo)


# what Hydra itself instantiates from the hydra section, by physgrad's own or Hydra's: physgrad's
# sweep summary and job log, the standard library's logging handlers Hydra's defaults name, and
# the launchers and sweepers of installed Hydra plugins (site-packages' hydra_plugins namespace)
HYDRA_OWN_TARGETS = ("physgrad.sweep_hooks.SweepSummary", "physgrad.sweep_hooks.JobLogFile")
HYDRA_PLUGIN_PREFIXES = ("hydra._internal.core_plugins.", "hydra_plugins.")
LOGGING_CLASSES = ("logging.StreamHandler", "logging.FileHandler", "logging.NullHandler")


def hydra_targets(hydra: dict) -> list[tuple[str, str]]:
    """Every (where, target) that Hydra instantiates from a composed config's hydra section (as
    data, unresolved): the callbacks' _target_, the logging handlers' and filters' class and a
    formatter's or handler's "()" factory in job_logging and hydra_logging, and the launcher's and
    sweeper's _target_."""
    found = []
    for name, node in (hydra.get("callbacks") or {}).items():
        if isinstance(node, dict) and "_target_" in node:
            found.append((f"hydra.callbacks.{name}", str(node["_target_"])))
    for logging_section in ("job_logging", "hydra_logging"):
        section = hydra.get(logging_section)
        for kind in ("handlers", "formatters", "filters"):
            nodes = (section.get(kind) or {}) if isinstance(section, dict) else {}
            for name, node in nodes.items():
                for key in ("class", "()"):
                    if isinstance(node, dict) and key in node:
                        found.append((f"hydra.{logging_section}.{kind}.{name}", str(node[key])))
    for plugin in ("launcher", "sweeper"):
        node = hydra.get(plugin) or {}
        if isinstance(node, dict) and "_target_" in node:
            found.append((f"hydra.{plugin}", str(node["_target_"])))
    return found


def _check_hydra_targets(overrides: list[str]) -> DictConfig | None:
    """The door for what Hydra itself would instantiate before physgrad's job runs: every target
    of the composed hydra section (hydra_targets) is physgrad's, the standard logging handlers,
    an installed Hydra plugin's launcher or sweeper, or passes physgrad's one policy for targets
    (validate.allowed_target: a function of the user's own module); UserError (one line)
    otherwise, before Hydra runs anything. A user's config folder cannot make Hydra call
    os.makedirs as a "callback"."""
    from hydra import compose as hydra_compose
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    try:  # a sweep's first job: the hydra section is one for all its jobs
        cfg = hydra_compose(
            "config", overrides=first_of_sweeps(overrides), return_hydra_config=True
        )
    except HydraException:
        return None  # the composition's own errors are said where the run composes it
    hydra = OmegaConf.to_container(cfg.hydra, resolve=False)
    for where, target in hydra_targets(hydra if isinstance(hydra, dict) else {}):
        if target in HYDRA_OWN_TARGETS or target in LOGGING_CLASSES:
            continue
        if where.startswith(("hydra.launcher", "hydra.sweeper")) and target.startswith(
            HYDRA_PLUGIN_PREFIXES
        ):
            continue
        allowed_target(where, target)
        from hydra.utils import get_object

        try:
            resolved = get_object(target)
        except Exception:  # noqa: BLE001 - Hydra says why it cannot import it
            continue
        allowed_target(where, target, resolved)
    return cfg


def first_of_sweeps(overrides: list[str]) -> list[str]:
    """The overrides with each sweep (a,b,c; range(...); choice(...)) replaced by its first value:
    the overrides of the sweep's first job."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    first = []
    for override in OverridesParser.create().parse_overrides(list(overrides)):
        if not override.is_sweep_override():
            first.append(override.input_line)
            continue
        try:  # a glob over a group's options needs the loader: left as it is (not composed)
            value = next(iter(override.sweep_string_iterator()), None)
        except Exception:  # noqa: BLE001 - Hydra's own sweep kinds raise their own errors
            value = None
        if value is not None:
            first.append(f"{override.input_line.partition('=')[0]}={value}")
    return first


def _check_key(cfg: DictConfig, key: str, combo: dict) -> None:
    from omegaconf import DictConfig, OmegaConf

    if OmegaConf.select(cfg, key, default=_ABSENT) is not _ABSENT:
        return
    parent_key, _, leaf = key.rpartition(".")
    parent = OmegaConf.select(cfg, parent_key, default=_ABSENT) if parent_key else cfg
    if not isinstance(parent, DictConfig):
        raise UserError(f"unknown key '{key}': '{parent_key}' is not a section of the config")
    siblings = [k for k in parent.keys() if k != "_target_"]
    close = (
        [RENAMED[leaf]]
        if RENAMED.get(leaf) in siblings
        else difflib.get_close_matches(leaf, siblings, n=1)
    )
    where = f"{parent_key} has" if parent_key else "the top level has"
    scope = "".join(f" with {g}={v}" for g, v in combo.items() if key.startswith(g + "."))
    hint = f": did you mean {'.'.join(filter(None, [parent_key, close[0]]))}?" if close else ""
    raise UserError(f"unknown key '{key}'{scope}{hint} ({where}: {', '.join(map(str, siblings))})")
