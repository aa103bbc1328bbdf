"""Checks of single settings, each a one-line UserError that names the key and says what is allowed.

The code that reads a setting checks it: a scene's build function its task keys, the runner the
trainer keys, the spectral rules their truncation. ``call_target`` builds what a config names with
``_target_`` (a scene's build function, an optax factory) and turns a wrong keyword into the same
kind of one-line error.
"""

from __future__ import annotations

import difflib
import inspect
import math
import numbers
import os
from collections.abc import Callable, Collection, Sequence
from typing import Any

from physgrad.errors import UserError


def number(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    integer: bool = False,
    optional: bool = False,
    open_low: bool = False,
) -> Any:
    """``value`` if it is a finite (whole) number within [low, high) (or (low, high) with
    open_low)."""
    if value is None and optional:
        return None
    ok = (
        isinstance(value, numbers.Integral if integer else numbers.Real)
        and not isinstance(value, bool)
        and math.isfinite(value)
    )
    if ok and low is not None:
        ok = value > low if open_low else value >= low
    if ok and high is not None:
        ok = value < high
    if not ok:
        bounds = []
        if low is not None:
            bounds.append(f"{'>' if open_low else '>='} {low}")
        if high is not None:
            bounds.append(f"< {high}")
        kind = "a whole number" if integer else "a number"
        extra = " or null" if optional else ""
        raise UserError(
            f"{name}={value!r} is not allowed: use {kind} {' and '.join(bounds)}".rstrip() + extra
        )
    return value


def choice(name: str, value: Any, choices: Collection[Any]) -> Any:
    if value not in choices:
        raise UserError(
            f"{name}={value!r} is not allowed: choose one of {', '.join(map(str, choices))}"
        )
    return value


ARRAY_LIMIT = 2**31 - 1  # elements of one array: XLA indexes and passes sizes as 32-bit integers


def array_size(what: str, shape: Sequence[int], settings: str) -> None:
    """UserError (one line) where a scene would build an array of more elements than ARRAY_LIMIT,
    naming the settings that make it."""
    count = math.prod(int(n) for n in shape)
    if count > ARRAY_LIMIT:
        raise UserError(
            f"{what} would hold {count:,} numbers, more than one array can (2^31 - 1): use a "
            f"smaller {settings}"
        )


def flag(name: str, value: Any) -> bool:
    return choice(name, value, (False, True))


def layer_widths(name: str, value: Any) -> list[int]:
    """A non-empty list of positive whole numbers (hidden layer widths)."""
    widths = list(value) if isinstance(value, (list, tuple)) else None
    if not widths or not all(
        isinstance(w, int) and not isinstance(w, bool) and w > 0 for w in widths
    ):
        raise UserError(
            f"{name}={value!r} is not allowed: use a list of positive layer widths, e.g. [20, 20]"
        )
    return widths


def finite_numbers(tree: Any, prefix: str = "") -> None:
    """Refuse NaN and infinity anywhere in a (plain, resolved) config: no setting of physgrad means
    "unbounded" by inf (a missing limit is null)."""
    items = (
        tree.items()
        if isinstance(tree, dict)
        else enumerate(tree)
        if isinstance(tree, list)
        else ()
    )
    for key, value in items:
        name = (
            f"{prefix}.{key}"
            if prefix and isinstance(key, str)
            else f"{prefix}[{key}]"
            if prefix
            else str(key)
        )
        if isinstance(value, float) and not math.isfinite(value):
            raise UserError(f"{name}={value} is not allowed: use a finite number")
        finite_numbers(value, name)


# The `_target_`s physgrad calls are an allow list: a scene, an update rule, a schedule or a
# tracker is physgrad's own (its scenes, rules and trackers), optax's, or the user's: a module whose
# file lies outside the Python installation (the working folder, a config folder, an editable
# install), or one named in PHYSGRAD_TARGET_MODULES (comma-separated top-level names, for a scene
# package installed into site-packages). Everything else, a system module's function above all, is
# refused.
ALLOWED_TARGET_PREFIXES = ("physgrad.tasks.", "physgrad.optim.", "physgrad.trackers.", "optax.")
TARGET_MODULES_ENV = "PHYSGRAD_TARGET_MODULES"


def _installation_folders() -> list[str]:
    """The folders of the Python installation: the standard library and site-packages."""
    import sysconfig

    paths = sysconfig.get_paths()
    folders = {paths[key] for key in ("stdlib", "platstdlib", "purelib", "platlib") if key in paths}
    import site

    folders.update(getattr(site, "getsitepackages", lambda: [])())
    return sorted(os.path.realpath(f) for f in folders)


def _users_file(path: object) -> bool:
    """Whether a module's file lies outside the Python installation (the user's code); physgrad's
    own modules are not the user's (only its scenes, rules and trackers are targets)."""
    if not isinstance(path, str) or not os.path.isfile(path):
        return False  # a built-in or frozen module
    real = os.path.realpath(path)
    package = os.path.dirname(os.path.realpath(__file__))
    if real.startswith(package + os.sep):
        return False
    return not any(real.startswith(folder + os.sep) for folder in _installation_folders())


def _named_by_user(name: str) -> bool:
    extra = {m.strip() for m in os.environ.get(TARGET_MODULES_ENV, "").split(",") if m.strip()}
    return name.split(".")[0] in extra


