"""Import every beadsight module and every library they import (at module level or inside
a function), so that Python writes their bytecode once, at setup (scripts/setup.sh); then
say what is ready.

uv installs without compiling bytecode, and where PYTHONDONTWRITEBYTECODE is set no process
writes it later: each would compile torch & co. from source on every import (3.9 s instead
of 2.1 s for ``import torch`` alone). Compiling all of site-packages (``--compile-bytecode``)
took 30 s of setup for 11k files; this compiles the ~2k files that are really imported, in
about 10 s of one core. Run it with PYTHONDONTWRITEBYTECODE unset.
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import sys
from pathlib import Path

import beadsight


def imported_libraries(package: Path) -> set[str]:
    """The modules outside beadsight and the standard library that the package imports."""
    names: set[str] = set()
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module)
    return {n for n in names if n.split(".")[0] not in {"beadsight", *sys.stdlib_module_names}}


def main() -> None:
    for module in pkgutil.walk_packages(beadsight.__path__, "beadsight."):
        if not module.name.endswith("__main__"):  # that one runs the CLI
            importlib.import_module(module.name)
    for name in sorted(imported_libraries(Path(beadsight.__file__).parent)):
        try:
            importlib.import_module(name)
        except ModuleNotFoundError:  # a backport for older Pythons (tomli); the tests
            pass  # check that every declared extra imports
    torch = sys.modules["torch"]
    print(f"beadsight {beadsight.__version__} ready (torch {torch.__version__}) in .venv")


if __name__ == "__main__":
    main()
