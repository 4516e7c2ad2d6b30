"""The layers of docs/architecture.md: a lower layer never imports a higher one.

``pipeline/core`` (errors, containers, the stage protocol, geometry, files) is imported by
everything and imports nothing of the project; ``pipeline/io`` (MCAP, CDR, the encoders, with
``schemas``) and ``pipeline/model`` (the physics) import only ``core`` and never each other;
``stages`` import ``core``, ``io`` and ``model``; ``pipeline/app`` (the program, campaigns,
the simulator) may import anything. Checked on the source of every module (imports inside
functions included); imports only for the type checker (``if TYPE_CHECKING:``) are exempt,
as they do not run.
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


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for n in node.body:
                skip.update(id(x) for x in ast.walk(n))
    return skip


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every runtime import of the project in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = _type_checking_nodes(tree)
    me = module_name(path).split(".")
    package = me if path.name == "__init__.py" else me[:-1]
    out = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from pipeline import core``: the names may be modules
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names]
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
        for line, mod in imports_of(path):
            other = layer_of(mod)
            if other is not None and other not in ALLOWED[mine]:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({mine}) imports {mod} ({other})")
    assert not bad, "\n".join(bad)
