"""The layers of docs/architecture.md hold over the whole house (physgrad/, hydra_plugins/ and
experiments/): every module has a layer, a module imports only modules of its own layer or below
(function-local, type-checking and relative imports included), no rooms import each other in a
cycle, and inside the packages comparison/ and tasks/ each module imports only the rooms below its
own."""

import ast
import re
from pathlib import Path

import pytest

from tests.helpers import REPO

PACKAGE = REPO / "physgrad"
ROOTS = [PACKAGE, REPO / "hydra_plugins", REPO / "experiments"]

# from the top; a package folder's modules all sit in its layer
LAYERS = [
    ("experiments", {"experiments"}),
    ("entry points", {"cli", "api", "__main__", "__init__"}),
    (
        "commands",
        {
            "comparison",
            "check",
            "stability_probes",
            "scene_check",
            "scene_derivatives",
            "bench",
            "bench_measure",
            "bench_tables",
        },
    ),
    (
        "a run",
        {
            "app",
            "sweep_hooks",
            "experiment",
            "job_spec",
            "members",
            "refusals",
            "run_figures",
            "resume",
            "timing",
        },
    ),
    (
        "training",
        {"runner", "trainer_settings", "guard", "writers", "training", "progress", "trackers"},
    ),
    (
        "reading",
        {
            "report",
            "report_figures",
            "cost_figures",
            "runs",
            "tables",
            "plots",
            "verdict",
            "paired_stats",
            "replication",
            "power",
            "claim_words",
            "claim_parts",
            "trend",
            "readout",
            "claim",
        },
    ),
    # what a sweep knows of its jobs, the launchers and the GPUs they claim: above the JAX core,
    # which knows nothing of jobs
    ("jobs", {"sweeps", "cluster", "gpus", "hydra_plugins"}),
    (
        "the JAX core",
        {
            "tasks",
            "optim",
            "gradients",
            "jacobians",
            "unroll",
            "loop_reference",
            "nets",
            "tridiagonal",
        },
    ),
    (
        "the bottom",
        {
            "results",
            "foreign",
            "files",
            "errors",
            "interrupts",
            "configs",
            "validate",
            "machine",
            "version",
        },
    ),
]

# inside a package, from the top: a module imports only modules of the entries below its own
INNER = {
    "comparison": [
        {"__init__"},
        {"study"},
        {"summary", "plan", "figure", "evaluation"},
        {"compare_text"},
        {"coverage"},
        {"tuning", "clock_text", "calibration"},
        {"journal", "tuned_in"},
        {"jobs", "study_folder"},
        {"progress"},
        {"spec"},
        {"points", "job_names", "search_space"},
    ],
    # a scene never imports another scene; the Kuramoto-Sivashinsky solver sits below its scene
    "tasks": [
        {"guidance", "ks", "multicart", "oscillator", "poisson", "quantum", "toy"},
        {"ks_solver"},
        {"__init__"},
    ],
}


def module_name(path: Path) -> str:
    """The dotted name a module is imported by (experiments' scripts by their file name, as they
    import each other from their folder)."""
    if path.is_relative_to(REPO / "experiments"):
        return "experiments." + path.stem
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def room_of_name(name: str) -> str | None:
    """The layer table's entry a dotted module name belongs to (None: not of this house)."""
    parts = name.split(".")
    if parts[0] == "experiments":
        return "experiments"
    if parts[:2] == ["hydra_plugins", "physgrad_launchers"]:
        return "hydra_plugins"
    if parts[0] != "physgrad":
        return None
    if len(parts) == 1:
        return "__init__"
    if (PACKAGE / parts[1]).is_dir() or (PACKAGE / f"{parts[1]}.py").exists():
        return parts[1]
    return None


def room(path: Path) -> str:
    return room_of_name(module_name(path)) or ""


def level(name: str) -> int:
    for depth, (_, rooms) in enumerate(LAYERS):
        if name in rooms:
            return depth
    raise KeyError(name)


