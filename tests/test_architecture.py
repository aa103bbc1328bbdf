"""The layers of docs/architecture.md hold: every module of physgrad/ has a layer, a module imports
only modules of its own layer or below (function-local and type-checking imports included), and no
modules import each other in a cycle."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "physgrad"

# from the top; a package folder's modules all sit in its layer
LAYERS = [
    ("entry points", {"cli", "api", "__main__", "__init__"}),
    ("commands", {"comparison", "check", "scene_check", "bench", "bench_measure", "bench_tables"}),
    ("a run", {"app", "experiment", "refusals", "run_figures", "resume", "timing"}),
    ("training", {"runner", "guard", "writers", "training", "progress", "trackers"}),
    (
        "reading",
        {"report", "report_figures", "runs", "tables", "plots", "verdict", "trend", "readout"},
    ),
    (
        "the JAX core",
        {"tasks", "optim", "gradients", "jacobians", "unroll", "nets", "tridiagonal"},
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
            "gpus",
            "sweeps",
            "cluster",
            "version",
        },
    ),
]


def room(path: Path) -> str:
    """The name of the layer table's entry holding a module: its first part under physgrad/."""
    return path.relative_to(PACKAGE).with_suffix("").parts[0]


def level(name: str) -> int:
    for depth, (_, rooms) in enumerate(LAYERS):
        if name in rooms:
            return depth
    raise KeyError(name)


def imported_rooms(path: Path) -> set[str]:
    """The rooms of physgrad a module imports anywhere in its text."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] != "physgrad":
                continue
            if len(parts) == 1:
                found.add("__init__")
            elif (PACKAGE / parts[1]).is_dir() or (PACKAGE / f"{parts[1]}.py").exists():
                found.add(parts[1])
    return found


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if "conf" not in p.relative_to(PACKAGE).parts)


def test_every_module_has_a_layer():
    missing = sorted({room(p) for p in MODULES} - set().union(*(r for _, r in LAYERS)))
    assert not missing, f"add to docs/architecture.md and LAYERS: {missing}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_a_module_imports_only_its_own_layer_and_below(path):
    mine = level(room(path))
    upward = sorted(r for r in imported_rooms(path) - {room(path)} if level(r) < mine)
    assert not upward, f"{path.relative_to(PACKAGE)} imports a higher layer: {upward}"


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
