"""The package's folders are its layers: a module imports only from its own layer or the ones below it.

The order (lowest first) is the architecture in the README: the pure core, what travels on the wire, the
simulated robots, policies, the robot interface, training, recording, scoring, transports, running
evaluations, reports, and the command line on top. Read from the source (``ast``), so a lazy import inside a
function counts as much as one at the top of a module.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "lq_ros"
LAYERS = (
    "core", "wire", "sim", "policies", "robot", "training", "recording", "scoring", "transport", "run", "report",
    "cli",
)  # fmt: skip


def layer_of(module: str) -> str | None:
    """``lq_ros.<layer>...`` -> its layer; the package root (``lq_ros``) belongs to no layer."""
    parts = module.split(".")
    if parts[0] != "lq_ros" or len(parts) < 2:
        return None
    return parts[1]


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            # ``from lq_ros.a import b``: b may be a module (lq_ros.a.b) or a name defined in lq_ros.a.
            out |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in out if name.startswith("lq_ros.")}


def modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def test_every_top_level_entry_is_a_known_layer():
    entries = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir() if not p.name.startswith(("_", "."))}
    entries.discard("__pycache__")
    assert entries == set(LAYERS)


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_import_from_a_higher_layer(path):
    own = layer_of("lq_ros." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
    upward = [
        name for name in imports_of(path)
        if (target := layer_of(name)) in LAYERS and LAYERS.index(target) > LAYERS.index(own)
    ]  # fmt: skip
    assert upward == [], f"{path.relative_to(PACKAGE)} ({own}) imports from higher layers: {upward}"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_import_cycle_between_modules():
    """No two modules import each other, directly or around a loop (lazy imports included)."""
    graph = {module_name(p): set() for p in PACKAGE.rglob("*.py")}
    for path in PACKAGE.rglob("*.py"):
        for name in imports_of(path):
            # ``from lq_ros.a import b`` may name the module lq_ros.a.b or a name in lq_ros.a.
            target = name if name in graph else name.rsplit(".", 1)[0]
            if target in graph and target != module_name(path):
                graph[module_name(path)].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert cycles == []
