"""The survey's products of ``magalign process``: targets.csv and anomaly.nc (CONVENTIONS).

Two short ground surveys from the independent generator (:mod:`indep_gen`), processed
together as a folder through the command line: one with buried objects (INSPVA attitude
and positions), one without (an IMU with NavSatFix fixes). Lines 2 m apart at 1 m above the
ground, 1 nT noise; the objects give 80-250 nT at their nearest line.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from indep_gen import Spec, dipole_field_nT, position_m, smooth_field_at, write
from scipy.spatial import cKDTree

from stages.write_survey import compile_grid

HERE = Path(__file__).resolve().parent
COLUMNS = [
    "id", "east_m", "north_m", "up_m", "lat_deg", "lon_deg", "height_m",
    "depth_below_sensor_m", "sigma_east_m", "sigma_north_m", "sigma_up_m",
    "moment_east_Am2", "moment_north_Am2", "moment_up_Am2", "moment_Am2",
    "closest_approach_m", "closest_approach_utc", "peak_nT", "delta_bic", "position_frame",
]
GLOBAL_ATTRS = {"position_origin_lat_deg", "position_origin_lon_deg",
                "position_origin_height_m", "position_frame", "height_m", "spacing_m",
                "mask_distance_m", "background_B_enu_nT", "method", "magalign_version"}
#: buried objects in the generator's ENU (ground at up = 0, the sensor 1 m above it)
OBJECTS = [
    {"position_m": [1.0, 10.0, -0.8], "moment_Am2": [2.0, 6.0, -5.0]},
    {"position_m": [3.0, 20.0, -1.5], "moment_Am2": [-8.0, 18.0, 15.0]},
]
HEIGHT_M = 1.0


def _survey(name: str, objects: list[dict], position_type: str, seed: int) -> Spec:
    att = ("novatel_oem7_msgs/msg/INSPVA" if position_type == "inspva"
           else "sensor_msgs/msg/Imu")
    eff = {"field_map": {"dipoles": objects}} if objects else {}
    return Spec(name, seed=seed, duration_s=110.0, mag_rate_hz=50.0, att_rate_hz=20.0,
                att_type=att, path="survey", position_type=position_type,
                survey_spacing_m=2.0, survey_height_m=HEIGHT_M, survey_calibration_s=30.0,
                mag_noise_nT=1.0, att_noise_deg=0.002, effects=eff)


SPECS = {"objects": _survey("objects", OBJECTS, "inspva", 21),
         "null": _survey("null", [], "navsatfix", 22)}


@pytest.fixture(scope="module")
def processed(tmp_path_factory) -> Path:
    """The two surveys processed as one folder: DIR/objects, DIR/null, DIR/anomaly.nc."""
    tmp = tmp_path_factory.mktemp("survey")
    data = tmp / "data"
    data.mkdir()
    for name, spec in SPECS.items():
        write(spec, data / f"{name}.mcap")
    out = tmp / "out"
    r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", str(data),
                        "--out", str(out), "--jobs", "2", "--no-progress"],
                       capture_output=True, text=True, timeout=600, cwd=HERE.parent)
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def _rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="", encoding="utf-8") as fh:
        header = next(csv.reader(fh))
    with open(path, newline="", encoding="utf-8") as fh:
        return header, list(csv.DictReader(fh))


def _grid(path: Path):
    import xarray as xr

    return xr.open_dataset(path, engine="h5netcdf")


def _sensor_offset_m(ds, spec: Spec) -> np.ndarray:
    """Generator ENU minus magalign's local ENU (the origin is the first fix, 1 m up)."""
    return np.array([0.0, 0.0, float(ds.attrs["position_origin_height_m"])
                     - spec.geo_origin[2]])


def test_generator_noise_off_gives_the_dipole_field_on_the_path():
    """The generator with its noise off: the field on the path is the background plus the
    two dipoles, each 80-250 nT at its nearest pass (the sizes the issue asks for)."""
    spec = SPECS["objects"]
    t = np.arange(spec.survey_calibration_s, spec.duration_s, 0.02)
    p = position_m(spec, t)
    for o in OBJECTS:
        b = np.linalg.norm(dipole_field_nT(np.asarray(o["moment_Am2"]),
                                           p - np.asarray(o["position_m"])), axis=1)
        assert 80.0 < b.max() < 300.0
    total = smooth_field_at({"dipoles": OBJECTS}, p)
    each = sum(dipole_field_nT(np.asarray(o["moment_Am2"]), p - np.asarray(o["position_m"]))
               for o in OBJECTS)
    np.testing.assert_allclose(total, each, atol=1e-9)


