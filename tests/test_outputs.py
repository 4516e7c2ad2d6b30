"""Outputs: corrected MCAP, rerun recording, the whole pipeline on one recording, view."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated
from pipeline.core.errors import OutputError
from pipeline.core.recording import Segment, SegmentKind
from pipeline.model.calibration import Calibration
from pipeline.run.runner import ProcessOptions, process_recording
from stages.context import Context
from stages.ingest import Ingest
from stages.write_mcap import write_corrected_mcap
from stages.write_rerun import write_rrd

RERUN = str(Path(sys.executable).with_name("rerun"))
B_ENU = [1300.0, 15000.0, -49000.0]


def _scenario(name: str, motion: dict, duration_s: float, *, json_family: bool = False,
              heading_sigma_deg: float = 0.01, seed: int = 7) -> dict:
    d = {
        "name": name,
        "seed": seed,
        "timing": {"mag_rate_hz": 50.0, "attitude_rate_hz": 50.0, "attitude_phase_s": 0.003},
        "motion": motion,
        "field": {"enu_nT": B_ENU},
        "sensor": {"misalignment_rotvec_deg": [1.2, -1.0, 1.2]},  # |rotvec| = 1.98 deg
        "noise": {"mag_sigma_nT": 0.5, "heading_sigma_deg": heading_sigma_deg,
                  "pitch_roll_sigma_deg": 0.005},
        "output": {"mag_log_delay_s": 0.002, "attitude_log_delay_s": 0.015},
    }
    if duration_s:
        d["timing"]["duration_s"] = duration_s
    if json_family:
        d["output"].update({"mag_type": "magalign.Magnetometer",
                            "attitude_type": "magalign.AttitudeQuaternion"})
    return d


ROTATION = {"profile": "multiaxis", "yaw_rate_deg_s": 12.0, "pitch_amplitude_deg": 25.0,
            "pitch_period_s": 7.0, "roll_amplitude_deg": 25.0, "roll_period_s": 11.0}
SURVEY = {"profile": "survey_lines", "heading_deg": 90.0, "n_lines": 2,
          "line_duration_s": 20.0, "turn_duration_s": 10.0, "turn_deg": 180.0,
          "wobble_deg": 1.5, "wobble_period_s": 6.0}


def _write(tmp_path: Path, d: dict) -> tuple[Path, object]:
    sim = simulate(scenario_from_dict(d))
    return write_simulated(sim, tmp_path / f"{d['name']}.mcap"), sim


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _truth_cal(sim) -> Calibration:
    tr = sim.truth
    return Calibration(R_body_mag=tr.R_body_mag, sigma_rotvec_deg=[0.01] * 3,
                       B_enu_nT=tr.B_enu_nT, estimator="truth", residual_rms_nT=0.5,
                       n_samples=len(sim.recording.mag))


def rrd_rows(path: Path) -> Counter:
    """Rows per entity of an .rrd, as rerun's own reader (``rerun rrd print``) reports."""
    out = subprocess.run([RERUN, "rrd", "print", str(path)], capture_output=True, text=True,
                         check=True, timeout=120).stdout
    rows: Counter = Counter()
    for m in re.finditer(r"^Chunk\(\S+\) with (\d+) rows \([^)]*\) - (\S+) - ", out, re.M):
        rows[m.group(2)] += int(m.group(1))
    return rows


def rrd_columns(path: Path) -> dict[str, dict[str, list]]:
    """Every column of an .rrd per entity, read back with rerun's own reader."""
    from rerun.chunk import RrdReader

    cols: dict[str, dict[str, list]] = {}
    for ch in RrdReader(str(path)).stream():
        batch = ch.to_record_batch()
        for name in batch.schema.names:
            cols.setdefault(str(ch.entity_path), {}).setdefault(name, []).extend(
                batch.column(name).to_pylist())
    return cols