def allowed_target(section: str, target: str, function: object = None) -> None:
    """physgrad's one policy for every `_target_` it calls (call_target, nested ones included), an
    allow list: the name must start with one of ALLOWED_TARGET_PREFIXES or name a module of the
    user's (its top-level module's file outside the Python installation, found without importing
    it, or named in PHYSGRAD_TARGET_MODULES), with no private part; and the function it resolves to
    (function, where the caller has resolved it) must be defined there too, so that a user's module
    cannot hand on os.system. UserError (one line) otherwise."""
    import importlib.util
    import sys

    refused = UserError(
        f"{section}._target_={target} is not allowed: a target is one of physgrad's scenes, rules "
        "or trackers, an optax function, or a function of your own module (in the working or "
        f"config folder, an editable install, or named in {TARGET_MODULES_ENV})"
    )
    parts = target.split(".")
    if len(parts) < 2 or any(not p or p.startswith("_") for p in parts):
        raise refused
    if not target.startswith(ALLOWED_TARGET_PREFIXES) and not _named_by_user(target):
        try:  # where the top-level module lives, without running it
            spec = importlib.util.find_spec(parts[0])
        except (ImportError, ValueError):
            spec = None
        if spec is None:
            return  # not importable: call_target says so in one line
        if not _users_file(spec.origin):
            raise refused
    if function is None:
        return
    defined_in = getattr(function, "__module__", None)
    if not isinstance(defined_in, str):
        raise refused
    if (defined_in + ".").startswith(ALLOWED_TARGET_PREFIXES) or _named_by_user(defined_in):
        return
    if not _users_file(getattr(sys.modules.get(defined_in), "__file__", None)):
        raise refused


def targets_by_name(section: str, node: Any) -> None:
    """allowed_target, by name alone (nothing imported), for node's `_target_` and every nested
    one: the check of a section's targets at a job's door (physgrad.job_spec.check)."""
    _nested_targets(section, node, resolve=False)


def _nested_targets(section: str, node: Any, resolve: bool = True) -> None:
    """allowed_target for every `_target_` under node, without recursion; with resolve, also the
    function each one imports to (call_target's second look)."""
    pending = [(section, node)]
    while pending:
        where, value = pending.pop()
        if isinstance(value, dict):
            if isinstance(value.get("_target_"), str):
                target = value["_target_"]
                allowed_target(where, target)  # by its name, before anything is imported
            if isinstance(value.get("_target_"), str) and resolve:
                from hydra.utils import get_object

                try:
                    resolved = get_object(target)
                except Exception:  # noqa: BLE001 - instantiate says why it cannot import it
                    resolved = None
                if resolved is not None:
                    allowed_target(where, target, resolved)
            pending.extend((f"{where}.{k}", v) for k, v in value.items())
        elif isinstance(value, list):
            pending.extend((f"{where}[{i}]", v) for i, v in enumerate(value))


def call_target(
    section: str,
    node: dict,
    reserved: Collection[str] = (),
    through: Callable[[Callable[..., Any]], Callable[..., Any]] | None = None,
    **runtime: Any,
) -> Any:
    """Call the function that ``node['_target_']`` names with the node's other keys (but
    ``reserved``, which physgrad reads itself) as keyword arguments, plus ``runtime``. Nested
    ``_target_`` nodes are built first (hydra.utils.instantiate), so a schedule can be an argument.
    ``section`` ("task", "optim") names the config group in messages; ``through`` wraps the function
    before the call (optax.inject_hyperparams). UserError if the target cannot be imported or does
    not take the keys given, or if it or a nested one is not allowed (allowed_target)."""
    from hydra.utils import get_object, instantiate

    target = node.get("_target_")
    if not isinstance(target, str) or not target:
        raise UserError(
            f"the {section} config has no _target_: name the function that builds it "
            f"(e.g. _target_: mylab.pendulum.build)"
        )
    allowed_target(section, target)  # by its name, before anything is imported
    _nested_targets(section, {k: v for k, v in node.items() if k != "_target_"})
    try:
        function = get_object(target)
    except Exception as error:  # noqa: BLE001 - Hydra wraps import errors of every kind
        cause = error.__cause__ or error
        raise UserError(
            f"{section}._target_={target} cannot be imported ({type(cause).__name__}: "
            f"{str(cause).splitlines()[0]}): check the name, and run from the folder that holds "
            f"the module or install it"
        ) from None
    allowed_target(section, target, function)
    if not callable(function):
        raise UserError(f"{section}._target_={target} is not a function")
    settings = {k: v for k, v in node.items() if k != "_target_" and k not in reserved}
    _check_keywords(section, target, function, set(settings), set(runtime))
    kwargs = instantiate(settings, _convert_="all") if settings else {}
    return (through(function) if through is not None else function)(**kwargs, **runtime)


def _check_keywords(
    section: str, target: str, function: Callable[..., Any], given: set, runtime: set
) -> None:
    try:
        parameters = inspect.signature(function).parameters
    except (TypeError, ValueError):  # a builtin without a signature: let the call itself decide
        return
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    accepted = [
        name
        for name, p in parameters.items()
        if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    ]
    for key in sorted(given - set(accepted)):
        close = difflib.get_close_matches(key, [a for a in accepted if a not in runtime], n=1)
        hint = f": did you mean {section}.{close[0]}?" if close else ""
        settable = ", ".join(a for a in accepted if a not in runtime)
        raise UserError(
            f"{section}.{key} is not a setting of {target}{hint} (it takes: {settable})"
        )
    for key in sorted(runtime - set(accepted)):
        raise UserError(
            f"{target} must take the keyword argument {key!r}: physgrad passes it (see "
            "docs/extending.md)"
        )
    missing = [
        name
        for name, p in parameters.items()
        if p.default is inspect.Parameter.empty
        and p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        and name not in given
        and name not in runtime
    ]
    if missing:
        raise UserError(
            f"{target} needs {', '.join(section + '.' + m for m in missing)}: add "
            f"{'it' if len(missing) == 1 else 'them'} to the {section} config"
        )
