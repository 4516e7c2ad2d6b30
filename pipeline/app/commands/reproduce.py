"""``magalign reproduce li2020|tang2016 --out DIR``: the papers' simulations beside ours."""

from __future__ import annotations

import argparse
import importlib

from pipeline.app.commands._options import check_out_folder

PAPERS = {
    "li2020": "pipeline.app.reproduce_li2020",
    "tang2016": "pipeline.app.reproduce_tang2016",
}


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    # no help=: a development command, listed under its own heading (cli.DEVELOPMENT_COMMANDS)
    p = sub.add_parser("reproduce", description="Development: reproduce a paper's simulation "
                       "and tables (Li et al. 2020, Tang et al. 2016), the paper's numbers "
                       "beside magalign's.")
    p.add_argument("paper", choices=sorted(PAPERS), help="which paper: li2020 or tang2016")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (gets PAPER.json and figures)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the chosen paper's reproduction (its module's ``reproduce(out_dir) -> int``)."""
    check_out_folder(args.out)
    mod = importlib.import_module(PAPERS[args.paper])
    return int(mod.reproduce(args.out) or 0)