def test_targets_csv_has_the_columns_in_order_and_the_null_survey_only_its_header(processed):
    for name in SPECS:
        header, rows = _rows(processed / name / "targets.csv")
        assert header == COLUMNS
        if name == "null":
            assert rows == []
    text = (processed / "objects" / "targets.csv").read_text(encoding="utf-8")
    assert "-0," not in text and ",-0.000," not in text


def test_every_buried_object_is_a_target_where_it_is(processed):
    """Each object within 0.5 m horizontally and 0.3 m in depth, the strongest first."""
    _, rows = _rows(processed / "objects" / "targets.csv")
    assert len(rows) == len(OBJECTS)
    assert [r["id"] for r in rows] == [f"T{i + 1}" for i in range(len(rows))]
    bic = [float(r["delta_bic"]) for r in rows]
    assert bic == sorted(bic)  # the more negative, the more strongly the data ask for it
    with _grid(processed / "objects" / "anomaly.nc") as ds:
        off = _sensor_offset_m(ds, SPECS["objects"])
    for o in OBJECTS:
        x = np.asarray(o["position_m"])
        d = [np.hypot(float(r["east_m"]) + off[0] - x[0], float(r["north_m"]) + off[1] - x[1])
             for r in rows]
        r = rows[int(np.argmin(d))]
        assert min(d) < 0.5
        assert abs(float(r["depth_below_sensor_m"]) - (HEIGHT_M - x[2])) < 0.3
        assert r["position_frame"] == "enu"
        assert r["lat_deg"] and r["lon_deg"] and r["height_m"]
        assert r["closest_approach_utc"].startswith("2026-01-01T") and \
            r["closest_approach_utc"].endswith("Z")
        assert 10.0 < float(r["peak_nT"]) < 400.0
        # the sigma covers the error, and a half of the survey that did not pass the object
        # does not widen it to metres (each object is passed on two or three lines)
        sig = np.array([float(r[f"sigma_{a}_m"]) for a in ("east", "north", "up")])
        err = np.array([float(r["east_m"]) + off[0] - x[0], float(r["north_m"]) + off[1] - x[1],
                        HEIGHT_M - x[2] - float(r["depth_below_sensor_m"])])
        assert np.all(sig < 0.1), sig
        assert np.all(np.abs(err) < 4 * sig), (err, sig)


def test_anomaly_nc_has_the_dimensions_variables_and_attributes(processed):
    for where in ("objects", "null", "."):
        with _grid(processed / where / "anomaly.nc") as ds:
            assert ds.attrs["Conventions"] == "CF-1.8"
            assert GLOBAL_ATTRS <= set(ds.attrs)
            assert ds.attrs["position_frame"] == "enu"
            assert np.asarray(ds.attrs["background_B_enu_nT"]).shape == (3,)
            assert "harmonica" in ds.attrs["method"]
            for v in ("B_east_nT", "B_north_nT", "B_up_nT", "total_field_anomaly_nT",
                      "latitude", "longitude"):
                assert ds[v].dims == ("northing", "easting"), v
            for d in ("easting", "northing"):
                step = np.diff(ds[d].values)
                np.testing.assert_allclose(step, float(ds.attrs["spacing_m"]), rtol=1e-9)
            B = np.stack([ds[v].values for v in ("B_east_nT", "B_north_nT", "B_up_nT")])
            tfa = np.linalg.norm(B, axis=0) - np.linalg.norm(ds.attrs["background_B_enu_nT"])
            ok = np.isfinite(tfa)
            np.testing.assert_allclose(ds["total_field_anomaly_nT"].values[ok], tfa[ok],
                                       atol=1e-6)
    head = (processed / "objects" / "anomaly.nc").read_bytes()[:8]
    assert head == b"\x89HDF\r\n\x1a\n"  # NetCDF-4 is HDF5


@pytest.mark.parametrize("name", list(SPECS))
def test_the_grid_matches_the_field_between_the_lines_and_is_blank_beyond_the_mask(
        processed, name):
    """Within 3 nT RMS of the generator's total-field anomaly at the grid's height, at the
    cells between the lines; NaN at every cell farther than mask_distance_m from the path."""
    spec = SPECS[name]
    with _grid(processed / name / "anomaly.nc") as ds:
        off = _sensor_offset_m(ds, spec)
        e, n = np.meshgrid(ds["easting"].values, ds["northing"].values)
        tfa = ds["total_field_anomaly_nT"].values
        h, mask = float(ds.attrs["height_m"]), float(ds.attrs["mask_distance_m"])
    x = np.column_stack([e.ravel(), n.ravel(), np.full(e.size, h)]) + off
    bg = np.asarray(spec.B_enu_nT, float)
    dip = spec.effects.get("field_map", {"dipoles": []})
    B = bg + (smooth_field_at(dip, x) if dip["dipoles"] else np.zeros_like(x))
    want = (np.linalg.norm(B, axis=1) - np.linalg.norm(bg)).reshape(e.shape)
    path = position_m(spec, np.arange(0.0, spec.duration_s, 0.02))[:, :2] - off[:2]
    lines_e = path[:, 0]
    between = (np.isfinite(tfa) & (e > lines_e.min()) & (e < lines_e.max())
               & (n > path[:, 1].min() + 2.0) & (n < path[:, 1].max() - 2.0))
    assert np.count_nonzero(between) > 100
    rms = float(np.sqrt(np.mean((tfa - want)[between] ** 2)))
    assert rms < 3.0, rms
    dist = cKDTree(path).query(np.column_stack([e.ravel(), n.ravel()]))[0].reshape(e.shape)
    assert np.all(np.isnan(tfa[dist > mask + 0.05]))  # the path between samples: 3 cm
    # near the path the grid is there (the path's last fixes may stop short of its end)
    assert np.mean(np.isfinite(tfa[dist < 0.9 * mask])) > 0.98


