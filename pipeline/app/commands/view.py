"""``magalign view PATH``: open results in the rerun viewer.

``PATH`` is a ``.rrd`` file, a ``.mcap`` recording (rerun reads MCAP itself) or a results
folder (every ``*.rrd`` under it). The viewer is the ``rerun`` program installed with
rerun-sdk; it needs a display. Without one (no ``DISPLAY`` / ``WAYLAND_DISPLAY`` on Linux)
the command says so in one line and exits with status 2; ``--web`` serves the web viewer
instead (``rerun --serve-web``: open the printed address in a browser), which needs
no display on this machine.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

from pipeline.app.commands._options import check_mcap_file
from pipeline.core.errors import InputError, UsageError

SUFFIXES = (".rrd", ".mcap")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("view", help="open results in the rerun viewer",
                       description="Open results in the rerun viewer: a .rrd file written by "
                       "magalign process, a .mcap recording, or a results folder (every .rrd "
                       "under it). The viewer needs a display; without one, --web serves "
                       "the web viewer, to open in a browser at the address it prints.")
    p.add_argument("path", metavar="PATH",
                   help="a .rrd file, a .mcap recording or a results folder")
    p.add_argument("--web", action="store_true",
                   help="serve the web viewer instead of opening a window")
    p.set_defaults(func=run)


def files_to_view(path: str | Path) -> list[Path]:
    """Return the files ``magalign view`` opens for ``path`` (sorted; .rrd under a folder)."""
    p = Path(path)
    if p.is_dir():
        files = sorted(p.rglob("*.rrd"))
        if not files:
            raise InputError("no .rrd file in this folder", path=p,
                             hint="run magalign process first")
        return files
    if not p.is_file():
        raise InputError("no such file or folder", path=p)
    if p.suffix.lower() not in SUFFIXES:
        raise InputError("not a .rrd or .mcap file", path=p)
    if p.suffix.lower() == ".mcap":
        check_mcap_file(p)
    return [p]


def rerun_program() -> str:
    """Path of the ``rerun`` program (beside this Python first, then on PATH)."""
    here = Path(sys.executable).with_name("rerun")
    if here.exists():
        return str(here)
    found = shutil.which("rerun")
    if found is None:
        raise UsageError("the rerun viewer program is not installed",
                         hint="pip install rerun-sdk==0.41.*")
    return found


def has_display() -> bool:
    """Tell whether a window can be opened (always on macOS and Windows)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def run(args: argparse.Namespace) -> int:
    """Open the viewer on the files of ``args.path``; returns the viewer's exit status."""
    files = files_to_view(args.path)
    if not args.web and not has_display():
        raise UsageError(
            "no display available to open the rerun viewer",
            path=args.path,
            hint="use --web, or run `rerun FILE` on a machine with a display",
        )
    cmd = [rerun_program()]
    if args.web:
        cmd.append("--serve-web")
    cmd += [str(f) for f in files]
    return subprocess.call(cmd)
