"""No function of ``src/sonarmap`` is longer than 80 lines, numba kernels apart (a kernel's loops
stay in one function so that numba compiles them as one unit)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "src" / "sonarmap"
MAX_LINES = 80


def _jitted(tree: ast.Module) -> set[str]:
    """Names of the module's functions compiled by numba: decorated ``@njit(...)`` / ``@jit``, or
    passed to ``njit(...)(name)`` at run time."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for d in node.decorator_list:
                target = d.func if isinstance(d, ast.Call) else d
                if isinstance(target, ast.Name | ast.Attribute) and ast.unparse(target).split(".")[-1] in ("njit", "jit"):
                    names.add(node.name)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Call):
            inner = node.func.func
            if ast.unparse(inner).split(".")[-1] in ("njit", "jit"):
                names.update(a.id for a in node.args if isinstance(a, ast.Name))
    return names


def _long_functions(source: str) -> list[tuple[str, int]]:
    tree = ast.parse(source)
    jitted = _jitted(tree)
    return [(n.name, n.end_lineno - n.lineno + 1) for n in ast.walk(tree)
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef) and n.name not in jitted
            and n.end_lineno - n.lineno + 1 > MAX_LINES]


def test_no_function_over_80_lines_outside_numba_kernels() -> None:
    long = [f"{p.relative_to(ROOT)}:{name} ({n} lines)" for p in sorted(ROOT.rglob("*.py"))
            for name, n in _long_functions(p.read_text(encoding="utf-8"))]
    assert not long, "functions over 80 lines: " + ", ".join(long)


def test_the_rule_sees_long_functions_and_spares_kernels() -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    src = (f"def long():\n{body}\n\n@njit(cache=True)\ndef kern():\n{body}\n\n"
           f"def late_py():\n{body}\n\nlate = njit(cache=True)(late_py)\n")
    assert _long_functions(src) == [("long", MAX_LINES + 1)]
