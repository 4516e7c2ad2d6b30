"""``magalign regress RESULTS --baseline BASE``: compare results with stored ones.

Prints a diff table (one row per compared quantity) and exits 1 when any quantity is outside
its tolerance (docs/campaigns.md), 0 otherwise, 2 on bad input.
"""

from __future__ import annotations

import argparse

from pipeline.app.regress import REGRESSION, Tolerances, compare, format_table
from pipeline.core.errors import RegressionFailure


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("regress", help="compare results with a stored baseline",
                       description="Compare results with stored ones, within tolerances; "
                       "exit status 1 when a quantity is outside its tolerance.")
    p.add_argument("results", help="results folder (the --out of magalign process)")
    p.add_argument("--baseline", required=True, help="baseline folder")
    p.add_argument("--tolerances", default=None, metavar="TOML",
                   help="tolerances file (default: BASE/tolerances.toml if present, else the "
                   "documented defaults)")
    p.add_argument("--failures-only", action="store_true",
                   help="show only the quantities outside tolerance")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Compare; print the table; raise RegressionFailure (exit 1) on any regression."""
    tol = Tolerances.load(args.tolerances) if args.tolerances else None
    rows = compare(args.results, args.baseline, tol)
    print(format_table(rows, failures_only=args.failures_only))
    bad = [r for r in rows if r.status == REGRESSION]
    if bad:
        recs = sorted({r.recording for r in bad})
        raise RegressionFailure(
            f"{len(bad)} quantit{'y' if len(bad) == 1 else 'ies'} outside tolerance in "
            f"{', '.join(recs)}", path=args.results,
            hint="see the table above; if the change is intended, regenerate the baseline")
    return 0