def names_in(source: str, package: list[str]) -> set[str]:
    """Every module name (and name imported from a module) that the source imports anywhere in its
    text, relative imports resolved against its package (a list of dotted parts)."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            found.add(module)
            found.update(f"{module}.{alias.name}" for alias in node.names)
    return found


def imported_names(path: Path) -> set[str]:
    package = module_name(path).split(".")
    return names_in(path.read_text(), package if path.name == "__init__.py" else package[:-1])


def imported_rooms(path: Path) -> set[str]:
    """The rooms of the house a module imports anywhere in its text."""
    found = {room_of_name(name) for name in imported_names(path)}
    if path.is_relative_to(REPO / "experiments"):  # its scripts import each other by file name
        scripts = {p.stem for p in (REPO / "experiments").glob("*.py")}
        found |= {"experiments" for name in imported_names(path) if name in scripts}
    return found - {None}


MODULES = sorted(
    p
    for root in ROOTS
    for p in root.rglob("*.py")
    if "conf" not in p.relative_to(root).parts and "__pycache__" not in p.parts
)


def test_every_module_has_a_layer():
    missing = sorted({room(p) for p in MODULES} - set().union(*(r for _, r in LAYERS)))
    assert not missing, f"add to docs/architecture.md and LAYERS: {missing}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(REPO)))
def test_a_module_imports_only_its_own_layer_and_below(path):
    mine = level(room(path))
    upward = sorted(r for r in imported_rooms(path) - {room(path)} if level(r) < mine)
    assert not upward, f"{path.relative_to(REPO)} imports a higher layer: {upward}"


def inner_level(package: str, module: str) -> int:
    for depth, modules in enumerate(INNER[package]):
        if module in modules:
            return depth
    raise KeyError(f"add {package}/{module}.py to INNER and docs/architecture.md")


@pytest.mark.parametrize("package", sorted(INNER))
def test_inside_a_package_a_module_imports_only_the_rooms_below_its_own(package):
    for path in sorted((PACKAGE / package).glob("*.py")):
        mine = inner_level(package, path.stem)
        for name in imported_names(path):
            parts = name.split(".")
            if parts[:2] != ["physgrad", package] or len(parts) < 3:
                continue
            target = parts[2]
            if not (PACKAGE / package / f"{target}.py").exists():
                continue  # a name imported from the package's __init__
            assert inner_level(package, target) > mine, (
                f"physgrad/{package}/{path.name} imports {package}/{target}.py, which is not below "
                "it in INNER"
            )


def test_no_import_cycle_between_rooms():
    edges = {}
    for path in MODULES:
        edges.setdefault(room(path), set()).update(imported_rooms(path) - {room(path)})
    seen, stack = set(), set()

    def visit(node, trail):
        if node in stack:
            raise AssertionError("import cycle: " + " -> ".join([*trail, node]))
        if node in seen:
            return
        stack.add(node)
        for nxt in sorted(edges.get(node, ())):
            visit(nxt, [*trail, node])
        stack.discard(node)
        seen.add(node)

    for node in sorted(edges):
        visit(node, [])


def test_relative_function_local_and_type_checking_imports_are_read():
    source = (
        "from typing import TYPE_CHECKING\n"
        "from .jobs import x\n"
        "if TYPE_CHECKING:\n"
        "    from physgrad.app import job\n"
        "def f():\n"
        "    from ..report import y\n"
        "    from . import spec\n"
    )
    names = names_in(source, ["physgrad", "comparison"])
    assert {"physgrad.comparison.jobs", "physgrad.report", "physgrad.app"} <= names
    assert "physgrad.comparison.spec" in names
    assert {room_of_name(n) for n in names} >= {"comparison", "report", "app"}


# rooms of their own size: a module that grows past MODULE_LINES, or a function past
# FUNCTION_LINES, is doing several jobs (docs/architecture.md). Those over it today are listed with
# their size and may not grow: each is to be cut by concept, and leaves the list when it is
MODULE_LINES, FUNCTION_LINES = 450, 80
OVER: dict[str, int] = {}
LONG_FUNCTIONS: dict[str, int] = {}
HOUSE = sorted(
    p
    for base in ("physgrad", "hydra_plugins", "experiments")
    for p in (REPO / base).rglob("*.py")
    if "build" not in p.relative_to(REPO).parts
)


@pytest.mark.parametrize("path", HOUSE, ids=lambda p: str(p.relative_to(REPO)))
def test_a_module_is_a_room_of_its_own_size(path):
    """No module of physgrad/, hydra_plugins/ or experiments/ over MODULE_LINES lines, no function
    over FUNCTION_LINES, but those listed, which may not grow."""
    name = str(path.relative_to(REPO))
    text = path.read_text()
    lines = len(text.splitlines())
    assert lines <= OVER.get(name, MODULE_LINES), f"{name}: {lines} lines: cut it by concept"
    if name in OVER:
        assert lines > MODULE_LINES, f"{name} is within {MODULE_LINES} lines now: drop it from OVER"
    long = [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.end_lineno - node.lineno + 1
        > LONG_FUNCTIONS.get(f"{name}:{node.name}", FUNCTION_LINES)
    ]
    assert not long, f"{name}: {', '.join(long)}"
    sizes = {
        f"{name}:{node.name}": node.end_lineno - node.lineno + 1
        for node in ast.walk(ast.parse(text))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
    }
    for listed in (key for key in LONG_FUNCTIONS if key.startswith(f"{name}:")):
        assert sizes.get(listed, 0) > FUNCTION_LINES, f"{listed} is short now: unlist it"


HEAVY = ("jax", "hydra", "pandas", "matplotlib")


@pytest.mark.parametrize(
    "code",
    [
        "import physgrad",
        "from physgrad.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass",
        *(
            f"from physgrad.cli import main\ntry:\n    main(['{command}', '--help'])\n"
            "except SystemExit:\n    pass"
            for command in ("compare", "check", "report")
        ),
    ],
    ids=[
        "import physgrad",
        "physgrad --help",
        "physgrad compare --help",
        "physgrad check --help",
        "physgrad report --help",
    ],
)
def test_importing_physgrad_and_asking_for_help_load_no_heavy_library(code):
    """docs/architecture.md's promise, held in a fresh interpreter: `import physgrad` and the
    console's help load no JAX, Hydra, pandas or matplotlib (the console script installs its signal
    handlers first; help answers at once)."""
    import subprocess
    import sys

    probe = f"{code}\nimport sys\nprint(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, check=True
    )
    assert result.stdout.splitlines()[-1] == "", result.stdout.splitlines()[-1]


def test_signals_are_installed_in_one_place():
    """docs/architecture.md: all signal handling in physgrad/interrupts.py (its installer,
    handling_signals and stop_on_signals): no other module calls signal.signal."""
    found = [
        str(path.relative_to(REPO))
        for path in sorted((REPO / "physgrad").rglob("*.py"))
        if path.name != "interrupts.py" and "signal.signal(" in path.read_text()
    ]
    assert not found, found


# the scenes' own figures sit in the JAX core, below the reading layer that holds readout.fmt
OWN_NUMBER_FORMAT = {"physgrad/readout.py", "physgrad/tasks/guidance.py", "physgrad/tasks/ks.py"}


@pytest.mark.parametrize("path", HOUSE, ids=lambda p: str(p.relative_to(REPO)))
def test_a_number_in_a_table_or_message_has_one_format(path):
    """Three significant figures are readout.fmt's (with "-" for a missing number and inf as
    such): no module writes that format itself, but fmt's and the scenes' figures."""
    name = str(path.relative_to(REPO))
    inline = re.findall(r"\{[^{}]*:\.3g\}", path.read_text())
    assert name in OWN_NUMBER_FORMAT or not inline, f"{name}: {inline}: use physgrad.readout.fmt"


def test_physgrad_s_own_imports_stand_at_the_top_but_where_help_would_load_them():
    """A module imports physgrad's own modules at its top. Function-local imports of them are kept
    only in the modules the console's help loads (`physgrad --help` and each command's, measured
    here in a fresh interpreter), where importing at the top would load JAX, Hydra, pandas or
    matplotlib before help answers, or where the import line says why it waits (as matplotlib's
    only once a figure is drawn) (docs/architecture.md)."""
    import subprocess
    import sys

    probe = (
        "import contextlib, io, sys\nfrom physgrad.cli import main\n"
        "commands = ('run', 'report', 'check', 'compare')\n"
        "for args in (['--help'], *([c, '--help'] for c in commands)):\n"
        "    try:\n        with contextlib.redirect_stdout(io.StringIO()):\n"
        "            main(args)\n    except SystemExit:\n        pass\n"
        "print(' '.join(m for m in sys.modules if m.startswith('physgrad')))"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, check=True
    )
    at_help = set(result.stdout.split())
    local = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        name = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        if name in at_help:
            continue
        lines = path.read_text().splitlines()
        found = [
            f"line {sub.lineno}: {sub.module}"
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            for sub in ast.walk(node)
            if isinstance(sub, ast.ImportFrom)
            and (sub.module or "").startswith("physgrad")
            and "#" not in lines[sub.lineno - 1]
        ]
        if found:
            local[name] = found
    assert not local, f"import these at the top: {local}"
