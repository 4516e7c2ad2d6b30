"""A long recording, analysed on windows and read in chunks (pipeline/run), gives the outputs
it gives analysed and restored whole for the same model, in memory that does not grow with
the recording: restore, metrics, corrected MCAP, rerun recording, report counts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from indep_gen import Spec, write
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from test_scale import make

from pipeline.core.recording import Segment, SegmentKind
from pipeline.io.mcap_header import read_recording_header
from pipeline.io.mcap_read import iter_recording_chunks, read_recording
from pipeline.model.attitude import AttitudeInterpolator
from pipeline.model.calibration import Calibration
from stages.metrics import MetricsAccumulator, compute_metrics
from stages.restore import ChunkedRestore, RestoreTotals, restore_samples


def walk_json(a, b, rel: float = 1e-6, path: str = "") -> None:
    """Every number of two JSON documents within ``rel`` or 1e-6 absolute (nT, deg, s, %),
    everything else equal."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            walk_json(a[k], b[k], rel, f"{path}/{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            walk_json(x, y, rel, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert b == pytest.approx(a, rel=rel, abs=1e-6), path
    else:
        assert a == b, path


def windowed(row) -> bool:
    """Whether ``process`` analysed windows of the recording: it segments before resampling."""
    steps = list(row["timings_s"])
    return steps.index("SegmentMotion") < steps.index("Resample")


def _cal(tau_s: float) -> Calibration:
    from test_scale import B_ENU, ROTVEC_DEG

    from pipeline.core.geometry import so3_exp

    return Calibration(R_body_mag=so3_exp(np.radians(ROTVEC_DEG)),
                       sigma_rotvec_deg=np.full(3, 0.01), B_enu_nT=B_ENU, estimator="test",
                       residual_rms_nT=0.5, n_samples=0, time_offset_s=tau_s)


def chunked(path, cal, chunk_messages, *, positions=False):
    """Restore ``path`` with ``cal`` chunk by chunk, as pass 2 of a long recording does.

    Returns ``(rec, parts, held, chunks)``: the whole recording, the restored parts, the most
    samples held between chunks (attitude, waiting rows, positions) and the chunks read.
    """
    rec = read_recording(path)
    it = AttitudeInterpolator.of(rec.attitude)
    cr = ChunkedRestore(cal, t0_ns=int(rec.mag.t_ns[0]), max_gap_s=it.max_gap_s,
                        cubic_weight=it.cubic_weight, step_s=it.step_s, positions=positions)
    parts, held = [], 0
    chunks = list(iter_recording_chunks(path, max_messages=chunk_messages))
    for ch in chunks:
        parts.append(cr.add(ch.mag.t_ns, ch.mag.values, ch.attitude.t_ns,
                            ch.attitude.q_enu_body, ch.position if positions else None))
        held = max(held, cr.attitude.held,
                   0 if cr.positions is None else len(cr.positions._t))
    parts.append(cr.finish())
    return rec, [p for p in parts if p is not None], held, chunks


def assert_restores_alike(parts, whole, fields=("enu_nT", "residual_nT")):
    """The chunked parts are the whole recording's rows, to 1e-6 nT, NaN where it has NaN."""
    np.testing.assert_array_equal(np.concatenate([p.t_ns for p in parts]), whole.t_ns)
    for f in fields:
        got = np.concatenate([getattr(p, f) for p in parts])
        np.testing.assert_array_equal(np.isnan(got), np.isnan(getattr(whole, f)))
        np.testing.assert_allclose(got, getattr(whole, f), atol=1e-6, equal_nan=True)  # nT


@pytest.mark.parametrize("tau_s", [0.0, 0.013, -0.031])
def test_chunked_restore_equals_the_whole_recording_restore(tmp_path, tau_s):
    path, _ = make(tmp_path / "a.mcap", n=9_000, chunk_size=16 << 10)
    cal = _cal(tau_s)
    rec, parts, held, _ = chunked(path, cal, 1_500)
    whole = restore_samples(rec, cal)
    assert len(parts) >= 5
    assert_restores_alike(parts, whole, ("enu_nT", "residual_nT", "calibrated_mag_nT"))
    tot = sum((RestoreTotals.of(p) for p in parts), RestoreTotals())
    assert (tot.n_total, tot.n_used) == (whole.n_total, whole.n_used)
    assert tot.residual_rms_nT == pytest.approx(whole.residual_rms_nT, rel=1e-9)
    # what is held between chunks stays about one chunk (750 + 750 messages), not the file
    assert held < 2_000


def test_metrics_accumulator_equals_compute_metrics(tmp_path):
    path, _ = make(tmp_path / "b.mcap", n=6_000)
    cal = _cal(0.004)
    rec, parts, _, _ = chunked(path, cal, 1_000)
    t = rec.mag.t_ns
    segs = (Segment(int(t[100]), int(t[2_500]), SegmentKind("rotation")),
            Segment(int(t[2_500]), int(t[-1]) + 1, SegmentKind("static")),
            Segment(int(t[3_000]), int(t[3_001]), SegmentKind("static")))
    acc = MetricsAccumulator(segs, int(t[0]), spill_dir=tmp_path)
    for p in parts:
        acc.add(p)
    walk_json(compute_metrics(restore_samples(rec, cal), segs).to_dict(),
          acc.finish().to_dict())


def _decoded(path: Path, topic: str) -> np.ndarray:
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
        for _s, _c, _m, msg in reader.iter_decoded_messages(topics=[topic]):
            v = msg.magnetic_field
            out.append([v.x, v.y, v.z])
    return np.array(out) * 1e9


@pytest.mark.parametrize("step", [1, 4])
def test_long_recording_gives_the_whole_recordings_outputs(tmp_path, monkeypatch, step):
    """Same model (one calibration file), two paths: every output agrees.

    ``step``: the long recording's analysis segments (and its report draws) every
    ``step``-th sample; with 1 its segments, so every scope of the metrics, are the whole
    recording's.
    """
    from test_outputs import rrd_rows

    import pipeline.run.plan as plan
    import pipeline.run.source as source
    from pipeline.run.runner import ProcessOptions, process_recording

    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 8_000 // step)
    monkeypatch.setattr(source, "RANGE_MESSAGES", 3_000)  # several ranges
    path, _ = make(tmp_path / "c.mcap", n=8_000)
    first = process_recording(path, tmp_path / "fit",
                              options=ProcessOptions(diagnose=False, write_rerun=False,
                                                     write_report=False))
    cal_path = first["paths"]["calibration.json"]
    rows = {}
    for name, scale in (("mem", None), ("two", 1_000)):
        rows[name] = process_recording(path, tmp_path / name, options=ProcessOptions(
            calibration_path=cal_path, scale_samples=scale))
    mem, two = rows["mem"], rows["two"]
    assert windowed(two) and not windowed(mem)
    assert set(mem["paths"]) == set(two["paths"])
    assert two["n_samples"] == mem["n_samples"] == 8_000
    for k in ("residual_rms_nT", "ratio_pct_x", "ratio_pct_y", "ratio_pct_z", "duration_s"):
        assert two[k] == pytest.approx(mem[k], rel=1e-6), k
    d = {n: json.loads(Path(r["paths"]["metrics.json"]).read_text()) for n, r in rows.items()}
    if step == 1:
        walk_json(d["mem"], d["two"])
    else:  # segments of every 4th sample differ: the whole recording's scope agrees
        walk_json(d["mem"]["scopes"][0], d["two"]["scopes"][0])
        for k in ("n_samples", "n_used", "n_without_attitude"):
            assert d["mem"][k] == d["two"][k]
    for suffix in ("calibrated", "enu", "residual"):
        a = _decoded(Path(mem["paths"]["corrected_mcap"]), f"/mag/{suffix}")
        b = _decoded(Path(two["paths"]["corrected_mcap"]), f"/mag/{suffix}")
        assert a.shape == b.shape == (8_000, 3)
        np.testing.assert_allclose(b, a, atol=1e-6, equal_nan=True)  # nT
    # the rerun recordings, read back by rerun: every time series has the same rows; the
    # 3D views and clouds come from every 4th row in the two-pass one
    ra, rb = rrd_rows(Path(mem["paths"]["rrd"])), rrd_rows(Path(two["paths"]["rrd"]))
    for ent in ("/field/calibrated/east", "/field/uncalibrated/up", "/residual/x",
                "/mag/raw/z", "/attitude/heading_deg"):
        assert rb[ent] == ra[ent] > 7_900, ent
    assert 0 < rb["/world/body"] <= ra["/world/body"]
    # the report quotes the residual of every sample and says what its figures show
    html = Path(two["paths"]["report.html"]).read_text()
    assert f"{two['residual_rms_nT']:.7g}" in html and "8000 magnetometer samples" in html
    assert ("every 4th sample (2000 of 8000)" in html) == (step == 4)
    assert "processed in chunks" not in Path(mem["paths"]["report.html"]).read_text()


def test_two_pass_fit_is_checked_by_its_halves(tmp_path):
    """The streaming fit's sigmas hold the disagreement of the recording's two halves (the
    attitude here lags the magnetometer by 2 ms, which the rotation-only fit leaves out)."""
    from pipeline.run.runner import ProcessOptions, process_recording

    path, _ = make(tmp_path / "d.mcap", n=8_000)
    row = process_recording(path, tmp_path / "o", options=ProcessOptions(
        scale_samples=1_000, diagnose=False, write_rerun=False, write_report=False))
    cal = json.loads(Path(row["paths"]["calibration.json"]).read_text())
    split = cal["checks"]["split"]
    d = np.array(split["difference_deg"])
    assert 70.0 < split["split_s"] < 90.0  # the halves meet half way through 160 s
    # d d^T / 2 added to the covariance (stages/estimators/checks.py): sigma >= |d_i| / sqrt 2
    assert np.all(np.array(row["sigma_rotvec_deg"]) >= np.abs(d) / np.sqrt(2) * 0.999)
    # nothing happens between the windows here: no warning about unseen physics
    assert not [w for w in row["warnings"] if "between the analysed windows" in w]


def test_two_pass_estimates_time_offset_and_soft_iron_from_every_sample(tmp_path):
    """--estimate soft_iron,time_offset on a long recording: the streamed sums of every sample
    (stages/estimators/streaming.py) agree with the in-memory ML estimator."""
    from pipeline.run.runner import ProcessOptions, process_recording

    path, R = make(tmp_path / "f.mcap", n=8_000)
    base = dict(terms=frozenset({"time_offset", "soft_iron"}), diagnose=False,
                write_rerun=False, write_report=False)
    mem = process_recording(path, tmp_path / "mem",
                            options=ProcessOptions(scale_samples=None, **base))
    two = process_recording(path, tmp_path / "two",
                            options=ProcessOptions(scale_samples=1_000, **base))
    assert two["estimator"] == "ml-streaming" and windowed(two)
    assert abs(two["time_offset_s"] - mem["time_offset_s"]) < 2e-4  # 0.2 ms
    assert abs(two["time_offset_s"]) > 1e-3  # the 2 ms lag of make() is seen
    cals = [json.loads(Path(r["paths"]["calibration.json"]).read_text()) for r in (mem, two)]
    np.testing.assert_allclose(cals[1]["D"], cals[0]["D"], atol=2e-4)
    np.testing.assert_allclose(two["rotvec_body_mag_deg"], mem["rotvec_body_mag_deg"],
                               atol=0.01)  # deg


def car_parked_recording(path: Path) -> Path:
    """160 s at 50 Hz, turning, 0.5 nT noise, and a car parked beside the sensor from 25 s to
    29 s (an offset of [300, -200, 100] nT): with 1 200 analysed samples, 12 windows of 2 s
    spread over it, the car lies between two of them."""
    from test_scale import B_ENU, ROTVEC_DEG

    from pipeline.core.geometry import li2020_euler_to_quat, quat_conj, quat_rotate, so3_exp
    from pipeline.io.mcap_write import write_recording

    n = 8_000
    s = np.arange(n) / 50.0
    q = li2020_euler_to_quat(2 * np.pi * s / 30.0, np.radians(20) * np.sin(s / 3.0),
                             np.radians(20) * np.sin(s / 4.0))
    y = quat_rotate(quat_conj(q), np.broadcast_to(B_ENU, (n, 3))) @ so3_exp(
        np.radians(ROTVEC_DEG))
    y = y + 0.5 * np.random.default_rng(0).standard_normal((n, 3))
    windows = [(0.5 + i) * s[-1] / 12 for i in range(12)]
    assert all(abs(w - 27.0) > 4.0 for w in windows)  # 25-29 s is between two windows
    y[(s >= 25.0) & (s < 29.0)] += [300.0, -200.0, 100.0]
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 20_000_000
    return write_recording(path, mag_t_ns=t, mag_nT=y, attitude_t_ns=t, q_enu_body=q,
                           chunk_size=32 << 10)


def test_two_pass_warns_of_physics_between_the_analysed_windows(tmp_path, monkeypatch):
    """A disturbance that falls between the diagnosis windows of a long recording: the
    final model fits the windows, and pass 2, which restores every sample, says where it
    does not fit (UNSEEN_RMS_RATIO). The windows about where the field's magnitude stands
    out (pipeline.run.passes) would hold this one; they are capped, so what lies beyond the
    cap is checked here with none."""
    import pipeline.run.passes as passes
    import pipeline.run.plan as plan
    import pipeline.run.source as source
    from pipeline.run.runner import ProcessOptions, process_recording

    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 1_200)  # windows of 2 s
    monkeypatch.setattr(source, "RANGE_MESSAGES", 1_000)  # chunks of 10 s
    monkeypatch.setattr(passes, "PASS_WINDOWS", 0)
    path = car_parked_recording(tmp_path / "g.mcap")
    row = process_recording(path, tmp_path / "o", options=ProcessOptions(
        scale_samples=1_000, write_rerun=False, write_report=False))
    note = [w for w in row["warnings"] if "between the analysed windows" in w]
    assert len(note) == 1, row["warnings"]
    import re

    a, b = (float(x) for x in re.search(r"from (\d+) s to (\d+) s", note[0]).groups())
    assert a <= 27.0 <= b and b - a < 12.0  # the chunk that holds it
    cal = json.loads(Path(row["paths"]["calibration.json"]).read_text())
    assert note[0] in cal["warnings"]
    with open(row["paths"]["corrected_mcap"], "rb") as f:  # the same calibration inside
        (meta,) = [m for m in make_reader(f).iter_metadata() if m.name == "magalign.calibration"]
    assert note[0] in json.loads(meta.metadata["json"])["warnings"]
    # what the analysis saw, for the report's samples paragraph
    seen = cal["checks"]["analysed_samples"]
    assert seen["windows"] >= 2 and 0 < seen["n"] < seen["of"] == row["n_samples"]
    assert cal["checks"]["fit_samples"]["of"] <= seen["n"]


def test_a_step_found_in_a_long_recordings_window_is_restored_at_its_own_time(tmp_path,
                                                                              monkeypatch):
    """The car parked from 25 s to 29 s, caught by a window where |B| stands out: the final
    model's residual on the analysed windows is the noise's, not the car's 374 nT.

    The diagnosis restores the windows it analysed to measure that residual; a step's window
    counts from the recording's first sample, which the windows do not hold (it read 100.6 nT
    when the windows' own first sample was taken as the origin). The residual of every sample
    agrees with it, and the check of the samples between the windows has a true reference.
    """
    import pipeline.run.plan as plan
    import pipeline.run.source as source
    from pipeline.run.runner import ProcessOptions, process_recording

    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 1_200)
    monkeypatch.setattr(source, "RANGE_MESSAGES", 1_000)
    path = car_parked_recording(tmp_path / "g.mcap")
    row = process_recording(path, tmp_path / "o", options=ProcessOptions(
        scale_samples=1_000, write_rerun=False, write_report=False))
    cal = json.loads(Path(row["paths"]["calibration.json"]).read_text())
    diag = json.loads(Path(row["paths"]["diagnosis.json"]).read_text())
    assert [f["effect"] for f in diag["findings"]] == ["hard_iron_step"]
    (a, b), = diag["findings"][0]["where"]["windows_s"]
    assert abs(a - 25.0) < 0.2 and abs(b - 29.0) < 0.2  # s
    assert cal["residual_rms_nT"] < 1.0  # nT; 0.5 nT noise
    assert diag["final"]["residual_rms_nT"] == pytest.approx(cal["residual_rms_nT"])
    metrics = json.loads(Path(row["paths"]["metrics.json"]).read_text())
    assert row["residual_rms_nT"] < 1.0 and metrics["n_used"] == 8_000


