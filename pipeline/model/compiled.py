"""Per-sample loops compiled by numba on first use in a process (cached on disk).

The model's hand-written loops (:mod:`pipeline.model.dipole_kernels`,
:mod:`pipeline.model.attitude_kernels`) are plain Python functions; :func:`compiled` returns
each one's compiled form. numba is imported here only, on the first call: a command that
never needs a loop never loads the compiler (about a second in a new process).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

_COMPILED: dict[Callable[..., Any], Any] = {}
_COMPILING = threading.Lock()


def compiled(loop: Callable[..., Any]) -> Any:
    """Return ``loop`` compiled (``numba.njit``, cached on disk, without the GIL).

    A helper thread warming the loops (:func:`pipeline.core.warm.warm_in_background`) and a
    fit may ask at once: the lock builds each dispatcher once.
    """
    hit = _COMPILED.get(loop)
    if hit is not None:
        return hit
    with _COMPILING:
        if loop not in _COMPILED:
            import numba  # pipeline.core.warm.LATE_IMPORTS

            _COMPILED[loop] = numba.njit(cache=True, nogil=True)(loop)
        return _COMPILED[loop]
