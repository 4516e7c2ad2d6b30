"""One colour scheme and type style for every figure: report, diagnosis and rerun.

More in docs/modules.md, ``pipeline.core.style``.
"""

from __future__ import annotations

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


def minus(text: str) -> str:
    """Return ``text`` with a true minus sign (U+2212) for a hyphen before a digit.

    ``+-`` (plus-minus written in ASCII) becomes ``±``.
    """
    text = text.replace("+-", "\u00b1")
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
