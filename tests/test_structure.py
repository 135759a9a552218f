"""The package's shape stays findable (issues 12 and 27): no import cycles between modules
or between packages, a written package order that every import keeps, few very long
modules and functions. ``python tests/test_structure.py`` prints the figures.

Every ``import`` and ``from ... import`` of a module counts, wherever it stands: at the top,
inside a function (a deferred import is still a dependency, only a later one), and under
``if TYPE_CHECKING:`` (a type from another package is a dependency on that package's shape,
and an order that only holds at run time would not say where a concept lives).
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "beadsight"
MAX_MODULE_LINES = 500  # a module longer than this is counted as long
MAX_FUNCTION_LINES = 80  # a function longer than this is counted as long
ALLOWED_LONG = 3  # "about 3" of each, each with a reason (docs/architecture.md)

# The package order, top to bottom (docs/architecture.md draws it). A package or top-level
# module may import only those on lines below its own; those on one line are independent of
# each other. ``beadsight`` is the package's ``__init__`` (``__version__``; its public API is
# named there as strings and imported on first use, so it imports nothing).
ORDER = (
    "__main__",
    "cli",
    "demo calibrate",
    "live",
    "health",
    "rig",
    "train",
    "evaluation",
    "report",
    "inference",
    "devices",
    "sim",
    "data",
    "assets",
    "checkpoint",
    "model",
    "preprocess",
    "lens",
    "metrics",
    "geometry torch_device",
    "config h5safe safe_numpy",
    "files lazy",
    "errors",
    "beadsight",
)


def _module_name(path: Path, src: Path) -> str:
    parts = path.relative_to(src).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _parsed() -> dict[str, tuple[Path, ast.Module]]:
    return _parse(SRC, PACKAGE)


@functools.cache
def _parse(src: Path, package: Path) -> dict[str, tuple[Path, ast.Module]]:
    """Every module of ``package`` parsed, once per process (a second each time otherwise)."""
    return {
        _module_name(p, src): (p, ast.parse(p.read_text())) for p in sorted(package.rglob("*.py"))
    }


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


def _init_names(tree: ast.Module) -> dict[str, str]:
    """What a package's ``__init__`` hands out: name -> the module defining it, from its
    ``from M import name`` lines and from lazy tables (dicts of name -> "beadsight.M")."""
    names: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names |= {a.asname or a.name: node.module for a in node.names}
        elif isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and isinstance(value, ast.Constant):
                    if str(value.value).startswith("beadsight"):
                        names[str(key.value)] = str(value.value)
    return names


def import_graph() -> dict[str, set[str]]:
    """module -> the beadsight modules it imports (anywhere in its text). ``from P import
    name`` of a package P counts as an import of the module that defines ``name`` (P's
    ``__init__`` re-exports it, eagerly or lazily), or of P itself if P defines it.
    Python runs a package's ``__init__`` before any of its modules; that edge is left out,
    as it says nothing about which concept needs which."""
    return {name: set(targets) for name, targets in _graph(SRC, PACKAGE).items()}


@functools.cache
def _graph(src: Path, package: Path) -> dict[str, set[str]]:
    parsed = _parse(src, package)
    packages = {name for name, (path, _) in parsed.items() if path.name == "__init__.py"}
    exports = {name: _init_names(parsed[name][1]) for name in packages}
    graph: dict[str, set[str]] = {}
    for name, (_path, tree) in parsed.items():
        here = name if name in packages else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = here.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                for alias in node.names:
                    full = f"{base}.{alias.name}"
                    if full in parsed:
                        targets.add(full)
                    elif base in packages:
                        targets.add(exports[base].get(alias.name, base))
                    else:
                        targets.add(base)
        graph[name] = {t for t in targets if t in parsed and t != name}
    return graph


def unit(module: str) -> str:
    """The package (or top-level module) a module belongs to: ``beadsight.data.dataset`` ->
    ``data``, ``beadsight.geometry`` -> ``geometry``, ``beadsight`` -> ``beadsight``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def package_graph(graph: dict[str, set[str]] | None = None) -> dict[str, set[str]]:
    graph = import_graph() if graph is None else graph
    packages: dict[str, set[str]] = {}
    for module, targets in graph.items():
        packages.setdefault(unit(module), set()).update(unit(t) for t in targets)
    return {name: targets - {name} for name, targets in packages.items()}


