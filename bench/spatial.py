"""The field in space: each figure of the issue's "Done when" beside its anchor, in one run.

Usage: ``python bench/spatial.py [WORKDIR] [SECTION ...]`` with sections ``ground`` (the
default) and ``survey2h`` (a 2-hour survey's time and memory, :func:`survey2h`). Each
section is a function ``section(work: Path) -> list[Row]`` registered in :data:`SECTIONS`;
a new one (indoor mapping) is added there.

``ground``: simulated ground surveys from the independent generator (``tests/indep_gen.py``,
no magalign model code), processed together by ``magalign process`` (every output):

- ``inspva``: INSPVA attitude and positions, 8 lines 3 m apart, 40 m long, at 1.5 m/s;
- ``navsatfix``: an IMU with a 10 Hz NavSatFix, 5 lines 6 m apart;
- ``null``: the INSPVA survey without objects.

Six objects of 5-50 A m^2 at 0.5-2 m below the ground (the sensor 1 m above it), each giving
10-300 nT at its nearest line; 1 nT noise. Figures: every object listed in targets.csv within
0.5 m horizontally and 0.3 m in depth; no target in the null survey; anomaly.nc's
total-field anomaly within 3 nT RMS of the generator's at the cells between the lines; NaN
at every cell beyond mask_distance_m from the path; R within 0.01 deg.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
sys.path.insert(0, str(HERE))
import indep_gen as g  # noqa: E402
from process import child_run  # noqa: E402
from scale import RATE_HZ, make_recording  # noqa: E402

HEIGHT_M = 1.0


@dataclass
class Row:
    """One figure beside its anchor."""

    what: str
    value: str
    anchor: str
    ok: bool | None


def _objects(spacing: float, seed: int) -> list[dict]:
    """Six buried dipoles near the lines (within 1 m of one), 5-50 A m^2, 0.5-2 m deep."""
    rng = np.random.default_rng(seed)
    lines = [0, 1, 2, 3, 4, 4] if spacing > 4 else [0, 1, 2, 3, 5, 6]
    north = [8.0, 30.0, 15.0, 24.0, 33.0, 12.0]
    depth = [0.5, 1.0, 1.5, 2.0, 0.8, 1.8]
    moment = [5.0, 10.0, 20.0, 50.0, 8.0, 25.0]
    out = []
    for k, y, d, m in zip(lines, north, depth, moment, strict=True):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        out.append({"position_m": [k * spacing + rng.uniform(-0.8, 0.8), y, -d],
                    "moment_Am2": (m * u).tolist()})
    return out


def _spec(name: str, spacing: float, n_lines: int, position_type: str, objects: list[dict],
          seed: int) -> g.Spec:
    speed, length = 1.5, 40.0
    turn = 8 * spacing / (3 * speed)
    duration = 20.0 + 3.0 + n_lines * length / speed + (n_lines - 1) * turn - 1.0
    att = ("novatel_oem7_msgs/msg/INSPVA" if position_type == "inspva"
           else "sensor_msgs/msg/Imu")
    return g.Spec(name, seed, duration_s=duration, path="survey", survey_line_m=length,
                  survey_spacing_m=spacing, survey_speed_m_s=speed, survey_height_m=HEIGHT_M,
                  survey_calibration_s=20.0, mag_noise_nT=1.0, att_type=att,
                  position_type=position_type, mag_rate_hz=100.0, att_rate_hz=100.0,
                  effects={"field_map": {"dipoles": objects}} if objects else {})


def _rows_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _peak_at_lines_nT(spec: g.Spec, objects: list[dict]) -> list[float]:
    t = np.arange(spec.survey_calibration_s, spec.duration_s, 0.01)
    p = g.position_m(spec, t)
    return [float(np.linalg.norm(g.dipole_field_nT(np.asarray(o["moment_Am2"]),
                                                   p - np.asarray(o["position_m"])),
                                 axis=1).max()) for o in objects]


def _grid_check(spec: g.Spec, nc: Path) -> tuple[float, int, int, float]:
    """RMS between the lines, cells beyond the mask that are not NaN, cells, mask distance."""
    import xarray as xr

    with xr.open_dataset(nc, engine="h5netcdf") as ds:
        off = np.array([0.0, 0.0, float(ds.attrs["position_origin_height_m"])
                        - spec.geo_origin[2]])
        e, n = np.meshgrid(ds["easting"].values, ds["northing"].values)
        tfa = ds["total_field_anomaly_nT"].values
        h, mask = float(ds.attrs["height_m"]), float(ds.attrs["mask_distance_m"])
    x = np.column_stack([e.ravel(), n.ravel(), np.full(e.size, h)]) + off
    bg = np.asarray(spec.B_enu_nT, float)
    dip = spec.effects.get("field_map", {"dipoles": []})["dipoles"]
    B = bg + (g.smooth_field_at({"dipoles": dip}, x) if dip else np.zeros_like(x))
    want = (np.linalg.norm(B, axis=1) - np.linalg.norm(bg)).reshape(e.shape)
    path = g.position_m(spec, np.arange(0.0, spec.duration_s, 0.01))[:, :2] - off[:2]
    between = (np.isfinite(tfa) & (e > path[:, 0].min()) & (e < path[:, 0].max())
               & (n > path[:, 1].min() + 2.0) & (n < path[:, 1].max() - 2.0))
    rms = float(np.sqrt(np.mean((tfa - want)[between] ** 2)))
    dist = cKDTree(path).query(np.column_stack([e.ravel(), n.ravel()]))[0].reshape(e.shape)
    beyond = dist > mask + 0.02
    return rms, int(np.count_nonzero(np.isfinite(tfa[beyond]))), int(np.count_nonzero(beyond)), \
        mask


def ground(work: Path) -> list[Row]:
    """The ground-survey figures (see the module's description)."""
    data = work / "ground"
    data.mkdir(parents=True, exist_ok=True)
    objs = {"inspva": _objects(3.0, 1), "navsatfix": _objects(6.0, 2)}
    specs = {"inspva": _spec("inspva", 3.0, 8, "inspva", objs["inspva"], 11),
             "navsatfix": _spec("navsatfix", 6.0, 5, "navsatfix", objs["navsatfix"], 12),
             "null": _spec("null", 3.0, 8, "inspva", [], 13)}
    for name, spec in specs.items():
        g.write(spec, data / f"{name}.mcap")
    out = work / "ground_out"
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", str(data),
                        "--out", str(out), "--jobs", "2", "--no-progress"],
                       capture_output=True, text=True, cwd=HERE.parent)
    wall = time.perf_counter() - t0
    rows = [Row("process, 3 surveys (s)", f"{wall:.0f}", "", None)]
    if r.returncode != 0:
        return rows + [Row("process exit status", str(r.returncode), "0", False)]
    for name, spec in specs.items():
        found = _rows_csv(out / name / "targets.csv")
        if name == "null":
            rows.append(Row("null survey: targets", str(len(found)), "0", not found))
        else:
            peaks = _peak_at_lines_nT(spec, objs[name])
            rows.append(Row(f"{name}: objects' field at the nearest line (nT)",
                            f"{min(peaks):.0f}-{max(peaks):.0f}", "10-300",
                            min(peaks) >= 10 and max(peaks) <= 300))
            dh, dz = [], []
            for o in objs[name]:
                x = np.asarray(o["position_m"])
                d = [np.hypot(float(f["east_m"]) - x[0], float(f["north_m"]) - x[1])
                     for f in found]
                if not d:
                    dh.append(np.inf)
                    dz.append(np.inf)
                    continue
                f = found[int(np.argmin(d))]
                dh.append(min(d))
                dz.append(abs(float(f["depth_below_sensor_m"]) - (HEIGHT_M - x[2])))
            rows.append(Row(f"{name}: targets listed / objects", f"{len(found)} / 6", "6 / 6",
                            len(found) == 6))
            rows.append(Row(f"{name}: worst horizontal error (m)", f"{max(dh):.3f}", "<= 0.5",
                            max(dh) <= 0.5))
            rows.append(Row(f"{name}: worst depth error (m)", f"{max(dz):.3f}", "<= 0.3",
                            max(dz) <= 0.3))
        rms, bad, beyond, mask = _grid_check(spec, out / name / "anomaly.nc")
        rows.append(Row(f"{name}: anomaly.nc RMS between the lines (nT)", f"{rms:.2f}",
                        "<= 3", rms <= 3.0))
        rows.append(Row(f"{name}: cells beyond {mask:.2f} m not NaN", f"{bad} of {beyond}",
                        "0", bad == 0))
        cal = __import__("json").loads((out / name / "calibration.json").read_text())
        R = Rotation.from_matrix(np.asarray(cal["R_body_mag"]))
        err = np.degrees((R.inv() * Rotation.from_rotvec(
            np.radians(spec.rotvec_body_mag_deg))).magnitude())
        rows.append(Row(f"{name}: R error (deg)", f"{err:.4f}", "<= 0.01", err <= 0.01))
    return rows