def _indep(tmp_path, name, **effects):
    """A recording of the independent generator (tests/indep_gen.py: scipy's Rotation and
    mcap_ros2's writer, no magalign code), 120 s, mag 100 Hz, attitude 50 Hz as Imu."""
    from indep_gen import Spec, write

    spec = Spec(name=name, seed=21, duration_s=120.0, mag_rate_hz=100.0, att_rate_hz=50.0,
                att_phase_s=0.004, att_type="sensor_msgs/msg/Imu", positions=False,
                mag_noise_nT=1.0, att_noise_deg=0.005, effects=effects)
    return write(spec, tmp_path / f"{name}.mcap"), spec


def _both(path, tmp_path, monkeypatch, decimated=6_000):
    import pipeline.run.plan as plan
    import pipeline.run.source as source
    from pipeline.run.runner import ProcessOptions, process_recording

    # 6,000 of 12,000 samples: 12 windows of 5 s
    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", decimated)
    monkeypatch.setattr(source, "RANGE_MESSAGES", 2_000)
    base = dict(write_rerun=False, write_report=False)
    mem = process_recording(path, tmp_path / "mem", options=ProcessOptions(
        scale_samples=None, **base))
    two = process_recording(path, tmp_path / "two", options=ProcessOptions(
        scale_samples=1_000, **base))
    assert windowed(two) and not windowed(mem)
    return mem, two


