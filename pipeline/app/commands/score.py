"""``magalign score DIR RESULTS``: compare diagnoses of a challenge with its key."""

from __future__ import annotations

import argparse
import json

from pipeline.app.challenge import confusion_text, score


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    # no help=: a development command, listed under its own heading (cli.DEVELOPMENT_COMMANDS)
    p = sub.add_parser("score", description="Development: score the diagnoses of a simulated "
                       "challenge (magalign simulate --challenge) against its key.")
    p.add_argument("challenge", help="challenge folder written by simulate --challenge")
    p.add_argument("results", help="folder with <stem>/diagnosis.json per recording")
    p.add_argument("--key", default=None, help="key file (default: <challenge>_key/key.json)")
    p.add_argument("--json", action="store_true", help="print the score as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Score and print; returns the exit status."""
    res = score(args.challenge, args.results, args.key)
    if args.json:
        print(json.dumps({k: v for k, v in res.items() if k != "rows"}, indent=2))
        return 0
    print(confusion_text(res))
    p3 = res["param_within_3sigma"]
    print(
        f"exact effect set: {res['exact']}/{res['n']}; strong (>= 5x threshold): "
        f"{res['strong_exact']}/{res['strong_n']}; null with false findings: "
        f"{res['null_false']}/{res['null_n']}; parameters within 3 sigma: "
        f"{'n/a' if p3 is None else f'{100 * p3:.0f} %'} of {res['n_param_checks']}"
    )
    return 0
