"""One colour scheme and type style for every figure: report, diagnosis and rerun.

More in docs/modules.md, ``pipeline.core.style``.
"""

from __future__ import annotations

import io
import math
import os
import re
import sys
import textwrap
from typing import Any

#: x / east, y / north, z / up
AXIS = ("#d62728", "#2ca02c", "#1f77b4")
#: heading, pitch, roll: the colour of the axis each turns about (z, x, y)
ANGLE = {"heading": AXIS[2], "pitch": AXIS[0], "roll": AXIS[1]}
BEFORE = "#e69f00"
AFTER = "#5b2a86"
REFERENCE = "#000000"
#: diagnosis windows (a disturbance, a magnet near the sensor)
EVENT = "#e8a0a0"
#: the edge of a diagnosis window (a narrow window stays visible at the scale of hours)
EVENT_EDGE = "#c0392b"
#: motion segment shading by kind (pipeline.core.recording.SegmentKind values)
SEGMENT = {
    "rotation": "#d9d9d9",
    "static": "#ecebe0",
    "manoeuvre": "#d9e2ec",
    "line": "#e6e6e6",
    "turn": "#cfcfcf",
}
SEGMENT_OTHER = "#e6e6e6"


def rgb(hex_colour: str) -> tuple[int, int, int]:
    """Return ``"#rrggbb"`` as an ``(r, g, b)`` tuple of 0..255 (for rerun)."""
    h = hex_colour.lstrip("#")
    return (int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16))


def segment_colour(kind: Any) -> str:
    """Return the shading colour of a segment kind (enum or its value)."""
    return SEGMENT.get(str(getattr(kind, "value", kind)), SEGMENT_OTHER)


def rc() -> dict[Any, Any]:
    """Return matplotlib rc settings for every magalign figure.

    Fonts of 10 pt and more (figures are embedded at about their size in inches at 100 %
    zoom), a true minus sign in tick labels, light grids.
    """
    return {
        "font.size": 11,
        "axes.titlesize": 12,
        "axes.labelsize": 11,
        "xtick.labelsize": 10,
        "ytick.labelsize": 10,
        "legend.fontsize": 10,
        "legend.framealpha": 0.9,
        "axes.unicode_minus": True,
        "axes.grid": True,
        "grid.alpha": 0.3,
        "figure.dpi": 100,
        "savefig.dpi": 100,
    }


def num(x: Any, spec: str = "") -> str:
    """Format the number ``x`` with ``spec`` (as ``format(x, spec)``), never as a negative zero.

    A value that rounds to zero at the shown precision is written as zero: ``-1e-12`` and
    ``-0.004`` at ``.2f`` are ``0.00`` (``+0.00`` with ``+.2f``), not ``-0.00``. Whether a sum
    of floats ends a hair below or above zero depends on the numerics of the build (SIMD
    paths, summation order); the number a person reads must not.
    """
    text = format(x, spec)
    try:
        finite = math.isfinite(float(x))
    except (TypeError, ValueError):
        return text
    if finite and text.lstrip().startswith("-") and _all_zero(text):
        return format(0.0, spec)
    return text


def nT_text(x: Any) -> str:
    """Format a field error or noise, nT, at the precision a reader compares it with.

    One decimal below 10 nT (a lab's residual of 0.5 nT against a noise of 0.4 nT is not "1
    nT vs 0 nT"), whole nanoteslas above; the unit is the caller's.
    """
    return num(x, ".1f" if abs(float(x)) < 10.0 else ".0f")


def _all_zero(text: str) -> bool:
    """Tell whether the digits of a formatted number's mantissa are all zero."""
    mantissa = re.split(r"[eE]", text, maxsplit=1)[0]
    return re.search(r"[1-9]", mantissa) is None


#: a negative zero in text: a minus (hyphen or U+2212) then a number whose digits are all
#: zero, standing alone (not part of a word, a date, ``+-`` or a longer number)
NEGATIVE_ZERO = re.compile(r"(?<![\w.+\-\u2212\u00b1])[-\u2212](?=(?:0+(?:\.0*)?|\.0+)(?![\w.]))")


