"""Rooms stay small: no module of diffsmf over `MAX_MODULE_LINES` lines and no function over
`MAX_FUNCTION_LINES` (docstring included). Read with ``ast``; nothing is imported."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "diffsmf"
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 100


def oversized(root: Path) -> list[str]:
    """The modules and functions under ``root`` over the limits, as ``path[:line] name size``."""
    out = []
    for path in sorted(root.rglob("*.py")):
        src = path.read_text()
        lines = src.count("\n")
        if lines > MAX_MODULE_LINES:
            out.append(f"{path.relative_to(root)}: {lines} lines")
        for node in ast.walk(ast.parse(src, str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                size = node.end_lineno - node.lineno + 1
                if size > MAX_FUNCTION_LINES:
                    out.append(f"{path.relative_to(root)}:{node.lineno} {node.name}: {size} lines")
    return out


def test_the_checker_finds_a_long_function_and_a_long_module(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "long.py").write_text("def f():\n" + body)
    (tmp_path / "big.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    (tmp_path / "fine.py").write_text("def g():\n    return 1\n")
    assert oversized(tmp_path) == ["big.py: 801 lines", "long.py:1 f: 101 lines"]


def test_no_module_or_function_of_diffsmf_is_over_the_limits():
    assert oversized(PACKAGE) == []