def _angle_to_truth_deg(row, spec):
    from pipeline.core.geometry import so3_exp, so3_log

    R = so3_exp(np.radians(row["rotvec_body_mag_deg"]))
    return float(np.degrees(np.linalg.norm(so3_log(
        R @ so3_exp(np.radians(spec.rotvec_body_mag_deg)).T))))


def test_two_pass_on_an_independent_null(tmp_path, monkeypatch):
    """Data our simulator did not make, nothing but the misalignment: both paths recover it
    and the two-pass one names nothing and warns of nothing unseen."""
    path, spec = _indep(tmp_path, "null")
    mem, two = _both(path, tmp_path, monkeypatch)
    assert _angle_to_truth_deg(mem, spec) < 0.02 and _angle_to_truth_deg(two, spec) < 0.02
    assert two["findings"] == [] and two["verdict"] == "OK"
    assert not [w for w in two["warnings"] if "between the analysed windows" in w]


def test_two_pass_on_independent_effects(tmp_path, monkeypatch):
    """An independent 12-ms time offset is found by the windows' diagnosis as by the whole
    recording's; a disturbance placed between two spread windows (8-12 s; windows at 2.5-7.5
    and 12.5-17.5 s) stands out of the field's magnitude, so the first pass reads it again
    (pipeline.run.passes) and the two-pass run names it too, with nothing left unseen."""
    path, spec = _indep(tmp_path, "effects",
                        time_offset={"time_offset_s": 0.012},
                        disturbance={"windows_s": [[8.0, 12.0]], "peak_nT": 400.0,
                                     "direction_enu": [0.6, 0.0, 0.8]})
    mem, two = _both(path, tmp_path, monkeypatch)
    for row in (mem, two):
        assert "time_offset" in row["findings"]
        assert abs(row["time_offset_s"] - 0.012) < 5e-4, row["time_offset_s"]  # 0.5 ms
        assert _angle_to_truth_deg(row, spec) < 0.05
    for row in (mem, two):
        assert "disturbance" in row["findings"]
    assert not [w for w in two["warnings"] if "between the analysed windows" in w]
    d = json.loads(Path(two["paths"]["diagnosis.json"]).read_text())
    (w,) = [f["params"]["windows_s"] for f in d["findings"] if f["effect"] == "disturbance"]
    assert w[0][0] < 10.0 < w[0][1] and 6.0 < w[0][0] and w[0][1] < 14.0, w