def unsigned_zeros(text: str) -> str:
    """Return ``text`` without the minus of any negative zero (``-0``, ``-0.00``, ``[-0.0,``).

    For text put together elsewhere with its own number formats (a check's doubt, a
    finding's explanation): every line a person reads passes through here or :func:`num`.
    """
    return NEGATIVE_ZERO.sub("", text)


def unsigned_zeros_in(obj: Any) -> Any:
    """Return ``obj`` (JSON-like) with every string passed through :func:`unsigned_zeros`.

    Numbers and keys are left as they are: the words of a result file (a verdict's reason,
    a warning, a finding's explanation) are what a person reads.
    """
    if isinstance(obj, str):
        return unsigned_zeros(obj)
    if isinstance(obj, dict):
        return {k: unsigned_zeros_in(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [unsigned_zeros_in(v) for v in obj]
    return obj


def minus(text: str) -> str:
    """Return ``text`` with a true minus sign (U+2212) for a hyphen before a digit.

    ``+-`` (plus-minus written in ASCII) becomes ``±``; a negative zero loses its sign.
    """
    text = unsigned_zeros(text).replace("+-", "\u00b1")
    out = []
    for i, ch in enumerate(text):
        nxt = text[i + 1] if i + 1 < len(text) else ""
        prev = text[i - 1] if i else " "
        if ch == "-" and nxt.isdigit() and not (prev.isalnum() or prev in ".)"):
            out.append("\u2212")
        else:
            out.append(ch)
    return "".join(out)


def pyplot() -> Any:
    """Return ``matplotlib.pyplot`` on the Agg backend (files only, no screen).

    The one place that selects the backend: it must be chosen before pyplot is imported.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png(fig: Any) -> bytes:
    """Return the figure as PNG bytes and close it; no text on it shows a negative zero.

    Titles, labels, legends and notes are put together from numbers formatted where each
    figure is drawn; they pass :func:`unsigned_zeros` here, once for every figure.
    """
    from matplotlib.text import Text

    for t in fig.findobj(Text):
        text = t.get_text()
        if isinstance(text, str) and unsigned_zeros(text) != text:
            t.set_text(unsigned_zeros(text))
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    pyplot().close(fig)
    return buf.getvalue()


#: columns of a terminal whose width is unknown (output to a file or a pipe)
DEFAULT_COLUMNS = 80


def terminal_width() -> int:
    """Return the columns a printed line may use: the terminal's, 80 when unknown.

    ``COLUMNS`` in the environment decides when set (as for every terminal program); then
    the terminal standard output is; else (a file, a pipe) :data:`DEFAULT_COLUMNS`. A width
    under 40 columns is taken as a mistake and replaced by the default.
    """
    cols = 0
    env = os.environ.get("COLUMNS", "").strip()
    if env.isdigit():
        cols = int(env)
    else:
        try:
            if sys.stdout is not None and sys.stdout.isatty():
                cols = os.get_terminal_size(sys.stdout.fileno()).columns
        except (OSError, ValueError, AttributeError):
            cols = 0
    return cols if cols >= 40 else DEFAULT_COLUMNS


def wrap(text: str, first: str = "", rest: str = "", width: int | None = None) -> list[str]:
    """Return ``text`` as lines of at most ``width`` columns (the terminal's by default).

    Lines break between words only: a number, a path or a word is never cut (one longer
    than the line stands on a line of its own). A no-break space (U+00A0) holds two words
    on one line (a value and its sigma) and is printed as a space.
    """
    w = terminal_width() if width is None else int(width)
    lines = textwrap.wrap(text, w, initial_indent=first, subsequent_indent=rest,
                          break_on_hyphens=False, break_long_words=False) or [first.rstrip()]
    return [line.replace(GLUE, " ") for line in lines]


#: a space that :func:`wrap` does not break at (a value and its sigma stay on one line)
GLUE = "\u00a0"