def survey2h(work: Path) -> list[Row]:
    """A 2-hour survey with positions and six objects against ``bench/process.py``'s 2 hours.

    The survey: INSPVA attitude and positions and a 1 nT sensor, both at 200 Hz (the message
    count of ``bench/process.py``'s recording: 1.44M + 1.44M), lines 200 m long and 3 m
    apart at 1.5 m/s, the six objects of :func:`ground`. Both are processed with every
    output (the survey's include targets.csv and anomaly.nc), each in a fresh process, in
    this one run: wall time and the peak resident memory of the process tree.
    """
    data = work / "survey2h"
    data.mkdir(parents=True, exist_ok=True)
    objs = _objects(3.0, 1)
    spec = g.Spec("survey2h", 21, duration_s=7200.0, path="survey", survey_line_m=200.0,
                  survey_spacing_m=3.0, survey_speed_m_s=1.5, survey_height_m=HEIGHT_M,
                  survey_calibration_s=20.0, mag_noise_nT=1.0,
                  att_type="novatel_oem7_msgs/msg/INSPVA", position_type="inspva",
                  mag_rate_hz=200.0, att_rate_hz=200.0,
                  effects={"field_map": {"dipoles": objs}})
    rec = data / "survey2h.mcap"
    if not rec.exists():
        g.write(spec, rec)
    ref = data / f"scale_{int(7200 * RATE_HZ)}.mcap"
    if not ref.exists():
        make_recording(ref, int(7200 * RATE_HZ))
    cli = [sys.executable, "-m", "pipeline.app.cli", "process"]
    t_ref, rss_ref = child_run(cli + [str(ref), "--out", str(work / "survey2h_ref")])
    t_ours, rss_ours = child_run(cli + [str(rec), "--out", str(work / "survey2h_out")])
    found = _rows_csv(work / "survey2h_out" / "survey2h" / "targets.csv")
    dh = [min((np.hypot(float(f["east_m"]) - o["position_m"][0],
                        float(f["north_m"]) - o["position_m"][1]) for f in found),
              default=np.inf) for o in objs]
    return [
        Row("bench/process.py's 2 h, process (s)", f"{t_ref:.0f}", "", None),
        Row("2 h survey, process with every output (s)", f"{t_ours:.0f}",
            f"<= {1.5 * t_ref:.0f}", t_ours <= 1.5 * t_ref),
        Row("2 h survey / bench/process.py's 2 h", f"{t_ours / t_ref:.2f}", "<= 1.5",
            t_ours <= 1.5 * t_ref),
        Row("2 h survey, peak RSS (MB)", f"{rss_ours:.0f}", "<= 1024", rss_ours <= 1024),
        Row("bench/process.py's 2 h, peak RSS (MB)", f"{rss_ref:.0f}", "", None),
        Row("2 h survey: targets listed / objects", f"{len(found)} / 6", "6 / 6",
            len(found) == 6),
        Row("2 h survey: worst horizontal error (m)", f"{max(dh):.3f}", "<= 0.5",
            max(dh) <= 0.5),
    ]


SECTIONS: dict[str, Callable[[Path], list[Row]]] = {"ground": ground, "survey2h": survey2h}


def main(argv: list[str]) -> int:
    work = Path(argv[1]) if len(argv) > 1 else Path(tempfile.mkdtemp(prefix="spatial-"))
    names = argv[2:] or ["ground"]
    bad = 0
    for name in names:
        rows = SECTIONS[name](work)
        print(f"\n== {name} ==")
        print(f"{'figure':<58} {'value':>14} {'anchor':>10}  ok")
        for r in rows:
            ok = "" if r.ok is None else ("yes" if r.ok else "NO")
            bad += r.ok is False
            print(f"{r.what:<58} {r.value:>14} {r.anchor:>10}  {ok}")
    print(f"\nwork folder: {work}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