BURIED = {"local_source": {"position_m": [2.0, 15.0, -1.0], "moment_Am2": [0.0, 20.0, -60.0]},
          "field_gradient": {"G_nT_per_m": [[8.0, 3.0, -2.0], [3.0, -5.0, 4.0],
                                            [-2.0, 4.0, -3.0]]}}


def _survey(tmp_path, position_type):
    """A ground survey of the independent generator: 20 Hz attitude, positions from INSPVA
    (every attitude message) or a 10 Hz NavSatFix channel, a buried dipole and a gradient."""
    from indep_gen import Spec, write

    att = ("novatel_oem7_msgs/msg/INSPVA" if position_type == "inspva"
           else "sensor_msgs/msg/Imu")
    spec = Spec("buried", seed=11, duration_s=110.0, mag_rate_hz=50.0, att_rate_hz=20.0,
                att_type=att, path="survey", position_type=position_type,
                survey_calibration_s=30.0, mag_noise_nT=1.0, att_noise_deg=0.002,
                effects=BURIED)
    return write(spec, tmp_path / f"survey_{position_type}.mcap", chunk_size=8 << 10), spec


@pytest.mark.parametrize("position_type", ["inspva", "navsatfix"])
def test_chunked_restore_with_positions_equals_the_whole_recording_restore(
        tmp_path, position_type):
    """The spatial terms (a located source, a gradient, a lever arm) restored chunk by chunk,
    each row waiting for the positions that bracket it, give the whole recording's restore
    (to 1e-6 nT), whether the positions come with the attitude or on their own channel."""
    from pipeline.app.commands.diagnose import diagnose_file

    path, _ = _survey(tmp_path, position_type)
    cal = diagnose_file(path).need_calibration()
    assert {"local_source", "field_gradient"} <= set(cal.effects), set(cal.effects)
    cal = cal.replace(effects={**cal.effects,
                               "lever_arm": {"lever_arm_body_m": [0.05, -0.02, 0.3]}})
    rec, parts, held, chunks = chunked(path, cal, 300, positions=True)
    assert rec.position is not None
    assert len(chunks) > 10 and all(c.position is not None for c in chunks)
    assert held < 2_000  # bounded: about a chunk, not the file
    whole = restore_samples(rec, cal)
    # the terms matter: without positions the residual differs by far more than 1e-6 nT
    _, bare, _, _ = chunked(path, cal, 300)
    got = np.concatenate([p.residual_nT for p in bare])
    assert np.nanmax(np.abs(got - whole.residual_nT)) > 50.0
    assert_restores_alike(parts, whole)