def import_cycles() -> list[list[str]]:
    """Cycles between modules (strongly connected components of more than one module)."""
    return _cycles(import_graph())


def package_cycles() -> list[list[str]]:
    """Cycles between packages and top-level modules."""
    return _cycles(package_graph())


def order_violations(graph: dict[str, set[str]] | None = None) -> list[str]:
    """Every import that goes up or sideways in :data:`ORDER`, and every package missing
    from it: "a.b -> c.d (a is not above c)"."""
    graph = import_graph() if graph is None else graph
    level = {name: n for n, line in enumerate(ORDER) for name in line.split()}
    found = [f"{u} is in no line of ORDER" for u in sorted({unit(m) for m in graph} - set(level))]
    for module, targets in sorted(graph.items()):
        for target in sorted(targets):
            a, b = unit(module), unit(target)
            if a != b and a in level and b in level and level[a] >= level[b]:
                found.append(f"{module} -> {target} ({a} is not above {b})")
    return found


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
                    work.append((child, iter(sorted(graph.get(child, ())))))
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


def test_the_graph_counts_imports_inside_functions_and_type_checking(tmp_path, monkeypatch):
    """A deferred import, a ``TYPE_CHECKING`` import, a relative import and a name a
    package's ``__init__`` re-exports all make edges; the order check names each upward one."""
    package = tmp_path / "beadsight"
    (package / "low").mkdir(parents=True)
    (package / "__init__.py").write_text('__version__ = "0"\n')
    (package / "low" / "__init__.py").write_text(
        "from beadsight.low.thing import Thing\n_LAZY = {'Other': 'beadsight.low.other'}\n"
    )
    (package / "low" / "thing.py").write_text(
        "def f():\n    from beadsight.high import g\n\nclass Thing: ...\n"
    )
    (package / "low" / "other.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .thing import Thing\n"
    )
    (package / "high.py").write_text(
        "from beadsight import __version__\nfrom beadsight.low import Other, Thing\n"
    )
    monkeypatch.setitem(globals(), "SRC", tmp_path)
    monkeypatch.setitem(globals(), "PACKAGE", package)
    graph = import_graph()
    assert graph["beadsight.low.thing"] == {"beadsight.high"}
    assert graph["beadsight.low.other"] == {"beadsight.low.thing"}
    assert graph["beadsight.high"] == {"beadsight", "beadsight.low.thing", "beadsight.low.other"}
    assert package_cycles() == [["high", "low"]]
    assert import_cycles() == [["beadsight.high", "beadsight.low.other", "beadsight.low.thing"]]
    monkeypatch.setitem(globals(), "ORDER", ("high", "low", "beadsight"))
    assert order_violations() == ["beadsight.low.thing -> beadsight.high (low is not above high)"]


def test_no_import_cycles_between_modules():
    assert import_cycles() == []


def test_no_import_cycles_between_packages():
    assert package_cycles() == []


def test_every_import_keeps_the_package_order():
    assert order_violations() == []


def test_few_long_modules_and_functions():
    assert len(long_modules()) <= ALLOWED_LONG, long_modules()
    assert len(long_functions()) <= ALLOWED_LONG, long_functions()


if __name__ == "__main__":
    print("package order (a package imports only those below it):")
    for line in ORDER:
        print(f"  {line}")
    print(f"modules: {len(_parsed())}")
    print(f"modules over {MAX_MODULE_LINES} lines: {long_modules()}")
    print(f"functions over {MAX_FUNCTION_LINES} lines: {long_functions()}")
    print(f"import cycles between modules: {import_cycles()}")
    print(f"import cycles between packages: {package_cycles()}")
    violations = order_violations()
    print(f"imports against the package order: {len(violations)}")
    for violation in violations:
        print(f"  {violation}")