def test_the_report_shows_the_grid_and_the_targets(processed):
    text = (processed / "objects" / "report.html").read_text(encoding="utf-8")
    assert "id=survey" in text and "<table id=targets>" in text
    assert 'alt="fig_anomaly.png"' in text
    text = (processed / "null" / "report.html").read_text(encoding="utf-8")
    assert "<p id=targets>" in text


def test_line_spacing_grid_rule_and_an_in_process_grid_raise_no_warning(tmp_path):
    """Parallel lines 4 m apart give a 4 m line spacing, 1 m cells and a 2.4 m mask; the
    grid of one dipole, written and read in this process (warnings are errors here)."""
    from stages.write_survey import Source, grid_rule, grid_survey, read_grid, write_anomaly

    north = np.arange(0.0, 30.0, 0.05)
    p = np.concatenate([np.column_stack([np.full_like(north, 4.0 * k),
                                         north if k % 2 == 0 else north[::-1],
                                         np.zeros_like(north)]) for k in range(5)])
    assert grid_rule(p) == pytest.approx((4.0, 1.0, 2.4), rel=1e-6)
    bg = np.array([1000.0, 20000.0, -40000.0])
    src = Source(np.array([6.0, 15.0, -2.0]), np.full(3, 0.01), np.array([5.0, 20.0, -30.0]),
                 2.0, 10.0, -500.0, "enu")
    B = bg + dipole_field_nT(src.moment_Am2, p - src.position_m)
    grid = grid_survey(p, B, bg, [src])
    assert grid is not None
    write_anomaly(tmp_path / "anomaly.nc", grid, position_frame="attitude_source_local",
                  origin=None, magalign_version="test")
    d = read_grid(tmp_path / "anomaly.nc")
    assert "position_origin_lat_deg" not in d["attrs"] and "latitude" not in d
    e, n = np.meshgrid(d["easting"], d["northing"])
    x = np.column_stack([e.ravel(), n.ravel(), np.full(e.size, d["attrs"]["height_m"])])
    want = (np.linalg.norm(bg + dipole_field_nT(src.moment_Am2, x - src.position_m), axis=1)
            - np.linalg.norm(bg)).reshape(e.shape)
    ok = np.isfinite(d["total_field_anomaly_nT"])
    assert np.sqrt(np.mean((d["total_field_anomaly_nT"] - want)[ok] ** 2)) < 0.5


def test_the_rerun_recording_shows_the_grid(processed):
    """``map/anomaly_grid``: a point per unmasked cell of anomaly.nc, at the grid's height."""
    from test_outputs import rrd_columns

    cols = rrd_columns(processed / "objects" / "objects.rrd")
    (pts,) = cols["/map/anomaly_grid"]["Points3D:positions"]
    with _grid(processed / "objects" / "anomaly.nc") as ds:
        n_cells = int(np.count_nonzero(np.isfinite(ds["total_field_anomaly_nT"].values)))
        h = float(ds.attrs["height_m"])
    assert len(pts) == n_cells
    np.testing.assert_allclose(np.asarray(pts)[:, 2], h, atol=1e-4)


def test_the_grids_warm_up_grids_a_constant_field_to_no_anomaly():
    """``compile_grid`` (run on process' helper thread) goes through the real grid: a circle
    where the field is the background everywhere grids to no anomaly inside the mask."""
    grid = compile_grid()
    assert grid is not None
    inside = np.isfinite(grid.total_field_anomaly_nT)
    assert inside.any() and not inside.all()  # the mask holds beyond its distance
    assert np.max(np.abs(grid.total_field_anomaly_nT[inside])) < 1e-6
    np.testing.assert_allclose(grid.B_enu_nT[:, inside].T - grid.background_B_enu_nT, 0.0,
                               atol=1e-6)
