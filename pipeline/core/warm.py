"""The modules imported late, and importing them ahead of their use on a helper thread.

Every other import stands at the top of its module. A process that will need one of these
later and is waiting (on its workers, on reading a file) imports it meanwhile, so that the
step that uses it does not pay for it.
"""

from __future__ import annotations

import importlib
import os
import threading

#: The only modules imported inside functions, where they are first needed: each is slow to
#: import (docs/performance.md) and would cost every command that never uses it. rerun and
#: matplotlib for the outputs that draw; dask and its ``distributed`` only with
#: ``--dask-local`` or ``--scheduler``; ppigrf only with ``--igrf``; ``scipy.interpolate``
#: only to simulate a scenario's field drift; harmonica, verde, xarray, ``scipy.spatial`` and
#: ``scipy.linalg`` only to grid a recording with positions (stages.write_survey), not in the
#: process that plans a campaign; ``scipy.signal``, which loads ``scipy.stats`` (0.4-0.6 s),
#: only to count a located source's approaches and for Li 2020's smoothed tangents; numba
#: only to compile the model's loops (pipeline.model.compiled) in the diagnosis of a recording
#: with positions: the point dipole's and the attitude's.
LATE_IMPORTS = ("rerun", "matplotlib", "dask", "distributed", "ppigrf", "scipy.interpolate",
                "harmonica", "verde", "xarray", "scipy.spatial", "scipy.linalg", "scipy.signal",
                "numba")


def import_quietly(*names: str) -> None:
    """Import modules; a failure is left to the code that uses them to report.

    ``"module:function"`` imports the module and calls the function (no arguments), for
    modules that must be set up before they are imported (matplotlib's backend).
    """
    for name in names:
        mod, _, fn = name.partition(":")
        try:
            m = importlib.import_module(mod)
            if fn:
                getattr(m, fn)()
        except Exception:  # noqa: BLE001 - the code that needs the module raises it properly
            pass


def _warm(names: tuple[str, ...], idle: bool) -> None:
    if idle:
        # Linux schedules threads, and a thread's nice value is its own: at 19 the imports
        # take only cycles the process's other work (or its worker processes) leave idle
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except (AttributeError, OSError):  # not Linux, or not allowed: normal priority
            pass
    import_quietly(*names)


def warm_in_background(*names: str, idle: bool = False) -> threading.Thread | None:
    """Start :func:`import_quietly` of ``names`` on a daemon thread (None when none).

    ``idle``: at the lowest priority, for imports needed only once the CPU-bound work of
    other processes (a campaign's workers) is over. Not for imports this process needs soon:
    its main thread would wait on a starved thread's import lock.
    """
    if not names:
        return None
    th = threading.Thread(target=_warm, args=(names, idle), daemon=True,
                          name="magalign-warm-imports")
    th.start()
    return th
