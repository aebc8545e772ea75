"""The package's modules import each other without a circle (module level, TYPE_CHECKING included)."""

from __future__ import annotations

import ast
from pathlib import Path

import phigenesis

ROOT = Path(phigenesis.__file__).parent


def _module_name(path: Path) -> str:
    parts = ["phigenesis", *path.relative_to(ROOT).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_level_imports(tree: ast.Module, known: set[str]) -> set[str]:
    """Modules of the package a module imports at its top level, or inside a top-level ``if``
    (``if TYPE_CHECKING:``); imports inside functions are deliberate lazy imports."""
    out: set[str] = set()
    nodes = list(tree.body)
    while nodes:
        node = nodes.pop()
        if isinstance(node, ast.If | ast.Try):
            nodes.extend(
                node.body + node.orelse + getattr(node, "handlers", []) + getattr(node, "finalbody", [])
            )
        elif isinstance(node, ast.ExceptHandler):
            nodes.extend(node.body)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in known)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                out.add(sub if sub in known else node.module)
    return {m for m in out if m in known}


def _graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    known = set(files)
    return {name: _module_level_imports(ast.parse(p.read_text()), known) for name, p in files.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            # A package's __init__ importing its own submodule (or a submodule its package) is not a circle.
            if nxt.startswith(node + ".") or node.startswith(nxt + "."):
                continue
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_cycle_finder_finds_a_planted_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_the_package_has_no_import_circle():
    graph = _graph()
    assert "phigenesis.data.records" in graph
    assert _cycle(graph) is None, " -> ".join(_cycle(graph) or [])
