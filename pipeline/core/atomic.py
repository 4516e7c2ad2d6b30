"""Outputs appear only when complete: write to a temporary name, then rename.

More in docs/modules.md, ``pipeline.core.atomic``.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from pipeline.core.errors import OutputError


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


#: errors of a full disk or file system (what the writer inside the block may meet)
_NO_SPACE = frozenset({errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS})


def write_hint(exc: OSError) -> str:
    """Return what to do about an output the file system refused (``exc``)."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return "free some disk space (or raise the file size limit) and run again"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return "choose an output folder you can write to"
    return "check the output folder"


PAUSE_DIR_ENV = "MAGALIGN_TEST_PAUSE_DIR"
PAUSE_AT_ENV = "MAGALIGN_TEST_PAUSE_AT"


def _test_event(event: str, dest: Path) -> None:
    """Record an atomic-write event and pause there when asked (docs/modules.md)."""
    folder = os.environ.get(PAUSE_DIR_ENV)
    if not folder:
        return
    line = f"{event} {dest.parent.name}/{dest.name}"
    log = Path(folder) / "events"
    with open(log, "a", encoding="utf-8") as fh:
        fh.write(line + "\n")
    n = len(log.read_text(encoding="utf-8").splitlines())
    flag = Path(folder) / "paused"
    if os.environ.get(PAUSE_AT_ENV) not in (line, str(n)) or flag.exists():
        return
    (Path(folder) / "pid").write_text(f"{os.getpid()}\n", encoding="utf-8")
    flag.with_suffix(".part").write_text(f"{n} {line}\n", encoding="utf-8")
    os.replace(flag.with_suffix(".part"), flag)  # whole when it appears
    while not (Path(folder) / "go").exists():
        time.sleep(0.01)


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
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    except OSError as exc:
        raise OutputError(f"cannot create a file in this folder: {exc.strerror}",
                          path=dest.parent, hint=write_hint(exc)) from exc
    os.close(fd)
    tmp_p = Path(tmp)
    try:
        _test_event("created", dest)
        yield tmp_p
        with open(tmp_p, "rb+") as fh:
            os.fsync(fh.fileno())
        # mkstemp creates 0600; results are shared files, so apply the usual umask instead.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_p, 0o666 & ~umask)
        _test_event("written", dest)
        os.replace(tmp_p, dest)
        _test_event("renamed", dest)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp_p.unlink()
        if isinstance(exc, OSError) and exc.errno in _NO_SPACE:
            raise OutputError(f"cannot write {dest.name}: {exc.strerror}", path=dest.parent,
                              hint=write_hint(exc)) from exc
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


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()
