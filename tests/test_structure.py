"""The package's shape stays findable (issue 12): no import cycles between modules, few
very long modules and functions. ``python tests/test_structure.py`` prints the figures."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "beadsight"
MAX_MODULE_LINES = 500  # a module longer than this is counted as long
MAX_FUNCTION_LINES = 80  # a function longer than this is counted as long
ALLOWED_LONG = 3  # "about 3" of each, each with a reason (docs/architecture.md)


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _parsed() -> dict[str, tuple[Path, ast.Module]]:
    return {_module_name(p): (p, ast.parse(p.read_text())) for p in sorted(PACKAGE.rglob("*.py"))}


def long_modules() -> list[tuple[int, str]]:
    lines = ((p.read_text().count("\n"), str(p.relative_to(SRC))) for p in PACKAGE.rglob("*.py"))
    return sorted((item for item in lines if item[0] > MAX_MODULE_LINES), reverse=True)


def long_functions() -> list[tuple[int, str]]:
    found = []
    for path, tree in _parsed().values():
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    found.append((n, f"{path.relative_to(SRC)}:{node.name}"))
    return sorted(found, reverse=True)


def import_cycles() -> list[list[str]]:
    """Cycles of module-level imports between modules (strongly connected components of
    more than one module). Packages' ``__init__`` re-exports are left out: they are lazy."""
    parsed = _parsed()
    packages = {name for name, (path, _) in parsed.items() if path.name == "__init__.py"}
    graph: dict[str, set[str]] = {}
    for name, (_path, tree) in parsed.items():
        if name in packages:
            continue
        targets: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets |= {node.module, *(f"{node.module}.{a.name}" for a in node.names)}
        graph[name] = {t for t in targets if t in parsed and t not in packages and t != name}
    return _cycles(graph)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components, iteratively; those with 2+ members."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    assert import_cycles() == []


def test_few_long_modules_and_functions():
    assert len(long_modules()) <= ALLOWED_LONG, long_modules()
    assert len(long_functions()) <= ALLOWED_LONG, long_functions()


if __name__ == "__main__":
    print(f"modules: {len(_parsed())}")
    print(f"modules over {MAX_MODULE_LINES} lines: {long_modules()}")
    print(f"functions over {MAX_FUNCTION_LINES} lines: {long_functions()}")
    print(f"import cycles: {import_cycles()}")
