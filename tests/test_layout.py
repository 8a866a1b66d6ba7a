"""The package's shape: no import cycles, light pure modules, recipes that are scripts of library calls."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (anywhere in its body, lazy imports included)."""
    modules = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            # a module importing its own parent package is not a cycle of interest (the package's
            # __init__ runs first anyway)
            graph[name] |= {t for t in targets if t in modules and t != name and not name.startswith(t + ".")}
    return graph


def test_no_import_cycles():
    graph = import_graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, cycles


def test_the_import_graph_sees_imports():  # the check above can fail: the graph has the known edges
    graph = import_graph()
    assert "contact_viz.params" in graph["contact_viz.geometry.patch"]
    assert "contact_viz.synth.params" in graph["contact_viz.synth.files"]


def test_pure_modules_import_no_heavy_library():
    code = ("import sys, contact_viz.geometry.patch, contact_viz.model.hmm, contact_viz.model.metrics; "
            "print(sorted(m for m in ('rerun', 'torch', 'open3d', 'typer') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def test_recipes_import_the_library_not_each_other():
    for recipe in (ROOT / "recipes").glob("*.py"):
        tree = ast.parse(recipe.read_text())
        assert "sys.path" not in recipe.read_text(), recipe
        imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not imported & {p.stem for p in (ROOT / "recipes").glob("*.py")}, recipe
