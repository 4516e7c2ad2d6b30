"""The layers of docs/architecture.md: a lower layer never imports a higher one.

``pipeline/core`` (errors, containers, the stage protocol, geometry, files) is imported by
everything and imports nothing of the project; ``pipeline/io`` (MCAP, CDR, the encoders, with
``schemas``) and ``pipeline/model`` (the physics) import only ``core`` and never each other;
``stages`` import ``core``, ``io`` and ``model``; ``pipeline/run`` (the runner) imports
the stages; ``pipeline/app`` (the program, campaigns, the simulator) may import anything.
Checked on the source of every module, every import statement included (those for the type
checker too: a type named across layers is a dependency all the same). An import inside a
function may not import the project at all, and no module imports another's private name.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: layer -> the layers it may import (itself included)
ALLOWED = {
    "core": {"core"},
    "schemas": {"core", "schemas"},
    "io": {"core", "schemas", "io"},
    "model": {"core", "model"},
    "stages": {"core", "schemas", "io", "model", "stages"},
    "run": {"core", "schemas", "io", "model", "stages", "run"},
    "app": {"core", "schemas", "io", "model", "stages", "run", "app"},
}


def layer_of(module: str) -> str | None:
    """The layer of a dotted module name of the project, or None for other modules."""
    parts = module.split(".")
    if parts[0] == "pipeline":
        if len(parts) > 1 and parts[1] in ALLOWED:
            return parts[1]
        return "core"  # the package itself (``__version__``, ``package_version``)
    if parts[0] in ("stages", "schemas"):
        return parts[0]
    return None


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _in_functions(tree: ast.AST) -> set[int]:
    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            inside.update(id(x) for x in ast.walk(node) if x is not node)
    return inside


def imports_of(path: Path) -> list[tuple[int, str, bool]]:
    """(line, absolute module, inside a function) of every import of the project in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    inside = _in_functions(tree)
    me = module_name(path).split(".")
    package = me if path.name == "__init__.py" else me[:-1]
    out = []
    for node in ast.walk(tree):
        late = id(node) in inside
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, late) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from pipeline import core``: the names may be modules
            out += [(node.lineno, f"{mod}.{a.name}", late) for a in node.names]
    return out


def sources() -> list[Path]:
    files = []
    for top in ("pipeline", "stages", "schemas"):
        files += sorted((ROOT / top).rglob("*.py"))
    return files


def test_every_module_is_in_a_layer_folder():
    for path in (ROOT / "pipeline").rglob("*.py"):
        rel = path.relative_to(ROOT / "pipeline")
        assert rel.parts[0] in ALLOWED or rel == Path("__init__.py"), path


def test_no_layer_imports_a_higher_one():
    bad = []
    for path in sources():
        mine = layer_of(module_name(path))
        for line, mod, _late in imports_of(path):
            other = layer_of(mod)
            if other is not None and other not in ALLOWED[mine]:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({mine}) imports {mod} ({other})")
    assert not bad, "\n".join(bad)


def test_no_project_import_inside_a_function():
    """A module's dependencies on the project, its own layer included, stand at its top."""
    bad = []
    for path in sources():
        mine = layer_of(module_name(path))
        for line, mod, late in imports_of(path):
            other = layer_of(mod)
            if late and other is not None:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({mine}) imports {mod} ({other}) "
                           "inside a function")
    assert not bad, "\n".join(bad)


def test_no_private_name_is_imported_from_another_module():
    """A name another module needs is public: ``_name`` is its own module's business."""
    bad = []
    for path in sources():
        for line, mod, _late in imports_of(path):
            name = mod.rsplit(".", 1)[-1]
            if name.startswith("_") and not name.startswith("__"):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)


def test_the_layer_rules_catch_what_they_forbid(tmp_path, monkeypatch):
    """The checks see an upward import under ``if TYPE_CHECKING:`` and one inside a function."""
    mod = tmp_path / "pipeline" / "core" / "x.py"
    mod.parent.mkdir(parents=True)
    mod.write_text("from typing import TYPE_CHECKING\n"
                   "if TYPE_CHECKING:\n    from stages.context import Context\n"
                   "def f():\n    from pipeline.model import forward\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    got = {(m, late) for _, m, late in imports_of(mod)}
    assert ("stages.context.Context", False) in got  # counted, not exempt
    assert ("pipeline.model.forward", True) in got  # inside a function


def test_only_the_listed_modules_are_imported_late():
    """Outside the project, a function imports only what ``LATE_IMPORTS`` lists (and why)."""
    from pipeline.core.warm import LATE_IMPORTS

    bad = []
    for path in sources():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        inside = _in_functions(tree)
        for node in ast.walk(tree):
            if id(node) not in inside or not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [] if node.level else [node.module or ""])
            for name in names:
                if layer_of(name) is None and not any(
                        name == m or name.startswith(m + ".") for m in LATE_IMPORTS):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {name}")
    assert not bad, "\n".join(bad)
