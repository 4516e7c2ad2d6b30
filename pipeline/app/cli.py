"""The ``magalign`` command line (CONVENTIONS, "Command line").

Each subcommand lives in its own module under :mod:`pipeline.app.commands` and exposes
``add_parser(subparsers)`` (which sets ``func`` on its parser) and a ``run(args) -> int``.
This module only turns :class:`~pipeline.core.errors.MagalignError` into exit codes and one line
on stderr; a traceback is shown only with ``--debug``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import shlex
import sys
import textwrap
import traceback
import warnings
from typing import Any, NoReturn, TextIO, cast

from pipeline import package_version
from pipeline.core.errors import MagalignError, UsageError, damage_behind
from pipeline.core.style import unsigned_zeros

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

#: Commands for checking magalign itself, not for calibrating a sensor: they stay out of the
#: command list (their parsers are registered without a help line) and are named under a
#: heading of their own.
DEVELOPMENT_COMMANDS = {
    "reproduce": "the papers' simulations and tables beside magalign's",
    "score": "diagnoses of a simulated challenge against its key",
}


class _Parser(argparse.ArgumentParser):
    """argparse that exits with status 2 and one line, as CONVENTIONS require."""

    def error(self, message: str) -> NoReturn:  # noqa: D102
        words = self.prog.split()
        see = "magalign -h" if len(words) < 2 else f"magalign {words[-1]} -h"
        self.exit(2, f"magalign: usage: {message} (see {see})\n")


DESCRIPTION = textwrap.fill("Calibrate the misalignment between a magnetometer and its "
                            "attitude source from MCAP recordings.", 78)
#: Laid out as the command list above it (the top-level help keeps it as written).
EPILOG = "development commands, for checking magalign itself:\n" + "\n".join(
    f"    {k:<13}{v}" for k, v in DEVELOPMENT_COMMANDS.items())


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Build the argument parser with every available subcommand.

    ``command``: the subcommand being run; only its module is imported (each imports what
    it runs at its top: the analysis, rerun, the campaign machinery), the others are named
    without their options. None: every subcommand in full (the top-level help).
    """
    parser = _Parser(prog="magalign", description=DESCRIPTION, epilog=EPILOG,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version",
                        version=f"magalign {package_version()}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMANDS:
        if command is not None and name != command:
            sub.add_parser(name)
            continue
        try:
            mod = importlib.import_module(f"pipeline.app.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"pipeline.app.commands.{name}":
                continue
            raise
        mod.add_parser(sub)
    return parser


class _UnsignedZeros:
    """stdout for a command: each whole line written passes :func:`unsigned_zeros`.

    The commands print text whose numbers many modules formatted; whatever the numerics of
    the build left a hair below zero is not printed as "-0" or "-0.00".
    """

    def __init__(self, target: TextIO):
        self.target = target
        self._tail = ""

    def write(self, text: str) -> int:
        head, nl, self._tail = (self._tail + text).rpartition("\n")
        if nl:
            self.target.write(unsigned_zeros(head + nl))
        return len(text)

    def flush(self) -> None:
        if self._tail:
            self.target.write(unsigned_zeros(self._tail))
            self._tail = ""
        self.target.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.target, name)


def _format_warning(message: Warning | str, category: type[Warning], filename: str,
                    lineno: int, line: str | None = None) -> str:
    """One line per warning, ``warning: <what was lost>`` (source location only with --debug)."""
    return f"warning: {message}"


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``magalign`` console script; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    named = [a for a in argv if not a.startswith("-")][:1]
    parser = build_parser(named[0] if named and named[0] in COMMANDS else None)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="magalign: %(message)s",
    )
    # Warnings are held until the command ends: a command that fails with bad input says so
    # in exactly one line (what it repaired before giving up is moot); one that succeeds, or
    # a campaign that partly failed, prints each warning as one line.
    # the report's provenance names the command line (worker processes inherit it)
    old_command = os.environ.get("MAGALIGN_COMMAND")
    os.environ["MAGALIGN_COMMAND"] = shlex.join(["magalign", *argv])
    stdout = sys.stdout
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        try:
            sys.stdout = cast(TextIO, _UnsignedZeros(stdout))
            try:
                status = int(args.func(args) or 0)
            finally:
                sys.stdout.flush()
                sys.stdout = stdout
            failed = False
        except MagalignError as exc:
            if exc.exit_code == 2 and not isinstance(exc, UsageError):
                # bad input: the recording (or input) the command was given, unless named
                exc.naming(getattr(args, "recording", None) or getattr(args, "input", None))
            if debug:
                traceback.print_exc()
            line = exc.one_line()
            if exc.exit_code == 2 and not debug:
                line += damage_behind(caught, exc.path)
            _show(caught, debug or exc.exit_code != 2, debug)
            print(f"magalign: {unsigned_zeros(line)}", file=sys.stderr)
            status, failed = exc.exit_code, True
        except KeyboardInterrupt:
            _show(caught, True, debug)
            print("magalign: interrupted; no partial output was kept", file=sys.stderr)
            status, failed = 130, True
        except BrokenPipeError:
            status, failed = 0, False
        if not failed:
            _show(caught, True, debug)
        if old_command is None:
            os.environ.pop("MAGALIGN_COMMAND", None)
        else:
            os.environ["MAGALIGN_COMMAND"] = old_command
    sys.stdout.flush()
    return status


def _show(caught: list[warnings.WarningMessage], show: bool, debug: bool) -> None:
    """Print the warnings a command issued, one line each (with their source under --debug)."""
    if not show:
        return
    for w in caught:
        if debug:
            text = warnings.formatwarning(w.message, w.category, w.filename, w.lineno)
        else:
            text = _format_warning(w.message, w.category, w.filename, w.lineno)
        print(f"magalign: {unsigned_zeros(text.rstrip())}", file=sys.stderr)
    caught.clear()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
