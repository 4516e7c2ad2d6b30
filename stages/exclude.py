"""Stages: leave out of the analysis the stretches a user knows are bad (``--exclude``).

More in docs/modules.md, ``stages.exclude``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import ClassVar

import numpy as np

from pipeline.core.errors import DataQualityError
from pipeline.model.calibration import Calibration
from stages.context import Context

_SECONDS = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*:\s*([0-9]+(?:\.[0-9]*)?)\s*$")
_ISO = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d+)?(?:Z|[+-]\d\d:\d\d)"
_UTC = re.compile(rf"^\s*({_ISO})\s*:\s*({_ISO})\s*$")


@dataclass(frozen=True)
class ExcludeWindow:
    """One stretch left out of the analysis, half-open ``[start, end)``.

    Attributes
    ----------
    start, end : float
        Seconds from the first magnetometer sample, or (``utc``) seconds since the Unix
        epoch.
    utc : bool

    """

    start: float
    end: float
    utc: bool = False

    @classmethod
    def parse(cls, text: str) -> ExcludeWindow:
        """Read ``START:END`` (seconds, or two ISO 8601 UTC times); ValueError says why."""
        m = _SECONDS.match(text)
        if m:
            a, b, utc = float(m.group(1)), float(m.group(2)), False
        else:
            m = _UTC.match(text)
            if not m:
                raise ValueError(f"{text!r} is not START:END in seconds from the first "
                                 "magnetometer sample (12.5:30) or in UTC "
                                 "(2026-11-20T10:03:00Z:2026-11-20T10:04:30Z)")
            a, b = (datetime.fromisoformat(g.replace("Z", "+00:00")).timestamp()
                    for g in m.groups())
            utc = True
        if not b > a:
            raise ValueError(f"{text!r}: the end must come after the start")
        return cls(a, b, utc)

    def ns(self, t0_ns: int) -> tuple[int, int]:
        """Return the window in ns since the Unix epoch, given the first magnetometer stamp."""
        if self.utc:
            return int(round(self.start * 1e9)), int(round(self.end * 1e9))
        return t0_ns + int(round(self.start * 1e9)), t0_ns + int(round(self.end * 1e9))

    def seconds(self, t0_ns: int) -> list[float]:
        """Return ``[start, end]`` in seconds from the first magnetometer sample."""
        a, b = self.ns(t0_ns)
        return [(a - t0_ns) * 1e-9, (b - t0_ns) * 1e-9]

    def text(self) -> str:
        """Return the window as the command line spells it."""
        if not self.utc:
            return f"{self.start:g}:{self.end:g}"
        a, b = (datetime.fromtimestamp(x, tz=timezone.utc).isoformat().replace("+00:00", "Z")
                for x in (self.start, self.end))
        return f"{a}:{b}"


def excluded_mask(t_ns: np.ndarray, windows: tuple[ExcludeWindow, ...], t0_ns: int
                  ) -> np.ndarray:
    """Return the rows of ``t_ns`` inside any window, (N,) bool."""
    t = np.asarray(t_ns, dtype=np.int64)
    out = np.zeros(len(t), dtype=bool)
    for w in windows:
        a, b = w.ns(t0_ns)
        out |= (t >= a) & (t < b)
    return out


@dataclass(frozen=True)
class Exclude:
    """Stage: drop the aligned samples inside the windows (docs/modules.md).

    Parameters
    ----------
    windows : tuple of ExcludeWindow
    t0_ns : int or None
        The recording's first magnetometer stamp (windows in seconds count from it); None:
        that of the context's recording (a long recording's analysis windows start later).

    """

    windows: tuple[ExcludeWindow, ...]
    t0_ns: int | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"aligned"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` whose aligned samples leave the windows out."""
        rec, al = ctx.need_recording(), ctx.need_aligned()
        t0 = int(rec.mag.t_ns[0]) if self.t0_ns is None else int(self.t0_ns)
        out = excluded_mask(al.t_ns, self.windows, t0)
        if out.all():
            raise DataQualityError(
                "--exclude leaves no sample to analyse", path=rec.path,
                hint="the windows cover the whole recording; exclude less")
        return ctx.replace(aligned=al.select(~out))


@dataclass(frozen=True)
class NoteExclusions:
    """Stage: say in the calibration which stretches were left out and how many samples.

    Adds ``checks["excluded_windows_s"]`` (``[[start, end], ...]``, seconds from the first
    magnetometer sample) and ``checks["excluded_samples"]``, and a warning in words.

    Parameters
    ----------
    windows : tuple of ExcludeWindow
    t0_ns : int or None
        The recording's first magnetometer stamp; None: that of the context's recording.
    n_samples : int or None
        The recording's samples inside the windows; None: counted in the context's recording
        (a long recording's analysis sees windows of it: the runner counts them).

    """

    windows: tuple[ExcludeWindow, ...]
    t0_ns: int | None = None
    n_samples: int | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with the exclusions noted in its calibration."""
        rec = ctx.need_recording()
        t0 = int(rec.mag.t_ns[0]) if self.t0_ns is None else int(self.t0_ns)
        n = (int(np.count_nonzero(excluded_mask(rec.mag.t_ns, self.windows, t0)))
             if self.n_samples is None else int(self.n_samples))
        return ctx.replace(calibration=noted(ctx.need_calibration(), self.windows, t0, n))


def noted(cal: Calibration, windows: tuple[ExcludeWindow, ...], t0_ns: int,
          n_samples: int) -> Calibration:
    """Return ``cal`` saying which stretches were left out (:class:`NoteExclusions`)."""
    spans = [w.seconds(t0_ns) for w in windows]
    words = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in spans)
    note = (f"left out of the fit and the verdict as asked (--exclude): {words} "
            f"({n_samples} magnetometer samples); restored and measured like the rest")
    return cal.replace(
        checks={**cal.checks, "excluded_windows_s": spans, "excluded_samples": n_samples},
        warnings=tuple(dict.fromkeys(cal.warnings + (note,))))
