"""Numbers inside sentences a person reads: true minus signs, vectors with sigmas, gradients.

The report's sentences and each effect's own sentence (``Effect.sentence``) write their
numbers through these, so a value reads the same wherever it appears.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.core.style import minus


def num(x: float, nd: int = 1) -> str:
    """Return a number with ``nd`` decimals and a true minus sign."""
    return minus(f"{x:.{nd}f}")


def sig2_decimals(x: float) -> int:
    """Return the decimals that show ``x`` to two significant digits: 2 to 6, 2 unless ``x > 0``.

    A sigma or a small disagreement then never reads "0.00" (0.35, 0.0082, 0.0044).
    """
    x = float(x)
    if not (np.isfinite(x) and x > 0):
        return 2
    return int(min(max(2, 1 - np.floor(np.log10(x))), 6))


def sig2(x: float) -> str:
    """Return ``x`` to two significant digits in fixed notation (:func:`sig2_decimals`)."""
    return f"{x:.{sig2_decimals(x)}f}"


def vec(a: Any, nd: int = 1) -> str:
    """Return ``[1.0, −2.0, 3.0]``."""
    return "[" + ", ".join(num(float(x), nd) for x in np.asarray(a, float).ravel()) + "]"


def pm_vec(a: Any, s: Any, nd: int = 1) -> str:
    """Return ``[1.0 ± 0.1, ...]`` (``±`` omitted where the sigma is missing)."""
    a = np.asarray(a, float).ravel()
    s = np.asarray(s if s is not None else np.full(a.shape, np.nan), float).ravel()
    parts = [num(x, nd) + (f" \u00b1 {sx:.{nd}f}" if np.isfinite(sx) else "")
             for x, sx in zip(a, s, strict=False)]
    return "[" + ", ".join(parts) + "]"


def per_metre(g_nT_per_m: float) -> str:
    """Return a field gradient in the unit that shows its value: ``3.47 µT/m``, ``2.0 nT/m``.

    Microtesla per metre from 1 µT/m up, nanotesla per metre below (a gradient of 2 nT/m
    must not read "0.00 µT/m").
    """
    g = abs(float(g_nT_per_m))
    if not np.isfinite(g):
        return "an unknown amount per metre"
    if g >= 1000.0:
        return f"{g / 1e3:.2f} \u00b5T/m"
    return f"{g:.0f} nT/m" if g >= 10.0 else f"{g:.1f} nT/m"
