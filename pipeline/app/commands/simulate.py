"""``magalign simulate SCENARIO.toml --out REC.mcap [--seed S]``: a synthetic recording.

With ``--challenge N --seed S --out DIR`` it generates a diagnosis challenge instead (N
recordings with hidden effects, see :mod:`pipeline.app.challenge`).
"""

from __future__ import annotations

import argparse
import logging

from pipeline.app.challenge import (
    generate,  # owned by DIAGNOSE; imported only when asked for
)
from pipeline.app.commands._options import check_out_file
from pipeline.app.simulate import load_scenario, simulate, write_simulated
from pipeline.core.errors import UsageError

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("simulate", help="write a synthetic recording from a scenario file",
                       description="Write a synthetic MCAP recording from a scenario TOML "
                       "file; with --challenge N, a folder of N recordings with hidden effects "
                       "and their key.")
    p.add_argument("scenario", nargs="?", help="scenario TOML file")
    p.add_argument("--out", required=True,
                   help="output recording (.mcap); with --challenge an output folder")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the scenario's)")
    p.add_argument("--challenge", type=int, default=None, metavar="N",
                   help="generate a challenge of N recordings with hidden effects")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate and write; returns the exit status."""
    if args.challenge is not None:
        if args.scenario is not None:
            raise UsageError("give either a SCENARIO file or --challenge N, not both")
        if args.challenge < 1:
            raise UsageError(f"--challenge needs a positive count, got {args.challenge}")

        generate(args.challenge, 0 if args.seed is None else args.seed, args.out)
        print(f"wrote a challenge of {args.challenge} recordings to {args.out}")
        return 0
    if args.scenario is None:
        raise UsageError("a SCENARIO file is required (or --challenge N)")

    check_out_file(args.out)
    sim = simulate(load_scenario(args.scenario), seed=args.seed)
    path = write_simulated(sim, args.out)
    rec = sim.recording
    att = rec.attitude if rec.attitude is not None else rec.turntable
    print(
        f"wrote {path}: {len(rec.mag)} magnetometer and {0 if att is None else len(att)} "
        f"{'attitude' if rec.attitude is not None else 'turntable'} messages, "
        f"{rec.duration_s:.1f} s"
    )
    return 0
