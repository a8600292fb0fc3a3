"""The size rules of the house: no module in services/ over 450 lines and no function over 60 lines, so that
each file and each function can be read whole."""

from __future__ import annotations

import ast

from tests.conftest import REPO_ROOT

SERVICES = REPO_ROOT / "services"
MAX_FILE_LINES = 450
MAX_FUNCTION_LINES = 60


def long_functions(source: str, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int]]:
    """(name, lines) of each function or method in `source` longer than `limit` lines, decorators included."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            lines = (node.end_lineno or node.lineno) - first + 1
            if lines > limit:
                found.append((node.name, lines))
    return found


def test_the_checker_finds_a_long_nested_function() -> None:
    body = "\n".join(f"        x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    source = f"def short():\n    return 1\n\n\nclass A:\n    def long(self):\n{body}\n"
    assert long_functions(source) == [("long", MAX_FUNCTION_LINES + 1)]


def test_no_module_in_services_is_too_long() -> None:
    sizes = {p: len(p.read_text().splitlines()) for p in SERVICES.rglob("*.py")}
    too_long = [
        f"{p.relative_to(REPO_ROOT)} ({n} lines)" for p, n in sorted(sizes.items()) if n > MAX_FILE_LINES
    ]
    assert not too_long, f"split these modules (at most {MAX_FILE_LINES} lines): {too_long}"


def test_no_function_in_services_is_too_long() -> None:
    too_long = [f"{p.relative_to(REPO_ROOT)}:{name} ({n} lines)"
                for p in sorted(SERVICES.rglob("*.py")) for name, n in long_functions(p.read_text())]
    assert not too_long, f"split these functions (at most {MAX_FUNCTION_LINES} lines): {too_long}"
