"""Write ``<stem>.rrd``: a rerun recording with a default blueprint (rerun-sdk 0.41).

More in docs/modules.md, ``stages.write_rerun``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core import style
from pipeline.core.atomic import atomic_path
from pipeline.core.errors import OutputError
from pipeline.core.geometry import quat_to_li2020_euler
from pipeline.core.recording import Recording, Segment
from stages.report import report_map_data
from stages.report_grid import grid_points
from stages.report_map import CMAP, colour_limit
from stages.restore import RestoreResult, restore_samples, view_data

ENU_NAMES = ("east", "north", "up")
AXES = ("x", "y", "z")
# the report's colours (pipeline.style): one scheme for every figure and view
BEFORE_RGB = style.rgb(style.BEFORE)
AFTER_RGB = style.rgb(style.AFTER)
IDEAL_RGB = style.rgb(style.REFERENCE)
AXIS_RGB = tuple(style.rgb(c) for c in style.AXIS)
ANGLE_RGB = {k: style.rgb(c) for k, c in style.ANGLE.items()}
#: rows per send_columns call of a long series: rerun encodes pieces of this size while the
#: next ones are sent (one call per series waits on one encoder; docs/performance.md)
SEND_ROWS = 50_000
#: how long a failed run waits for rerun to write what it holds, s
FLUSH_TIMEOUT_S = 5.0
#: rerun streams whose file writer stopped (RrdStream.__exit__)
_STOPPED_STREAMS: list[Any] = []
#: length of the unit field arrows against the body axes (length 1) in the 3D view
FIELD_ARROW = 1.5


def rrd_path(out_dir: str | Path, recording_path: str | Path) -> Path:
    """``out_dir / <stem>.rrd``."""
    return Path(out_dir) / f"{Path(recording_path).stem}.rrd"


def _decimate(n: int, max_points: int) -> np.ndarray:
    step = max(1, int(np.ceil(n / max_points))) if max_points > 0 else 1
    return np.arange(0, n, step)


def blueprint() -> Any:
    """Return the default layout: Figs. 5/8 on top, residuals/attitude/segments, 3D views beside."""
    import rerun.blueprint as rrb

    enu_row = rrb.Horizontal(
        *[
            rrb.TimeSeriesView(
                name=f"{c} component, before and after (nT)",
                origin="/field",
                contents=[f"/field/uncalibrated/{c}", f"/field/calibrated/{c}"],
            )
            for c in ENU_NAMES
        ]
    )
    lower = rrb.Horizontal(
        rrb.TimeSeriesView(name="residual, mag frame (nT)", origin="/residual"),
        rrb.TimeSeriesView(name="attitude (deg)", origin="/attitude"),
        rrb.Vertical(
            rrb.StateTimelineView(name="segments and diagnosis events",
                                  contents=["/segments/spans", "/diagnosis/events"]),
            rrb.TextLogView(name="segments and diagnosis", contents=["/segments/log",
                                                                     "/diagnosis/log"]),
        ),
    )
    spatial = rrb.Vertical(
        rrb.Spatial3DView(name="body and field (ENU): field before / after / reference",
                          origin="/world"),
        rrb.Spatial3DView(name="field in body frame: before / after / ideal (nT)",
                          origin="/trajectory"),
        rrb.Spatial3DView(name="path (m) coloured by restored |B| minus its median",
                          origin="/map"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(enu_row, lower, row_shares=[3, 2]), spatial,
                       column_shares=[3, 1]),
        collapse_panels=True,
    )


def spans(items: list[tuple[int, int, str]]) -> list[tuple[int, str | None]]:
    """Return the state changes of labelled spans ``(start_ns, end_ns, label)``.

    ``(t_ns, label)`` at each start, ``(t_ns, None)`` at an end where no other span starts
    (a gap in the lane).
    """
    out: list[tuple[int, str | None]] = []
    items = sorted(items)
    for i, (a, b, lab) in enumerate(items):
        if out and out[-1][0] == a and out[-1][1] is None:
            out.pop()  # the previous span ends where this one starts
        out.append((int(a), lab))
        nxt = items[i + 1][0] if i + 1 < len(items) else None
        if nxt is None or nxt > b:
            out.append((int(b), None))
    return out


def _log_spans(rec: Any, entity: str, items: list[tuple[int, int, str]],
               colours: dict[str, tuple[int, int, int]]) -> None:
    """Log labelled spans as state changes (rerun's state timeline shows them as lanes)."""
    import rerun as rr

    if not items:
        return
    labels = sorted({lab for _, _, lab in items})
    rec.log(entity, rr.StateConfiguration(
        values=labels, labels=labels,
        colors=[colours.get(lab.split(": ", 1)[-1].split(" ")[0], (150, 150, 150))
                for lab in labels]), static=True)
    for t, lab in spans(items):
        rec.set_time("time", timestamp=np.datetime64(int(t), "ns"))
        if lab is None:
            rec.log(entity, rr.StateChange.cleared())
        else:
            rec.log(entity, rr.StateChange(state=lab))
    rec.reset_time()


class RrdStream:
    """The rerun recording written chunk by chunk (docs/modules.md for the entities).

    Use as a context manager: :meth:`add` sends the time series of the next magnetometer
    samples (a chunk's :class:`stages.restore.RestoreResult`, in time order), :meth:`finish`
    the 3D views (from a sample of the rows: all of them, or every k-th of a long
    recording), the segments and the diagnosis, and leaving the block flushes rerun and
    renames the file into place (left by an exception, no file appears).

    Parameters
    ----------
    recording : Recording
        Its path names the recording (its series are not used).
    calibration : Calibration
    dest : path
        ``<stem>.rrd``; never the input.

    """

    def __init__(self, recording: Recording, calibration: Any, dest: str | Path) -> None:
        self.recording = recording
        self.calibration = calibration
        self.dest = Path(dest)
        self._atomic: Any = None
        self.rec: Any = None
        self._sent = False

    def __enter__(self) -> RrdStream:
        # rerun's own log lines (several per failure) would break the one-line answer; a
        # failed write is reported by magalign itself (OutputError below)
        os.environ.setdefault("RUST_LOG", "off")
        import rerun as rr

        self._atomic = atomic_path(self.dest, (self.recording.path,))
        tmp = self._atomic.__enter__()
        try:
            os.unlink(tmp)  # rerun creates the file itself
            stem = Path(self.recording.path).stem
            rec = rr.RecordingStream("magalign", recording_id=f"magalign-{stem}")
            rec.save(str(tmp), default_blueprint=blueprint())
            rec.send_recording_name(stem)
            self.rec = rec
            self._styles(rr)
        except BaseException as exc:
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            try:
                self.rec.flush()
                self.rec.disconnect()
            except RuntimeError as err:  # rerun's file writer stopped (disk full, ...)
                e = OutputError(f"cannot write the rerun recording: {err}", path=self.dest,
                                hint="free some disk space and run again")
                self._atomic.__exit__(OutputError, e, None)
                raise e from err
        elif self.rec is not None:
            # a run that failed: rerun blocks for good dropping a stream whose file writer
            # stopped (a full disk), so such a stream is kept until the process ends
            try:
                self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
                self.rec.disconnect()
            except RuntimeError:
                _STOPPED_STREAMS.append(self.rec)
        self.rec = None
        self._atomic.__exit__(exc_type, exc, tb)

    def _styles(self, rr: Any) -> None:
        rec = self.rec
        for c in ENU_NAMES:
            rec.log(f"field/calibrated/{c}",
                    rr.SeriesLines(colors=[AFTER_RGB], names=[f"{c} calibrated"]), static=True)
            rec.log(f"field/uncalibrated/{c}",
                    rr.SeriesLines(colors=[BEFORE_RGB], names=[f"{c} uncalibrated"]),
                    static=True)
        for k, a in enumerate(AXES):
            rec.log(f"residual/{a}", rr.SeriesLines(colors=[AXIS_RGB[k]], names=[f"residual {a}"]),
                    static=True)
            rec.log(f"mag/raw/{a}", rr.SeriesLines(colors=[AXIS_RGB[k]], names=[f"raw {a}"]),
                    static=True)
        for name in ("heading", "pitch", "roll"):
            rec.log(f"attitude/{name}_deg", rr.SeriesLines(colors=[ANGLE_RGB[name]],
                                                           names=[f"{name} (deg)"]), static=True)

    def add(self, restored: RestoreResult) -> None:
        """Send the time series of the restore result ``restored`` (the next samples)."""
        import rerun as rr

        rec = self.rec
        if self._sent:
            # rerun encodes on its own thread and queues what it has not written yet: wait
            # for the previous rows (encoded meanwhile) so that a long recording's backlog
            # stays one range (~100 MB at 200k rows), however busy the machine
            rec.flush()
        self._sent = True
        t_all = np.asarray(restored.t_ns, dtype="datetime64[ns]")
        v = restored.valid

        def send_scalars(ent: str, values: np.ndarray, mask: np.ndarray | None = None) -> None:
            """One Scalars series, sent in pieces of SEND_ROWS rows (no Python object per row)."""
            t = t_all
            if mask is not None and not bool(mask.all()):
                t, values = t_all[mask], values[mask]
            for a in range(0, len(t), SEND_ROWS):
                rec.send_columns(ent,
                                 indexes=[rr.TimeColumn("time", timestamp=t[a:a + SEND_ROWS])],
                                 columns=rr.Scalars.columns(scalars=values[a:a + SEND_ROWS]))

        # The series the restore result holds go first: rerun encodes them on its own
        # thread while the view series are computed.
        # --- Li 2020 Figs. 5 and 8: ENU components after calibration, then before
        enu = np.asarray(restored.enu_nT)
        for k, c in enumerate(ENU_NAMES):
            send_scalars(f"field/calibrated/{c}", enu[:, k], np.isfinite(enu[:, k]))
        # --- residuals and raw magnetometer, mag frame
        raw = np.asarray(restored.raw_mag_nT, dtype=float)
        for k, a in enumerate(AXES):
            send_scalars(f"residual/{a}", np.asarray(restored.residual_nT)[:, k], v)
            send_scalars(f"mag/raw/{a}", raw[:, k])
        # the view series of these rows (view_data's; the body-frame ones only the 3D views
        # at the end need)
        unc = restored.uncalibrated_enu_nT()
        for k, c in enumerate(ENU_NAMES):
            send_scalars(f"field/uncalibrated/{c}", unc[:, k], np.isfinite(unc[:, k]))
        # --- attitude: Li 2020 Euler angles
        h, p, r = quat_to_li2020_euler(restored.q_or_identity())  # identity where not valid
        for name, ang in (("heading", h), ("pitch", p), ("roll", r)):
            send_scalars(f"attitude/{name}_deg", np.degrees(ang), v)

    def finish(self, sample: RestoreResult, *, segments: tuple[Segment, ...] | None = None,
               diagnosis: Any = None, max_points: int = 20000) -> None:
        """Send the 3D views (from ``sample``, a restore result), segments and diagnosis."""
        import rerun as rr

        rec = self.rec
        # The views show at most max_points rows each: view_data computes the body-frame
        # series only for max_points rows spread evenly and as many valid ones (the sample
        # may be every row of a recording), and the views pick from those.
        valid = np.asarray(sample.valid, dtype=bool)
        rows = np.union1d(_decimate(len(valid), max_points),
                          np.flatnonzero(valid)[_decimate(int(valid.sum()), max_points)])
        vd = view_data(sample.rows(rows, copy=False), self.calibration.R_body_mag)
        t_all = np.asarray(vd.t_ns, dtype="datetime64[ns]")
        v = vd.valid

        def times(idx: np.ndarray) -> list:
            return [rr.TimeColumn("time", timestamp=t_all[idx])]

        # --- 3D: the body turning in ENU, and the field: the reference (fixed in ENU) and
        # the measured field before / after calibration, carried by the body frame (they
        # point along the reference when the calibration is right); unit length x 1.5
        rec.log("world/enu_axes", rr.Arrows3D(vectors=np.eye(3) * 0.6, colors=list(AXIS_RGB),
                                              labels=["east", "north", "up"]), static=True)
        rec.log("world/body/axes", rr.Arrows3D(vectors=np.eye(3), colors=list(AXIS_RGB),
                                               labels=["x", "y", "z"]), static=True)
        B = np.asarray(vd.B_enu_nT, float)
        scale = FIELD_ARROW / max(float(np.linalg.norm(B)), 1e-9)
        rec.log("world/field/reference", rr.Arrows3D(vectors=[B * scale], colors=[IDEAL_RGB],
                                                     labels=["reference field"]), static=True)
        dec = np.flatnonzero(v)[_decimate(int(np.count_nonzero(v)), max_points)]
        rec.send_columns("world/body", indexes=times(dec),
                         columns=rr.Transform3D.columns(quaternion=vd.q_enu_body[dec]))
        for name, arr, rgb in (("before", vd.body_before_nT, BEFORE_RGB),
                               ("after", vd.body_after_nT, AFTER_RGB)):
            ok = dec[np.isfinite(arr[dec]).all(axis=1)]
            if len(ok) == 0:
                continue
            ent = f"world/body/field_{name}"
            rec.log(ent, rr.Arrows3D.from_fields(colors=[rgb], labels=[f"field {name}"]),
                    static=True)
            rec.send_columns(ent, indexes=times(ok),
                             columns=rr.Arrows3D.columns(vectors=arr[ok] * scale))
        # --- Li 2020 Fig. 7: field in the body frame before / after / ideal (static clouds)
        for name, arr, rgb in (
            ("before", vd.body_before_nT, BEFORE_RGB),
            ("after", vd.body_after_nT, AFTER_RGB),
            ("ideal", vd.body_ideal_nT, IDEAL_RGB),
        ):
            good = np.flatnonzero(np.isfinite(arr).all(axis=1))
            sel = good[_decimate(len(good), max_points)]
            rec.log(f"trajectory/{name}", rr.Points3D(arr[sel], colors=[rgb], radii=[50.0]),
                    static=True)
        self._map(rr, sample, diagnosis)
        # --- segments and diagnosis events: labelled spans (state timeline) and text logs
        seg_items = [
            (int(sg.start_ns), int(sg.end_ns),
             f"{i}: {getattr(sg.kind, 'value', sg.kind)} {(sg.end_ns - sg.start_ns) * 1e-9:.1f} s")
            for i, sg in enumerate(segments or ())
        ]
        kinds = {k: style.rgb(c) for k, c in style.SEGMENT.items()}
        _log_spans(rec, "segments/spans", seg_items, kinds)
        if segments:
            st = np.array([s.start_ns for s in segments], dtype="datetime64[ns]")
            texts = [
                f"segment {i}: {getattr(s.kind, 'value', s.kind)} "
                f"{(s.end_ns - s.start_ns) * 1e-9:.1f} s"
                + ("" if s.twist_deg is None else f", turned {s.twist_deg:.0f} deg about its axis")
                for i, s in enumerate(segments)
            ]
            rec.send_columns("segments/log", indexes=[rr.TimeColumn("time", timestamp=st)],
                             columns=rr.TextLog.columns(text=texts))
        if diagnosis is not None:
            d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
            t0 = int(sample.t_ns[0]) if len(sample.t_ns) else 0
            stamps, texts = [], []
            events: list[tuple[int, int, str]] = []
            for f in d.get("findings", []):
                eff = str(f.get("effect"))
                for w in (f.get("where") or {}).get("windows_s") or []:
                    stamps.append(t0 + int(float(w[0]) * 1e9))
                    texts.append(f"{eff}: {float(w[0]):.1f}-{float(w[1]):.1f} s")
                    if eff in ("disturbance", "hard_iron_step"):
                        events.append((t0 + int(float(w[0]) * 1e9),
                                       t0 + int(float(w[1]) * 1e9), eff.replace("_", " ")))
            _log_spans(rec, "diagnosis/events", events,
                       {"disturbance": style.rgb(style.EVENT), "hard": style.rgb(style.EVENT)})
            if stamps:
                rec.send_columns(
                    "diagnosis/log",
                    indexes=[rr.TimeColumn("time", timestamp=np.array(stamps,
                                                                      dtype="datetime64[ns]"))],
                    columns=rr.TextLog.columns(text=texts, level=["WARN"] * len(texts)),
                )


    def _map(self, rr: Any, sample: Any, diagnosis: Any) -> None:
        """Log the path through space coloured by the restored field, sources and events.

        The report's plan view (:mod:`stages.report_map`) in 3D: ``map/path`` (Points3D, the
        path's run means coloured by |B| minus its median, blue below, red above, and a grey
        LineStrips3D joining them), ``map/sources`` (Ellipsoids3D: each located source with
        its 1-sigma half-sizes) and ``map/events`` (Points3D: where the sensor was during
        each diagnosed event, labelled). Nothing without positions.
        """
        md = report_map_data(self.recording, sample, self.calibration, diagnosis)
        if md is None:
            return
        import matplotlib

        rec = self.rec
        path = np.asarray(md["path"], dtype=float)
        lim = colour_limit(md)
        cmap = matplotlib.colormaps[CMAP]
        rgb = (np.asarray(cmap(np.clip(0.5 + 0.5 * path[:, 4] / lim, 0.0, 1.0)))[:, :3]
               * 255).astype(np.uint8)
        xyz = path[:, 1:4]
        scale = float(np.ptp(xyz, axis=0).max()) or 1.0
        rec.log("map/path", rr.Points3D(xyz, colors=rgb, radii=[0.004 * scale]), static=True)
        rec.log("map/path/line", rr.LineStrips3D([xyz], colors=[(150, 150, 150)],
                                                 radii=[0.0008 * scale]), static=True)
        src = md.get("sources") or []
        if src:
            half = [[(s or 0.02 * scale) for s in (x.get("sigma_m") or [None] * 3)]
                    for x in src]
            rec.log("map/sources", rr.Ellipsoids3D(
                centers=[x["position_m"] for x in src], half_sizes=half,
                colors=[IDEAL_RGB], labels=[f"source {i + 1}" for i in range(len(src))]),
                static=True)
        ev = md.get("events") or []
        if ev:
            rec.log("map/events", rr.Points3D(
                [[e["x"], e["y"], e["z"]] for e in ev], colors=[style.rgb(style.EVENT_EDGE)],
                radii=[0.012 * scale],
                labels=[f"{e['effect'].replace('_', ' ')} {e['start_s']:.0f}-{e['end_s']:.0f} s"
                        for e in ev]), static=True)
        cells = grid_points(self.dest.parent)  # anomaly.nc, written before this file
        if cells is not None:
            rec.log("map/anomaly_grid", rr.Points3D(cells[0], colors=cells[1],
                                                    radii=[cells[2]]), static=True)


def write_rrd(
    recording: Recording,
    calibration: Any,
    dest: str | Path,
    *,
    segments: tuple[Segment, ...] | None = None,
    diagnosis: Any = None,
    max_gap_s: float | None = None,
    max_points: int = 20000,
    restored: Any = None,
) -> Path:
    """Write the rerun recording (docs/modules.md for the entities).

    Parameters
    ----------
    recording : Recording
        With ``attitude`` filled.
    calibration : Calibration
        The fitted model.
    dest : path
        ``<stem>.rrd``; never the input.
    segments : tuple of Segment, optional
        Shown as ``segments/index`` and ``segments/log``.
    diagnosis : Diagnosis or dict, optional
        Its findings' windows are logged under ``diagnosis/log``.
    max_gap_s : float
        Attitude gap bridged by interpolation.
    max_points : int
        Most points per static 3D trajectory.
    restored : RestoreResult, optional
        ``ctx.restored``; computed when not given.

    Returns
    -------
    Path
        ``dest``.

    """
    if restored is None:
        restored = restore_samples(recording, calibration, max_gap_s=max_gap_s)
    with RrdStream(recording, calibration, dest) as out:
        out.add(restored)
        out.finish(restored, segments=segments, diagnosis=diagnosis, max_points=max_points)
    return Path(dest)
