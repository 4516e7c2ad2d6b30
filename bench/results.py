"""One row per benchmark figure appended to ``bench/results.csv`` (issue 18).

Columns: ``date`` (UTC, ISO 8601), ``commit`` (short hash, ``+dirty`` with uncommitted
changes), ``machine`` (architecture, logical cores, memory; no host name), ``load`` (1-minute
load average when the figure was taken), ``bench``, ``figure``, ``value``, ``unit``,
``reference`` (the ecosystem's or the ceiling's figure measured in the same run, when there
is one) and ``ratio``. The file is appended to, never rewritten, so that runs can be compared
over time; plot or filter it with any CSV tool.
"""

from __future__ import annotations

import csv
import datetime as _dt
import os
import platform
import subprocess
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results.csv"
COLUMNS = ("date", "commit", "machine", "load", "bench", "figure", "value", "unit",
           "reference", "ratio")


def _commit() -> str:
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, text=True, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty.strip() else "")


def _machine() -> str:
    mem_gib = ""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        mem_gib = f", {pages * size / 2**30:.0f} GiB"
    except (ValueError, OSError, AttributeError):
        pass
    return f"{platform.machine()}, {os.cpu_count()} cores{mem_gib}"


def record(bench: str, figure: str, value: float, unit: str, *,
           reference: float | None = None, ratio: float | None = None) -> None:
    """Append one figure of a benchmark run to ``bench/results.csv``."""
    new = not RESULTS.exists()
    with open(RESULTS, "a", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        if new:
            w.writerow(COLUMNS)
        w.writerow([
            _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"), _commit(),
            _machine(), f"{os.getloadavg()[0]:.2f}", bench, figure, f"{value:.6g}", unit,
            "" if reference is None else f"{reference:.6g}",
            "" if ratio is None else f"{ratio:.4g}",
        ])
