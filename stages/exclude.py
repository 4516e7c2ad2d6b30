"""Stages: leave out of the analysis the stretches a user knows are bad (``--exclude``).

The windows are the framework's :class:`pipeline.core.vocabulary.ExcludeWindow`. More in
docs/modules.md, ``stages.exclude``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.errors import DataQualityError
from pipeline.core.vocabulary import ExcludeWindow
from pipeline.model.calibration import Calibration
from stages.context import Context


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
        In seconds from the recording's first magnetometer stamp
        (:meth:`~pipeline.core.recording.Recording.origin_ns`: also when the context holds
        a long recording's analysed windows, which start later).

    """

    windows: tuple[ExcludeWindow, ...]

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "aligned"})
    provides: ClassVar[frozenset[str]] = frozenset({"aligned"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` whose aligned samples leave the windows out."""
        rec, al = ctx.need_recording(), ctx.need_aligned()
        out = excluded_mask(al.t_ns, self.windows, rec.origin_ns())
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
        In seconds from the recording's first magnetometer stamp (``origin_ns``).
    n_samples : int or None
        The recording's samples inside the windows; None: counted in the context's recording
        (a long recording's analysis sees windows of it: the runner counts them).

    """

    windows: tuple[ExcludeWindow, ...]
    n_samples: int | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with the exclusions noted in its calibration."""
        rec = ctx.need_recording()
        t0 = rec.origin_ns()
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
