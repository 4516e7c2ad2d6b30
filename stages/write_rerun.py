"""Write ``<stem>.rrd``: a rerun recording with a default blueprint (rerun-sdk 0.41).

Every time series goes in with ``send_columns`` (one call per entity, no per-sample log
call). Timeline ``time`` (timestamps, the magnetometer stamps). Entities:

- ``field/uncalibrated/{east,north,up}`` (Scalars): one row per sample with attitude,
  ``C_enu_body @ y`` (Li 2020 Figs. 5 and 8, "before");
- ``field/calibrated/{east,north,up}`` (Scalars): one row per restored sample ("after");
- ``residual/{x,y,z}`` (Scalars): measured minus predicted, mag frame, nT;
- ``mag/raw/{x,y,z}`` (Scalars): one row per magnetometer sample, mag frame, nT;
- ``attitude/{heading,pitch,roll}_deg`` (Scalars): Li 2020 Euler angles at ``t - tau``;
- ``world/body`` (Transform3D): the attitude rotating the body axes ``world/body/axes``
  (static arrows);
- ``trajectory/{before,after,ideal}`` (Points3D, static): the field in the body frame (Li 2020
  Fig. 7 circles), at most ``max_points`` points each;
- ``segments/index`` (Scalars): the segment number at each sample (-1 outside segments);
- ``segments/log``, ``diagnosis/log`` (TextLog): one row per segment / diagnosis window start.

The blueprint puts the three ENU components (before and after) in a row of plots on top,
residuals, attitude and segments below, and the 3D views (trajectories, attitude) beside.
The file is saved to a temporary name and renamed when complete.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from pipeline.atomic import atomic_path
from pipeline.errors import OutputError
from pipeline.recording import Context, Recording, Segment

ENU_NAMES = ("east", "north", "up")
AXES = ("x", "y", "z")
BEFORE_RGB = (230, 120, 30)
AFTER_RGB = (30, 110, 220)
IDEAL_RGB = (40, 170, 60)
AXIS_RGB = ((220, 50, 50), (50, 180, 50), (60, 90, 230))


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
            rrb.TimeSeriesView(name="segments", origin="/segments"),
            rrb.TextLogView(name="segments and diagnosis", contents=["/segments/**",
                                                                     "/diagnosis/**"]),
        ),
    )
    spatial = rrb.Vertical(
        rrb.Spatial3DView(name="field in body frame: before / after / ideal (nT)",
                          origin="/trajectory"),
        rrb.Spatial3DView(name="attitude", origin="/world"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(enu_row, lower, row_shares=[3, 2]), spatial,
                       column_shares=[3, 1]),
        collapse_panels=True,
    )


def _segment_index(t_ns: np.ndarray, segments: tuple[Segment, ...] | None) -> np.ndarray:
    idx = np.full(len(t_ns), -1.0)
    for i, s in enumerate(segments or ()):
        idx[s.contains(t_ns)] = i
    return idx


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
    """Write the rerun recording (module docstring for the entities).

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
    # rerun's own log lines (several per failure) would break the one-line answer; a failed
    # write is reported by magalign itself (OutputError below)
    os.environ.setdefault("RUST_LOG", "off")
    import rerun as rr

    from pipeline.geometry import quat_to_li2020_euler
    from stages.restore import restore_samples, view_data

    if restored is None:
        restored = restore_samples(recording, calibration, max_gap_s=max_gap_s)
    vd = view_data(restored, calibration.R_body_mag)
    stem = Path(recording.path).stem
    dest = Path(dest)
    t_all = np.asarray(vd.t_ns, dtype="datetime64[ns]")
    v = vd.valid

    def times(mask: np.ndarray | None = None) -> list:
        return [rr.TimeColumn("time", timestamp=t_all if mask is None else t_all[mask])]

    with atomic_path(dest, (recording.path,)) as tmp:
        os.unlink(tmp)  # rerun creates the file itself
        rec = rr.RecordingStream("magalign", recording_id=f"magalign-{stem}")
        rec.save(str(tmp), default_blueprint=blueprint())
        rec.send_recording_name(stem)
        # --- Li 2020 Figs. 5 and 8: ENU components before and after calibration
        for k, c in enumerate(ENU_NAMES):
            for kind, arr, rgb in (
                ("uncalibrated", vd.uncalibrated_enu_nT, BEFORE_RGB),
                ("calibrated", vd.calibrated_enu_nT, AFTER_RGB),
            ):
                ent = f"field/{kind}/{c}"
                m = np.isfinite(arr[:, k])
                rec.log(ent, rr.SeriesLines(colors=[rgb], names=[f"{c} {kind}"]), static=True)
                rec.send_columns(ent, indexes=times(m), columns=rr.Scalars.columns(
                    scalars=arr[m, k]))
        # --- residuals and raw magnetometer, mag frame
        for k, a in enumerate(AXES):
            rec.log(f"residual/{a}", rr.SeriesLines(colors=[AXIS_RGB[k]], names=[f"residual {a}"]),
                    static=True)
            rec.send_columns(f"residual/{a}", indexes=times(v),
                             columns=rr.Scalars.columns(scalars=vd.residual_nT[v, k]))
            rec.log(f"mag/raw/{a}", rr.SeriesLines(colors=[AXIS_RGB[k]], names=[f"raw {a}"]),
                    static=True)
            rec.send_columns(f"mag/raw/{a}", indexes=times(),
                             columns=rr.Scalars.columns(scalars=vd.raw_mag_nT[:, k]))
        # --- attitude: Li 2020 Euler angles and a rotating body frame
        h, p, r = quat_to_li2020_euler(vd.q_enu_body[v])
        for k, (name, ang) in enumerate((("heading", h), ("pitch", p), ("roll", r))):
            rec.log(f"attitude/{name}_deg", rr.SeriesLines(colors=[AXIS_RGB[k]],
                                                           names=[f"{name} (deg)"]), static=True)
            rec.send_columns(f"attitude/{name}_deg", indexes=times(v),
                             columns=rr.Scalars.columns(scalars=np.degrees(ang)))
        rec.log("world/body/axes", rr.Arrows3D(vectors=np.eye(3), colors=list(AXIS_RGB),
                                               labels=["x", "y", "z"]), static=True)
        dec = np.flatnonzero(v)[_decimate(int(np.count_nonzero(v)), max_points)]
        rec.send_columns("world/body", indexes=times(dec),
                         columns=rr.Transform3D.columns(quaternion=vd.q_enu_body[dec]))
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
        # --- segments and diagnosis windows
        rec.send_columns("segments/index", indexes=times(),
                         columns=rr.Scalars.columns(scalars=_segment_index(vd.t_ns, segments)))
        if segments:
            st = np.array([s.start_ns for s in segments], dtype="datetime64[ns]")
            texts = [
                f"segment {i}: {getattr(s.kind, 'value', s.kind)} "
                f"{(s.end_ns - s.start_ns) * 1e-9:.1f} s"
                + (f", twist {s.twist_deg:.0f} deg" if s.twist_deg is not None else "")
                for i, s in enumerate(segments)
            ]
            rec.send_columns("segments/log", indexes=[rr.TimeColumn("time", timestamp=st)],
                             columns=rr.TextLog.columns(text=texts))
        if diagnosis is not None:
            d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
            t0 = int(vd.t_ns[0]) if len(vd.t_ns) else 0
            stamps, texts = [], []
            for f in d.get("findings", []):
                for w in (f.get("where") or {}).get("windows_s") or []:
                    stamps.append(t0 + int(float(w[0]) * 1e9))
                    texts.append(f"{f.get('effect')}: {float(w[0]):.1f}-{float(w[1]):.1f} s")
            if stamps:
                rec.send_columns(
                    "diagnosis/log",
                    indexes=[rr.TimeColumn("time", timestamp=np.array(stamps,
                                                                      dtype="datetime64[ns]"))],
                    columns=rr.TextLog.columns(text=texts, level=["WARN"] * len(texts)),
                )
        try:
            rec.flush()
            rec.disconnect()
        except RuntimeError as exc:  # rerun's file writer stopped (disk full, ...)
            raise OutputError(f"cannot write the rerun recording: {exc}", path=dest,
                              hint="free some disk space and run again") from exc
    return dest


@dataclass(frozen=True)
class WriteRerun:
    """Stage: write ``<out_dir>/<stem>.rrd`` (module docstring).

    Parameters
    ----------
    out_dir : str
    max_gap_s : float
        Attitude gap bridged by interpolation.
    max_points : int
        Most points per static 3D trajectory.

    """

    out_dir: str
    max_gap_s: float | None = None
    max_points: int = 20000

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"outputs"})

    def run(self, ctx: Context) -> Context:
        """Write the .rrd and list it in ``ctx.outputs``."""
        dest = rrd_path(self.out_dir, ctx.recording.path)
        write_rrd(
            ctx.recording,
            ctx.calibration,
            dest,
            segments=ctx.segments,
            diagnosis=ctx.diagnosis,
            max_gap_s=self.max_gap_s,
            max_points=self.max_points,
            restored=ctx.restored,
        )
        return ctx.replace(outputs=ctx.outputs + (("rrd", str(dest)),))