@pytest.mark.parametrize("json_family", [False, True], ids=["ros2", "json"])
def test_corrected_mcap(tmp_path, json_family):
    src, sim = _write(tmp_path, _scenario("rec", ROTATION, 12.0, json_family=json_family))
    before = _sha(src)
    rec = Ingest().run(Context(source=str(src))).recording
    cal = _truth_cal(sim)
    out = write_corrected_mcap(rec, cal, tmp_path / "out" / "rec.corrected.mcap")
    assert _sha(src) == before  # the input's bytes are unchanged
    n_mag = len(rec.mag)
    with open(out, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        counts = Counter(ch.topic for _, ch, _ in
                         ((s, c, m) for s, c, m in reader.iter_messages()))
        summary = reader.get_summary()
        meta = list(reader.iter_metadata())
        att = list(reader.iter_attachments())
    with open(src, "rb") as f:
        in_counts = Counter(c.topic for _, c, _ in make_reader(f).iter_messages())
    for topic, k in in_counts.items():
        assert counts[topic] == k
    for suffix in ("calibrated", "enu", "residual", "magnitude"):
        assert counts[f"/mag/{suffix}"] == n_mag  # one message per magnetometer sample
    # four channels with one message per magnetometer sample, and one /tf_static message
    assert summary.statistics.message_count == sum(in_counts.values()) + 4 * n_mag + 1
    (m,) = [m for m in meta if m.name == "magalign.calibration"]
    assert Calibration.from_json(m.metadata["json"]).estimator == "truth"
    (a,) = [a for a in att if a.name == "calibration.json"]
    assert json.loads(a.data)["format"] == "magalign.calibration/1"
    # copied messages are byte-identical to the input's
    with open(src, "rb") as f1, open(out, "rb") as f2:
        a_msgs = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f1).iter_messages()]
        b_msgs = {(c.topic, m.log_time, m.data) for _, c, m in make_reader(f2).iter_messages()}
    assert all(x in b_msgs for x in a_msgs)
    # /mag/enu values: the restored field (true calibration: B_enu within noise)
    if json_family:
        with open(out, "rb") as f:
            enu = [json.loads(m.data) for _, c, m in make_reader(f).iter_messages(
                topics=["/mag/enu"])]
        assert enu[0]["frame_id"] == "enu"
        v = np.array([e["mag_nT"] for e in enu])
    else:
        with open(out, "rb") as f:
            r = make_reader(f, decoder_factories=[DecoderFactory()])
            msgs = [d for _, _, _, d in r.iter_decoded_messages(topics=["/mag/enu"])]
        assert msgs[0].header.frame_id == "enu"
        v = np.array([[d.magnetic_field.x, d.magnetic_field.y, d.magnetic_field.z]
                      for d in msgs]) * 1e9  # tesla on the wire
    ok = np.isfinite(v).all(axis=1)
    assert ok.mean() > 0.95
    assert np.abs(np.median(v[ok], axis=0) - B_ENU).max() < 5.0
    # never over an input
    with pytest.raises(OutputError):
        write_corrected_mcap(rec, cal, src)
    assert _sha(src) == before


def test_corrected_mcap_opens_in_rerun(tmp_path):
    src, sim = _write(tmp_path, _scenario("rec", ROTATION, 8.0))
    rec = Ingest().run(Context(source=str(src))).recording
    out = write_corrected_mcap(rec, _truth_cal(sim), tmp_path / "rec.corrected.mcap")
    rrd = tmp_path / "conv.rrd"
    subprocess.run([RERUN, "mcap", "convert", str(out), "-o", str(rrd)], check=True,
                   capture_output=True, timeout=120)
    rows = rrd_rows(rrd)
    # rerun decodes sensor_msgs/MagneticField itself: one row per message
    assert rows["/mag/enu"] - 1 == len(rec.mag)  # plus one channel-description row
    assert rows["/mag/residual"] == rows["/mag/enu"] == rows["/mag/calibrated"]
    assert rows["/__mcap_metadata"] >= 1


