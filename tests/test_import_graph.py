"""One way in each direction: no import circle between modules of services/, nor between its folders.

Every import counts, at any depth: inside functions and `if TYPE_CHECKING:` blocks too, because a
circle hidden in a function is still a circle a reader must hold in mind.

Folders: each directory under services/ is a node (its own modules, not its sub-folders'). A folder may
use its ancestors' modules (a service's root holds what its rooms share: deps, errors, context), so an
edge to an ancestor folder is not counted; every other edge is, siblings and cousins alike.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

from tests.conftest import REPO_ROOT

SERVICES = REPO_ROOT / "services"


def module_name(path: Path, root: Path = REPO_ROOT) -> str:
    """Dotted name of the module at `path` (a package's __init__ is the package itself)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_names(path: Path, module: str) -> set[str]:
    """Every dotted name `path` imports, relative imports resolved; `from a import b` gives a and a.b."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def module_graph(root: Path = SERVICES, repo: Path = REPO_ROOT) -> dict[str, set[str]]:
    """Module -> the modules of `root` it imports (a name that is not a module resolves to its parent)."""
    paths = {module_name(p, repo): p for p in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        targets = set()
        for name in imported_names(path, module):
            while name and name not in paths:
                name = name.rpartition(".")[0]
            # Importing a package's own parent package's __init__ is not an edge worth a circle.
            if name and name != module and not module.startswith(name + "."):
                targets.add(name)
        graph[module] = targets
    return graph


def folder_of(module: str, packages: set[str]) -> str:
    """The folder (package) a module lives in; a package's __init__ lives in the package itself."""
    return module if module in packages else module.rpartition(".")[0]


def folder_graph(graph: Mapping[str, set[str]], packages: set[str]) -> dict[str, set[str]]:
    """Folder -> folders its modules import, leaving out a folder's imports of its own ancestors."""
    folders: dict[str, set[str]] = {}
    for module, targets in graph.items():
        source = folder_of(module, packages)
        edges = folders.setdefault(source, set())
        for target in targets:
            folder = folder_of(target, packages)
            if folder != source and not source.startswith(folder + "."):
                edges.add(folder)
    return folders


def find_cycle(graph: Mapping[str, Iterable[str]]) -> list[str] | None:
    """One cycle of `graph` as [a, b, ..., a], or None; iterative depth-first search."""
    state: dict[str, int] = {}  # 1 on the current path, 2 finished
    for start in sorted(graph):
        if state.get(start):
            continue
        path = [start]
        stack = [iter(sorted(graph.get(start, ())))]
        state[start] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            elif not state.get(nxt):
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph.get(nxt, ()))))
    return None


def packages_of(root: Path = SERVICES, repo: Path = REPO_ROOT) -> set[str]:
    return {module_name(p, repo) for p in root.rglob("__init__.py")}


def test_the_checker_names_a_cycle_hidden_in_a_function(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "a").mkdir(parents=True)
    (pkg / "b").mkdir()
    for init in (pkg, pkg / "a", pkg / "b"):
        (init / "__init__.py").write_text("")
    (pkg / "a" / "one.py").write_text("from ..b import two\n")
    (pkg / "b" / "two.py").write_text("def f():\n    from pkg.a.one import x\n")
    graph = module_graph(pkg, tmp_path)
    assert find_cycle(graph) == ["pkg.a.one", "pkg.b.two", "pkg.a.one"]
    folders = folder_graph(graph, packages_of(pkg, tmp_path))
    assert find_cycle(folders) == ["pkg.a", "pkg.b", "pkg.a"]


def test_the_checker_sees_type_checking_imports_and_passes_a_tree(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "one.py").write_text("from pkg import two\n")
    (pkg / "two.py").write_text("from typing import TYPE_CHECKING\n"
                                "if TYPE_CHECKING:\n    from . import one\n")
    assert find_cycle(module_graph(pkg, tmp_path)) == ["pkg.one", "pkg.two", "pkg.one"]
    (pkg / "two.py").write_text("import os\n")
    assert find_cycle(module_graph(pkg, tmp_path)) is None


def test_no_import_cycle_between_modules() -> None:
    cycle = find_cycle(module_graph())
    assert cycle is None, f"modules import each other in a circle: {' -> '.join(cycle or [])}"


def test_no_import_cycle_between_folders() -> None:
    cycle = find_cycle(folder_graph(module_graph(), packages_of()))
    assert cycle is None, f"folders import each other in a circle: {' -> '.join(cycle or [])}"
