"""Print a pip constraints file pinning every dependency to the lowest version pyproject allows.

Used by ``make test-fresh``: the suite is run once with the newest dependencies and once with
these, so that the ``>=`` bounds in ``pyproject.toml`` stay honest (a bound that no longer
works is raised). ``name>=X`` becomes ``name==X.*``: the oldest release series the bound
allows, in its newest patch release (a bound names a series, ``numpy>=1.26``, and the first
release of a series is not always published: ``mcap`` 1.2 starts at 1.2.1). Extras are
dropped (constraints take plain names); requirements without a lower bound are left free.

Usage: ``python tests/oldest_deps.py [pyproject.toml] > constraints.txt``
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import tomllib

_REQ = re.compile(r"^\s*([A-Za-z0-9_.-]+)(\[[^\]]*\])?\s*(.*)$")


def oldest(requirements: list[str]) -> list[str]:
    """Return ``name==lowest.*`` for each requirement with a ``>=`` bound."""
    out = []
    for req in requirements:
        m = _REQ.match(req)
        if m is None:
            continue
        name, spec = m.group(1), m.group(3)
        low = re.search(r">=\s*([0-9][0-9A-Za-z.]*)", spec)
        if low:
            out.append(f"{name}=={low.group(1)}.*")
    return out


def main(argv: list[str]) -> int:
    """Print the constraints of the pyproject file given (default ./pyproject.toml)."""
    path = Path(argv[1]) if len(argv) > 1 else Path("pyproject.toml")
    proj = tomllib.loads(path.read_text(encoding="utf-8"))["project"]
    reqs = list(proj.get("dependencies", []))
    for extra in proj.get("optional-dependencies", {}).values():
        reqs += extra
    print("\n".join(oldest(reqs)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
