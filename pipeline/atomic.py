"""Outputs appear only when complete: write to a temporary name, then rename.

A run killed at any point leaves at most a ``.tmp-*`` file that no reader takes as finished.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .errors import OutputError


def safe_join(root: str | Path, *parts: str) -> Path:
    """Join ``parts`` under ``root`` and refuse any result that escapes ``root``.

    Names from recordings, topics or configuration may contain ``..`` or ``/``; they are
    sanitised to one path component each.
    """
    root_p = Path(root).resolve()
    clean = []
    for p in parts:
        s = "".join(c if (c.isalnum() or c in "._-") else "_" for c in str(p)).strip(".")
        clean.append(s or "_")
    out = root_p.joinpath(*clean).resolve()
    if root_p != out and root_p not in out.parents:
        raise OutputError(f"output path {out} escapes the output folder", path=root_p)
    return out


@contextlib.contextmanager
def atomic_path(dest: str | Path, inputs: tuple[str | Path, ...] = ()) -> Iterator[Path]:
    """Yield a temporary path next to ``dest``; rename it to ``dest`` when the block succeeds.

    Parameters
    ----------
    dest : path
        Final name.
    inputs : tuple of path
        Input files that must never be overwritten; writing over one is refused.

    """
    dest = Path(dest)
    for i in inputs:
        if Path(i).exists() and dest.exists() and os.path.samefile(i, dest):
            raise OutputError("refusing to write over an input file", path=dest)
        if Path(i).resolve() == dest.resolve():
            raise OutputError("refusing to write over an input file", path=dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    os.close(fd)
    tmp_p = Path(tmp)
    try:
        yield tmp_p
        with open(tmp_p, "rb+") as fh:
            os.fsync(fh.fileno())
        # mkstemp creates 0600; results are shared files, so apply the usual umask instead.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_p, 0o666 & ~umask)
        os.replace(tmp_p, dest)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_p.unlink()
        raise


@contextlib.contextmanager
def atomic_open(dest: str | Path, mode: str = "w", **kw) -> Iterator[IO]:
    """Open a temporary file for writing; it becomes ``dest`` only when the block succeeds."""
    with atomic_path(dest) as tmp, open(tmp, mode, **kw) as fh:
        yield fh


def write_text_atomic(dest: str | Path, text: str) -> Path:
    """Write ``text`` to ``dest`` atomically; returns ``dest``."""
    with atomic_open(dest, "w", encoding="utf-8") as fh:
        fh.write(text)
    return Path(dest)