def test_two_pass_keeps_the_spatial_terms_of_a_survey(tmp_path, monkeypatch):
    """A survey with NavSatFix positions processed in two passes: the diagnosis windows carry
    their positions, so the buried object is located as in memory (within 0.5 m of the
    truth) and every sample is restored with it; the residual over every sample is the
    in-memory one's."""
    from indep_gen import truth

    path, spec = _survey(tmp_path, "navsatfix")
    mem, two = _both(path, tmp_path, monkeypatch, decimated=6_000)
    tr = np.asarray(truth(spec)["effects"]["local_source"]["position_m"])
    for row in (mem, two):
        assert "local_source" in row["findings"], row["findings"]
        assert "field_gradient" in row["findings"], row["findings"]
        diag = json.loads(Path(row["paths"]["diagnosis.json"]).read_text())
        (src,) = [f for f in diag["findings"] if f["effect"] == "local_source"]
        assert src["params"]["position_frame"] == "enu"
        assert np.linalg.norm(np.asarray(src["params"]["position_m"]) - tr) < 0.5  # m
        assert _angle_to_truth_deg(row, spec) < 0.05
    assert two["residual_rms_nT"] == pytest.approx(mem["residual_rms_nT"], rel=0.05)
    assert two["residual_rms_nT"] < 3.0  # nT, against 1 nT of noise: the dipole restored