def test_rrd_read_back(tmp_path):
    src, sim = _write(tmp_path, _scenario("rec", ROTATION, 8.0))
    before = _sha(src)
    rec = Ingest().run(Context(source=str(src))).recording
    t = rec.mag.t_ns
    segs = (Segment(int(t[0]), int(t[len(t) // 2]), SegmentKind.ROTATION),
            Segment(int(t[len(t) // 2]), int(t[-1]), SegmentKind.STATIC))
    diag = {"findings": [{"effect": "disturbance", "params": {}, "where": {
        "windows_s": [[1.0, 2.0]], "axes": ["x"], "frame": "enu"}}]}
    (tmp_path / "out").mkdir()
    rrd = write_rrd(rec, _truth_cal(sim), tmp_path / "out" / "rec.rrd", segments=segs,
                    diagnosis=diag)
    assert rrd.name == "rec.rrd" and _sha(src) == before
    assert not list(rrd.parent.glob(".*.tmp"))  # the temporary name is gone
    rows = rrd_rows(rrd)
    n = len(rec.mag)
    for c in ("east", "north", "up"):
        assert n - 5 <= rows[f"/field/calibrated/{c}"] <= n
        assert rows[f"/field/uncalibrated/{c}"] == rows[f"/field/calibrated/{c}"]
    for a in "xyz":
        assert rows[f"/mag/raw/{a}"] == n + 1  # + the static SeriesLines row
    assert rows["/trajectory/after"] == 1 and rows["/world/body"] > 0
    # the body and the field in 3D: the field arrows move with the body
    assert rows["/world/body/field_after"] == rows["/world/body"] + 1  # + static style row
    assert rows["/world/field/reference"] == 1 and rows["/world/enu_axes"] == 1
    # segments and the diagnosed event as labelled spans: a start per span, an end where
    # no other starts (the two segments touch), plus the static colour configuration
    assert rows["/segments/spans"] == 3 + 1
    assert rows["/diagnosis/events"] == 2 + 1
    assert "/segments/index" not in rows
    assert any(e.startswith("/view/") for e in rows)  # the default blueprint is stored
    # the values, read back with rerun's own reader: labelled spans, the report's colours
    from pipeline.core import style

    cols = rrd_columns(rrd)
    states = cols["/segments/spans"]["StateChange:state"]
    assert states == [["0: rotation 4.0 s"], ["1: static 4.0 s"], []]
    assert cols["/diagnosis/events"]["StateChange:state"] == [["disturbance"], []]

    def rgba(hex_colour: str) -> int:
        r, g, b = style.rgb(hex_colour)
        return (r << 24) | (g << 16) | (b << 8) | 0xFF

    assert cols["/segments/spans"]["StateConfiguration:colors"] == [
        [rgba(style.SEGMENT["rotation"]), rgba(style.SEGMENT["static"])]]
    assert cols["/world/body/field_after"]["Arrows3D:colors"][0] == [rgba(style.AFTER)]
    assert cols["/attitude/heading_deg"]["SeriesLines:colors"][0] == [
        rgba(style.ANGLE["heading"])]


def test_spans_end_where_nothing_follows():
    from stages.write_rerun import spans

    assert spans([(10, 20, "b"), (0, 10, "a"), (30, 40, "c")]) == [
        (0, "a"), (10, "b"), (20, None), (30, "c"), (40, None)]


def test_simulated_survey_ratio_below_two_percent(tmp_path):
    # The paper's field result: ratio of the fluctuation range 0.9-1.3 % after calibration.
    # Calibrate on a rotation run, restore a survey line with that calibration (2 deg
    # misalignment, navigation-grade attitude: 0.01 deg heading noise).
    cal_rec, _ = _write(tmp_path, _scenario("calib", ROTATION, 40.0))
    survey, _ = _write(tmp_path, _scenario("line", SURVEY, 0.0, seed=9))
    opts = ProcessOptions(diagnose=False, write_rerun=False, write_report=False)
    row = process_recording(cal_rec, tmp_path / "res", options=opts)
    cal_path = Path(row["paths"]["calibration.json"])
    assert np.linalg.norm(row["rotvec_body_mag_deg"]) == pytest.approx(1.98, abs=0.05)
    h = _sha(survey)
    row2 = process_recording(survey, tmp_path / "res", options=ProcessOptions(
        calibration_path=str(cal_path), write_rerun=False, write_report=False))
    assert _sha(survey) == h
    for c in "xyz":
        assert row2[f"ratio_pct_{c}"] < 2.0, row2
    files = {p.name for p in (tmp_path / "res" / "line").iterdir()}
    assert {"calibration.json", "metrics.json", "metrics.parquet",
            "line.corrected.mcap"} <= files


def test_view_without_display_says_so(tmp_path):
    (tmp_path / "x.rrd").write_bytes(b"")
    env = {"PATH": "/usr/bin:/bin"}
    p = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "view", str(tmp_path)],
                       capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and "no display" in p.stderr
    p = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "view", str(tmp_path / "nope")],
                       capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 2 and "no such file" in p.stderr
