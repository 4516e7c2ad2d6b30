"""Give freed heap memory back to the operating system between the steps of a long run.

Reading a long recording allocates and frees many arrays of a few kB to a few hundred kB
(one per MCAP chunk and channel); glibc keeps the freed pages in its heap, so the resident
size of a two-pass ``process`` grew with the file although nothing held the arrays
(113 MB after scanning a 10-hour file's indexes). :func:`release_free_memory` asks the C
library to return them (``malloc_trim``); elsewhere it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from typing import Any


@functools.cache
def _libc() -> Any:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        lib = ctypes.CDLL(name)
    except OSError:
        return None
    return lib if hasattr(lib, "malloc_trim") else None


def release_free_memory() -> None:
    """Return the heap's free pages to the operating system (glibc's ``malloc_trim(0)``)."""
    lib = _libc()
    if lib is not None:
        lib.malloc_trim(0)
