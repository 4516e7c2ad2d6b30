"""The diagnosis and the physics are functions that read as one idea (issue 37's bound).

No function or method in ``stages/diagnose/`` or ``pipeline/model/`` is longer than 120
lines, its docstring included: the search grew by rules that each added a branch to one long
loop, and the bound keeps every move of it a function of its own.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("stages/diagnose", "pipeline/model")
MAX_LINES = 120


def long_functions(folder: Path, max_lines: int = MAX_LINES) -> list[str]:
    """``path:line name (n lines)`` of every function in ``folder`` longer than ``max_lines``."""
    out = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                n = int(node.end_lineno or node.lineno) - first + 1
                if n > max_lines:
                    out.append(f"{path.relative_to(ROOT)}:{first} {node.name} ({n} lines)")
    return out


def test_no_function_of_the_diagnosis_or_the_model_is_longer_than_120_lines():
    bad = [f for folder in FOLDERS for f in long_functions(ROOT / folder)]
    assert not bad, "\n".join(bad)


def test_the_bound_sees_a_long_function_and_its_decorator(tmp_path, monkeypatch):
    """The check counts from a decorator to the last line, nested functions included."""
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES - 2))
    src = tmp_path / "m.py"
    src.write_text(f"@staticmethod\ndef f():\n{body}\n    return 0\n"
                   "def g():\n    def h():\n        return 1\n    return h\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    assert long_functions(tmp_path) == [f"m.py:1 f ({MAX_LINES + 1} lines)"]
    assert long_functions(tmp_path, max_lines=MAX_LINES + 1) == []
