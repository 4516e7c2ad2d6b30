"""Import modules ahead of their use, on a helper thread.

Importing rerun's SDK takes about a second, matplotlib and pandas about half a second each.
A process that will need them later and is waiting (on its workers, on reading a file)
imports them meanwhile, so that the step that uses them does not pay for it.
"""

from __future__ import annotations

import importlib
import threading


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


def warm_in_background(*names: str) -> threading.Thread | None:
    """Start :func:`import_quietly` of ``names`` on a daemon thread (None when none)."""
    if not names:
        return None
    th = threading.Thread(target=import_quietly, args=names, daemon=True,
                          name="magalign-warm-imports")
    th.start()
    return th
