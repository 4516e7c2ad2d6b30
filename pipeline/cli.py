"""The ``magalign`` command line (CONVENTIONS, "Command line").

Each subcommand lives in its own module under :mod:`pipeline.commands` and exposes
``add_parser(subparsers)`` (which sets ``func`` on its parser) and a ``run(args) -> int``.
This module only turns :class:`~pipeline.errors.MagalignError` into exit codes and one line
on stderr; a traceback is shown only with ``--debug``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback
import warnings

from .errors import MagalignError

COMMANDS = (
    "info",
    "export",
    "simulate",
    "calibrate",
    "diagnose",
    "process",
    "regress",
    "reproduce",
    "score",
    "view",
)


class _Parser(argparse.ArgumentParser):
    """argparse that exits with status 2 and one line, as CONVENTIONS require."""

    def error(self, message: str) -> None:  # noqa: D102
        words = self.prog.split()
        see = "magalign -h" if len(words) < 2 else f"magalign {words[-1]} -h"
        self.exit(2, f"magalign: usage: {message} (see {see})\n")


DESCRIPTION = ("Calibrate the misalignment between a magnetometer and its attitude source "
               "from MCAP recordings.")


def package_version() -> str:
    """Return the installed magalign version (package metadata), or "unknown"."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("magalign")
    except PackageNotFoundError:  # running from a source tree that was never installed
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser with every available subcommand."""
    parser = _Parser(prog="magalign", description=DESCRIPTION)
    parser.add_argument("--version", action="version",
                        version=f"magalign {package_version()}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"pipeline.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"pipeline.commands.{name}":
                continue
            raise
        mod.add_parser(sub)
    return parser


def _format_warning(message: Warning | str, category: type[Warning], filename: str,
                    lineno: int, line: str | None = None) -> str:
    """One line per warning, ``warning: <what was lost>`` (source location only with --debug)."""
    return f"warning: {message}"


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``magalign`` console script; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="magalign: %(message)s",
    )
    logging.captureWarnings(True)
    warnings.simplefilter("default")
    saved_format = warnings.formatwarning
    if not debug:
        warnings.formatwarning = _format_warning
    try:
        status = int(args.func(args) or 0)
    except MagalignError as exc:
        if debug:
            traceback.print_exc()
        print(f"magalign: {exc.one_line()}", file=sys.stderr)
        status = exc.exit_code
    except KeyboardInterrupt:
        print("magalign: interrupted; no partial output was kept", file=sys.stderr)
        status = 130
    except BrokenPipeError:
        status = 0
    finally:
        warnings.formatwarning = saved_format
    sys.stdout.flush()
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