def test_two_pass_report_maps_the_path(tmp_path, monkeypatch):
    """The report of a survey processed in two passes draws the path from every k-th
    position, with the located source on it (map.json beside the report)."""
    import pipeline.run.plan as plan
    import pipeline.run.source as source
    from pipeline.run.runner import ProcessOptions, process_recording

    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 6_000)
    monkeypatch.setattr(source, "RANGE_MESSAGES", 2_000)
    path, _ = _survey(tmp_path, "navsatfix")
    row = process_recording(path, tmp_path / "two", options=ProcessOptions(
        scale_samples=1_000, write_rerun=False))
    assert windowed(row)
    folder = Path(row["paths"]["report.html"]).parent
    m = json.loads((folder / "map.json").read_text())
    assert "local_source" in row["findings"]
    assert len(json.dumps(m)) > 1_000 and "sources" in json.dumps(m)
    assert 'id=map' in Path(row["paths"]["report.html"]).read_text()


def test_a_survey_that_starts_with_a_turn_in_place_has_positions_in_its_header(tmp_path):
    """A survey's first minute is a calibration turn at the first fix: its positions in local
    ENU metres are all zero there, yet INSPVA wrote latitudes and longitudes. The header
    (read from the first block of each channel, which holds only that minute here) must say
    the recording has positions: the two-pass run of a long recording writes targets.csv and
    anomaly.nc only when it does (a 2-hour 200 Hz survey wrote neither)."""
    spec = Spec("turn_first", seed=3, duration_s=90.0, mag_rate_hz=50.0, att_rate_hz=20.0,
                att_type="novatel_oem7_msgs/msg/INSPVA", path="survey",
                position_type="inspva", survey_calibration_s=60.0, mag_noise_nT=1.0)
    path = write(spec, tmp_path / "turn_first.mcap", chunk_size=8 << 10)
    whole = read_recording(path)
    assert whole.position is not None
    first = whole.position.t_ns[0]
    still = whole.position.t_ns < first + int(50e9)
    assert np.all(whole.position.p_m[still] == 0.0)  # standing at the first fix
    header = read_recording_header(path)
    assert header.position is not None
    assert header.position.frame == whole.position.frame
