"""``magalign reproduce li2020|tang2016 --out DIR``: the papers' simulations beside ours."""

from __future__ import annotations

import argparse
import importlib

PAPERS = {
    "li2020": "pipeline.app.reproduce_li2020",
    "tang2016": "pipeline.app.reproduce_tang2016",
}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("reproduce", help="reproduce a paper's simulation and tables")
    p.add_argument("paper", choices=sorted(PAPERS))
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the chosen paper's reproduction (its module's ``reproduce(out_dir) -> int``)."""
    mod = importlib.import_module(PAPERS[args.paper])
    return int(mod.reproduce(args.out) or 0)
