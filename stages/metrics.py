"""The paper's quality metrics of the restored field (Li et al. 2020, Table 4).

More in docs/modules.md, ``stages.metrics``.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core.atomic import atomic_path, write_text_atomic
from pipeline.core.errors import OutputError
from pipeline.core.recording import Segment
from pipeline.model.tang import heading_error_stats as tang_heading_error_stats
from pipeline.model.tang import wrap_angle
from stages.restore import RestoreResult

FORMAT = "magalign.metrics/1"
COMPONENTS = ("x", "y", "z")
STATS = ("fluctuation_range_nT", "absolute_deviation_nT", "std_nT")


def component_stats(v: np.ndarray) -> dict[str, float]:
    """Li 2020 Table 4 statistics of one component series (nT); NaN when empty."""
    v = np.asarray(v, dtype=float)
    if v.size == 0:
        return dict.fromkeys(STATS, float("nan"))
    mean = float(np.mean(v))
    return {
        "fluctuation_range_nT": float(np.max(v) - np.min(v)),
        "absolute_deviation_nT": float(np.mean(np.abs(v - mean))),
        "std_nT": float(np.std(v)),
    }


def _ratio(a: float, b: float) -> float:
    return float(100.0 * a / b) if b > 0 and np.isfinite(a) and np.isfinite(b) else float("nan")


def heading_error_stats(heading_rad: np.ndarray, reference_rad: float) -> dict[str, float]:
    """Tang 2016 Table 2 style heading error statistics (deg) of a restored series.

    The heading of a horizontal field vector is ``atan2(east, north)`` (``heading_rad``); the
    error is it minus the reference field's heading, wrapped to (-180, 180]. The statistics
    are those of :func:`pipeline.model.tang.heading_error_stats`, of which this file keeps
    ``max_abs_deg``, ``mean_deg``, ``std_deg``, ``rms_deg`` and ``peak_to_peak_deg``.
    """
    stats = tang_heading_error_stats(wrap_angle(np.asarray(heading_rad) - reference_rad))
    return {k: stats[k] for k in _HEADING_KEYS}


_HEADING_KEYS = ("max_abs_deg", "mean_deg", "std_deg", "rms_deg", "peak_to_peak_deg")


@dataclass(frozen=True)
class ScopeMetrics:
    """Metrics over one scope (the whole recording or one segment).

    Attributes
    ----------
    scope : str
        ``"all"`` or ``"segment_<i>"``.
    kind : str
        ``"all"`` or the segment kind.
    start_s, end_s : float
        Window, seconds from the first magnetometer sample.
    n_samples : int
    components : dict
        ``{"x": {"calibrated": {...}, "uncalibrated": {...}, "ratio_pct": {...}}, ...}``.

    """

    scope: str
    kind: str
    start_s: float
    end_s: float
    n_samples: int
    components: dict

    def to_dict(self) -> dict[str, Any]:
        """JSON object of this scope."""
        return {
            "scope": self.scope,
            "kind": self.kind,
            "start_s": self.start_s,
            "end_s": self.end_s,
            "n_samples": self.n_samples,
            "components": self.components,
        }


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_nan_to_none(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


@dataclass(frozen=True)
class MetricsResult:
    """Frozen result of the metrics stage (docs/modules.md for the layout)."""

    n_samples: int
    n_without_attitude: int
    n_used: int
    scopes: tuple[ScopeMetrics, ...]
    heading_error: dict | None = None
    extra: dict = field(default_factory=dict)
    #: restored (attitude at ``t - tau``) but without an attitude at the stamp itself, so not
    #: compared with the uncalibrated field: ``n_used + n_without_attitude + this = n_samples``
    n_without_attitude_at_stamp: int = 0

    @property
    def whole(self) -> ScopeMetrics:
        """The ``"all"`` scope."""
        return self.scopes[0]

    def ratio_pct(self, stat: str = "fluctuation_range_nT") -> dict[str, float]:
        """Whole-recording ratio (percent) of ``stat`` per component."""
        return {c: self.whole.components[c]["ratio_pct"][stat] for c in COMPONENTS}

    def to_dict(self) -> dict[str, Any]:
        """Return the metrics.json object; non-finite numbers become null."""
        return _nan_to_none(
            {
                "format": FORMAT,
                "n_samples": self.n_samples,
                "n_without_attitude": self.n_without_attitude,
                "n_used": self.n_used,
                "n_without_attitude_at_stamp": self.n_without_attitude_at_stamp,
                "scopes": [s.to_dict() for s in self.scopes],
                "heading_error": self.heading_error,
            }
        )

    def to_table(self) -> Any:  # a pyarrow.Table
        """metrics.parquet as a pyarrow Table (docs/modules.md for the columns)."""
        cols: dict[str, list] = {
            k: []
            for k in (
                "scope", "kind", "start_s", "end_s", "n_samples", "component", "calibrated",
                *STATS, "ratio_pct", "ratio_absolute_deviation_pct", "ratio_std_pct",
            )
        }
        for s in self.scopes:
            for c in COMPONENTS:
                comp = s.components[c]
                for calibrated in (True, False):
                    st = comp["calibrated" if calibrated else "uncalibrated"]
                    cols["scope"].append(s.scope)
                    cols["kind"].append(s.kind)
                    cols["start_s"].append(s.start_s)
                    cols["end_s"].append(s.end_s)
                    cols["n_samples"].append(s.n_samples)
                    cols["component"].append(c)
                    cols["calibrated"].append(calibrated)
                    for k in STATS:
                        cols[k].append(st[k])
                    cols["ratio_pct"].append(comp["ratio_pct"]["fluctuation_range_nT"])
                    cols["ratio_absolute_deviation_pct"].append(
                        comp["ratio_pct"]["absolute_deviation_nT"]
                    )
                    cols["ratio_std_pct"].append(comp["ratio_pct"]["std_nT"])
        schema = pa.schema(
            [
                ("scope", pa.string()), ("kind", pa.string()), ("start_s", pa.float64()),
                ("end_s", pa.float64()), ("n_samples", pa.int64()), ("component", pa.string()),
                ("calibrated", pa.bool_()),
                *[(k, pa.float64()) for k in STATS],
                ("ratio_pct", pa.float64()), ("ratio_absolute_deviation_pct", pa.float64()),
                ("ratio_std_pct", pa.float64()),
            ]
        )
        return pa.table(cols, schema=schema)

    def write(self, out_dir: str | Path, inputs: tuple[str, ...] = ()) -> tuple[Path, Path]:
        """Write metrics.json and metrics.parquet atomically into ``out_dir``."""
        out = Path(out_dir)
        j = write_text_atomic(out / "metrics.json", json.dumps(self.to_dict(), indent=2))
        pq_path = out / "metrics.parquet"
        with atomic_path(pq_path, inputs) as tmp:
            pq.write_table(self.to_table(), tmp)
        return j, pq_path


class _Moments:
    """Per scope: count, minimum, maximum, mean and centred sum of squares, mergeable.

    Arrays of shape (S, 3) for S scopes. Chunks are merged with the pairwise update of
    Chan, Golub & LeVeque (1979), so the standard deviation of hours of ~50,000 nT readings
    loses nothing to cancellation.
    """

    def __init__(self, scopes: int) -> None:
        self.n = np.zeros(scopes, dtype=np.int64)
        self.lo = np.full((scopes, 3), np.inf)
        self.hi = np.full((scopes, 3), -np.inf)
        self.mean = np.zeros((scopes, 3))
        self.m2 = np.zeros((scopes, 3))

    def add(self, v: np.ndarray, sel: list[Any]) -> None:
        """Merge the rows ``v`` (N, 3) of each scope (``sel``: None, slice or mask)."""
        if not len(v):
            return
        ref = v.mean(axis=0)  # centring: squares of deviations, not of ~50,000 nT
        d = v - ref
        k = np.zeros(len(sel), dtype=np.int64)
        sm = np.zeros((len(sel), 3))
        sq = np.zeros((len(sel), 3))
        lo = np.full((len(sel), 3), np.inf)
        hi = np.full((len(sel), 3), -np.inf)
        slices = [(i, x) for i, x in enumerate(sel) if isinstance(x, slice) and x.stop > x.start]
        if slices:
            idx = np.array([[x.start, x.stop] for _, x in slices]).ravel()
            ends = idx[1::2] == len(v)
            idx = np.minimum(idx, len(v) - 1)  # reduceat: a start of len(v) is not allowed
            which = np.array([i for i, _ in slices])
            for arr, out, op in ((d, sm, np.add), (d * d, sq, np.add), (v, lo, np.minimum),
                                 (v, hi, np.maximum)):
                r = op.reduceat(arr, idx, axis=0)[::2]
                # reduceat stops one row short where a slice ends at the last row
                last = ends & (idx[::2] < len(v) - 1)
                if last.any():
                    r[last] = op(r[last], arr[-1])
                out[which] = r
            k[which] = [x.stop - x.start for _, x in slices]
        for i, x in enumerate(sel):
            if x is None or not isinstance(x, slice):
                w = d if x is None else d[x]
                if len(w):
                    vv = v if x is None else v[x]
                    k[i], sm[i], sq[i] = len(w), w.sum(axis=0), (w * w).sum(axis=0)
                    lo[i], hi[i] = vv.min(axis=0), vv.max(axis=0)
        has = k > 0
        if not has.any():
            return
        kk = np.where(has, k, 1)[:, None]
        mb = sm / kk  # chunk mean of each scope, relative to ref
        m2b = sq - kk * mb * mb
        n = self.n[:, None] + k[:, None]
        nn = np.where(n > 0, n, 1)
        delta = (mb + ref) - self.mean
        upd = has[:, None]
        self.mean = np.where(upd, self.mean + delta * (k[:, None] / nn), self.mean)
        self.m2 = np.where(upd, self.m2 + m2b + delta * delta * (self.n[:, None] * k[:, None]
                                                              / nn), self.m2)
        self.n = self.n + k
        self.lo = np.minimum(self.lo, lo)
        self.hi = np.maximum(self.hi, hi)


class MetricsAccumulator:
    """The metrics of a recording, computed chunk by chunk (docs/modules.md).

    Feed every chunk's :class:`stages.restore.RestoreResult` in time order (:meth:`add`),
    then :meth:`finish` (a recording held whole is one chunk). Range, mean and standard
    deviation are merged from per-chunk moments; the mean absolute deviation needs the final
    mean, so the rows used (stamp, calibrated and uncalibrated ENU) are spilled to an
    anonymous temporary file in ``spill_dir`` (56 bytes per sample, gone when the
    accumulator is) and read back block by block. Same definitions as
    :func:`component_stats`.

    Parameters
    ----------
    segments : tuple of Segment, optional
        Windows of the per-segment scopes.
    t0_ns : int
        First magnetometer stamp of the recording.
    spill_dir : path, optional
        Folder of the temporary file (default: the system's).
    heading_reference_enu_nT : ndarray (3,), optional
        The reference field of a turntable recording: Tang's heading errors are added.

    """

    _ROW = np.dtype([("t", "<i8"), ("c", "<f8", (3,)), ("r", "<f8", (3,))])
    _BLOCK = 262_144

    def __init__(self, segments: tuple[Segment, ...] | None, t0_ns: int,
                 spill_dir: str | Path | None = None,
                 heading_reference_enu_nT: np.ndarray | None = None) -> None:
        self.heading_B = (None if heading_reference_enu_nT is None
                          else np.asarray(heading_reference_enu_nT, dtype=float))
        self.segments = tuple(segments or ())
        self.t0_ns = int(t0_ns)
        self.t_last_ns = int(t0_ns)
        self._cal = _Moments(1 + len(self.segments))
        self._raw = _Moments(1 + len(self.segments))
        self._starts = np.array([sg.start_ns for sg in self.segments], dtype=np.int64)
        self._ends = np.array([sg.end_ns for sg in self.segments], dtype=np.int64)
        self._spill_dir = str(spill_dir) if spill_dir is not None else tempfile.gettempdir()
        self._spill = tempfile.TemporaryFile(dir=self._spill_dir)
        self.n_samples = 0
        self.n_valid = 0
        self.n_used = 0

    def _masks(self, t: np.ndarray) -> list[Any]:
        """Row selections of each scope: None (all), a slice (sorted stamps) or a mask."""
        if len(t) < 2 or bool(np.all(t[1:] >= t[:-1])):
            # half-open windows (Segment.contains) of sorted stamps: slices
            a = np.searchsorted(t, self._starts, "left")
            b = np.searchsorted(t, self._ends, "left")
            return [None] + [slice(int(i), int(j)) for i, j in zip(a, b, strict=True)]
        return [None] + [sg.contains(t) for sg in self.segments]

    def add(self, rs: RestoreResult) -> None:
        """Take one chunk's restore result."""
        n = len(rs.t_ns)
        if n == 0:
            return
        self.n_samples += n
        self.n_valid += int(np.count_nonzero(rs.valid))
        self.t_last_ns = max(self.t_last_ns, int(rs.t_ns[-1]))
        used = rs.used
        self.n_used += int(np.count_nonzero(used))
        rows = np.empty(int(np.count_nonzero(used)), self._ROW)
        rows["t"] = rs.t_ns[used]
        rows["c"] = np.asarray(rs.enu_nT)[used]
        # Uncalibrated: attitude only, C_enu_body(t) @ y_mag (Li 2020, Table 4 "before").
        rows["r"] = rs.uncalibrated_enu_nT()[used]
        sel = self._masks(rows["t"])
        self._cal.add(rows["c"], sel)
        self._raw.add(rows["r"], sel)
        try:
            rows.tofile(self._spill)
        except OSError as exc:
            raise OutputError(f"cannot keep the restored rows for the metrics: "
                              f"{exc.strerror or exc}", path=self._spill_dir,
                              hint="free some disk space beside the outputs (56 bytes a "
                              "sample) and run again") from exc

    def finish(self) -> MetricsResult:
        """Return the metrics of every sample added (and drop the temporary file)."""
        dev = np.zeros((2, 1 + len(self.segments), 3))
        self._spill.flush()
        self._spill.seek(0)
        # the horizontal field's heading (turntables): calibrated and uncalibrated
        headings: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
        while True:
            rows = np.fromfile(self._spill, self._ROW, count=self._BLOCK)
            if not len(rows):
                break
            if self.heading_B is not None:
                headings[0].append(np.arctan2(rows["c"][:, 0], rows["c"][:, 1]))
                headings[1].append(np.arctan2(rows["r"][:, 0], rows["r"][:, 1]))
            for i, m in enumerate(self._masks(rows["t"])):
                for j, (name, mo) in enumerate((("c", self._cal), ("r", self._raw))):
                    v = rows[name] if m is None else rows[name][m]
                    if len(v):
                        dev[j, i] += np.abs(v - mo.mean[i]).sum(axis=0)
        self._spill.close()

        def stats(mo: _Moments, d: np.ndarray, i: int, k: int) -> dict[str, float]:
            if mo.n[i] == 0:
                return dict.fromkeys(STATS, float("nan"))
            return {"fluctuation_range_nT": float(mo.hi[i, k] - mo.lo[i, k]),
                    "absolute_deviation_nT": float(d[i, k] / mo.n[i]),
                    "std_nT": float(np.sqrt(max(mo.m2[i, k], 0.0) / mo.n[i]))}

        def components(i: int) -> dict[str, dict]:
            out: dict[str, dict] = {}
            for k, c in enumerate(COMPONENTS):
                sc, su = stats(self._cal, dev[0], i, k), stats(self._raw, dev[1], i, k)
                out[c] = {"calibrated": sc, "uncalibrated": su,
                          "ratio_pct": {s: _ratio(sc[s], su[s]) for s in STATS}}
            return out

        t0 = self.t0_ns
        scopes = [ScopeMetrics("all", "all", 0.0, float((self.t_last_ns - t0) * 1e-9),
                               int(self._cal.n[0]), components(0))]
        for i, seg in enumerate(self.segments):
            scopes.append(ScopeMetrics(
                f"segment_{i}", str(getattr(seg.kind, "value", seg.kind)),
                float((seg.start_ns - t0) * 1e-9), float((seg.end_ns - t0) * 1e-9),
                int(self._cal.n[i + 1]), components(i + 1)))
        heading = None
        if self.heading_B is not None:
            ref = np.arctan2(self.heading_B[0], self.heading_B[1])
            heading = {name: heading_error_stats(
                np.concatenate(h) if h else np.zeros(0), ref)
                for name, h in zip(("calibrated", "uncalibrated"), headings, strict=True)}
        return MetricsResult(
            n_samples=self.n_samples,
            n_without_attitude=self.n_samples - self.n_valid,
            n_used=self.n_used,
            n_without_attitude_at_stamp=self.n_valid - self.n_used,
            scopes=tuple(scopes),
            heading_error=heading,
        )


def compute_metrics(restored: RestoreResult, segments: tuple[Segment, ...] | None = None, *,
                    t0_ns: int | None = None,
                    heading_reference_enu_nT: np.ndarray | None = None) -> MetricsResult:
    """Return the metrics of a restore result held whole (one chunk of the accumulator).

    ``t0_ns``: the recording's first magnetometer stamp (default: the first row's).
    """
    t0 = int(restored.t_ns[0]) if t0_ns is None and len(restored.t_ns) else int(t0_ns or 0)
    acc = MetricsAccumulator(segments, t0, heading_reference_enu_nT=heading_reference_enu_nT)
    acc.add(restored)
    return acc.finish()
