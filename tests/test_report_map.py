"""The report's model line, event shading, sample counts and the plan view of the path."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated
from pipeline.model.calibration import Calibration
from pipeline.model.forward import evaluate
from stages.context import Context
from stages.ingest import Ingest
from stages.report import counts_sentence, make_figures, predicted_field, write_report
from stages.report_map import event_windows, read_map_json
from stages.restore import restore_samples

G = [[300.0, 100.0, 0.0], [100.0, -200.0, 50.0], [0.0, 50.0, -100.0]]  # nT/m, traceless


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """A recording moving through a field gradient, with positions, and its true model."""
    tmp = tmp_path_factory.mktemp("map")
    sc = {"name": "moving", "timing": {"duration_s": 30.0, "mag_rate_hz": 50.0,
                                       "attitude_rate_hz": 50.0},
          "motion": {"profile": "multiaxis"}, "field": {"enu_nT": [0.0, 20000.0, -40000.0]},
          "trajectory": {"amplitude_m": [2.0, 1.5, 0.2]},
          "effects": {"field_gradient": {"G_nT_per_m": G}},
          "noise": {"mag_sigma_nT": 1.0},
          "output": {"attitude_type": "geometry_msgs/msg/PoseStamped"}}
    sim = simulate(scenario_from_dict(sc))
    path = write_simulated(sim, tmp / "moving.mcap")
    rec = Ingest().run(Context(source=str(path))).recording
    assert rec.position is not None
    ref = np.asarray(sim.scenario.trajectory.center_m, float)
    cal = Calibration(R_body_mag=sim.truth.R_body_mag, sigma_rotvec_deg=[0.01] * 3,
                      B_enu_nT=sim.truth.B_enu_nT, estimator="truth", residual_rms_nT=1.0,
                      n_samples=len(rec.mag),
                      effects={"field_gradient": {"G_nT_per_m": G,
                                                  "reference_position_m": ref.tolist(),
                                                  "position_frame": "attitude_source_local"}})
    ctx = SimpleNamespace(recording=rec, calibration=cal, restored=restore_samples(rec, cal))
    return tmp, ctx


def test_model_line_is_the_forward_models_field(moving):
    """The black line: |B_enu + F| where the sensor was, as pipeline.model.forward predicts."""
    _, ctx = moving
    rec, cal, rs = ctx.recording, ctx.calibration, ctx.restored
    enu, norm = predicted_field(rs, cal)
    ev = evaluate(cal.forward_model(), rs.t_ns, rec.attitude,
                  position=rec.position)
    ok = rs.valid & ev.valid
    want = ev.field_enu_nT[ok]
    assert np.nanmax(np.abs(norm[ok] - np.linalg.norm(want, axis=1))) < 1e-6
    assert np.nanmax(np.abs(enu[ok] - want)) < 1e-6
    # the field changes from place to place by far more than the noise: not a flat line
    assert np.nanmax(norm) - np.nanmin(norm) > 200.0


def test_map_in_report_and_map_json(moving):
    tmp, ctx = moving
    diag = {"findings": [{"effect": "disturbance", "params": {}, "where": {
        "windows_s": [[10.0, 12.0]], "axes": ["x"], "frame": "enu"}},
        {"effect": "local_source", "params": {"position_m": [0.5, 0.2, 1.0],
                                               "position_frame": "attitude_source_local",
                                               "moment_Am2": [0.1, 0.0, 0.0]},
         "sigma": {"position_m": [0.1, 0.2, 0.3]}, "where": {"windows_s": [[0.0, 30.0]]}}]}
    out = tmp / "out"
    out.mkdir()
    figs = make_figures(ctx.recording, ctx.calibration, restored=ctx.restored,
                        diagnosis=diag)
    assert "fig_map.png" in figs
    write_report(out, ctx.recording, ctx.calibration, restored=ctx.restored, diagnosis=diag,
                 figures=figs)
    text = (out / "report.html").read_text(encoding="utf-8")
    assert "id=map" in text and 'alt="fig_map.png"' in text
    m = read_map_json(out / "map.json")
    assert m is not None and m["frame"] == "attitude_source_local"
    assert 2 <= len(m["path"]) <= 1500 and len(m["path"][0]) == 6
    # the restored field follows the model's along the path (the gradient is in both)
    path = np.asarray(m["path"])
    assert np.corrcoef(path[:, 4], path[:, 5])[0, 1] > 0.95
    # the event where the sensor was; the source with its sigma
    (e,) = m["events"]
    assert e["effect"] == "disturbance" and e["start_s"] == 10.0
    (s,) = m["sources"]
    assert s["position_m"] == [0.5, 0.2, 1.0] and s["sigma_m"] == [0.1, 0.2, 0.3]
    json.dumps(m)  # plain JSON


def test_event_windows_in_time_order():
    d = {"findings": [
        {"effect": "hard_iron_step", "where": {"windows_s": [[50.0, 60.0]]}},
        {"effect": "time_offset", "where": {"windows_s": [[0.0, 100.0]]}},
        {"effect": "hard_iron_step", "where": {"windows_s": [[5.0, 6.0], [20.0, 21.0]]}},
        {"effect": "local_source", "where": {"windows_s": [[0.0, 99.0]]}}]}
    # a term present throughout is no event
    assert event_windows(d, 100.0) == [(5.0, 6.0, "hard_iron_step"),
                                       (20.0, 21.0, "hard_iron_step"),
                                       (50.0, 60.0, "hard_iron_step")]
    assert event_windows(None) == []


def test_counts_add_up(moving):
    """Received = without attitude + restored; repeats + new readings = restored."""
    _, ctx = moving
    rs = ctx.restored
    text = counts_sentence(rs, ctx.calibration)
    n = lambda x: f"{x:,}".replace(",", "\u2009")  # noqa: E731
    assert f"Of {n(rs.n_total)} magnetometer samples received, " \
           f"{n(rs.n_total - rs.n_valid)} have no usable attitude and {n(rs.n_valid)} are " \
           "restored" in text
    held = ctx.calibration.replace(sample_hold={"native_rate_hz": 40.0,
                                                "repeated_fraction": 0.2})
    text = counts_sentence(rs, held)
    import re

    m = re.search(r"are restored = ([\d\u2009]+) repeats .* \+ ([\d\u2009]+) new readings", text)
    assert m is not None
    a, b = (int(x.replace("\u2009", "")) for x in m.groups())
    assert a + b == rs.n_valid
    assert "left out of the fit only" in text
    # the fit's count is a sentence of its own, not a clause on the metrics' count
    assert "which used" not in text and "The calibration's fit used" in text


def test_rerun_path_in_3d(moving):
    """The plan view in rerun: the path coloured by the field, sources and events, read back."""
    from test_outputs import rrd_columns

    from stages.write_rerun import write_rrd

    tmp, ctx = moving
    diag = {"findings": [{"effect": "disturbance", "params": {}, "where": {
        "windows_s": [[10.0, 12.0]], "axes": ["x"], "frame": "enu"}},
        {"effect": "local_source", "params": {"position_m": [0.5, 0.2, 1.0]},
         "sigma": {"position_m": [0.1, 0.2, 0.3]}, "where": {"windows_s": [[0.0, 30.0]]}}]}
    rrd = write_rrd(ctx.recording, ctx.calibration, tmp / "moving.rrd", diagnosis=diag,
                    restored=ctx.restored)
    cols = rrd_columns(rrd)
    (pts,) = cols["/map/path"]["Points3D:positions"]
    (rgb,) = cols["/map/path"]["Points3D:colors"]
    assert 2 <= len(pts) <= 1500 and len(rgb) == len(pts)
    assert len(set(rgb)) > 10  # coloured by the field, not one colour
    m = read_map_json(tmp / "out" / "map.json") if (tmp / "out" / "map.json").is_file() \
        else None
    if m is not None:  # the same path as the report's plan view
        assert np.allclose(np.asarray(pts)[:, :2], np.asarray(m["path"])[:, 1:3], atol=1e-3)
    assert np.allclose(cols["/map/sources"]["Ellipsoids3D:centers"][0], [[0.5, 0.2, 1.0]])
    assert np.allclose(cols["/map/sources"]["Ellipsoids3D:half_sizes"][0], [[0.1, 0.2, 0.3]])
    (labels,) = cols["/map/events"]["Points3D:labels"]
    assert labels == ["disturbance 10-12 s"]


def test_a_fit_of_every_message_is_not_said_to_leave_the_repeats_out():
    """lab_02: the diagnosis kept its model on every message; 45 383 are no new readings."""
    from types import SimpleNamespace

    from stages.restore import RestoreTotals

    totals = RestoreTotals(n_total=47639, n_valid=45440, n_used=45436)
    part = SimpleNamespace(t_ns=[0])  # a chunk: the counts come from ``totals``
    held = {"native_rate_hz": 202.2, "repeated_fraction": 0.29}
    every = SimpleNamespace(checks={"fit_samples": {"n": 11346, "stride": 4, "of": 45383}},
                            sample_hold=held, n_samples=11346)
    text = counts_sentence(part, every, totals)
    assert "left out of the fit" not in text and "new readings" not in text.split(". ")[-1]
    assert "The calibration's fit used 45\u2009383 of the 45\u2009440 restored samples" in text
    fewer = SimpleNamespace(checks={"fit_samples": {"n": 8000, "stride": 4, "of": 32000}},
                            sample_hold=held, n_samples=8000)
    text = counts_sentence(part, fewer, totals)
    assert "the repeats are left out of the fit only" in text and "new readings" in text


def test_a_long_recordings_fit_says_its_analysis_saw_windows_of_it():
    """The 2-hour survey: the fit used the windows' samples, not "too close to the ends"."""
    from types import SimpleNamespace

    from stages.restore import RestoreTotals

    totals = RestoreTotals(n_total=1_440_000, n_valid=1_440_000, n_used=1_440_000)
    part = SimpleNamespace(t_ns=[0])
    cal = SimpleNamespace(checks={"fit_samples": {"n": 12000, "stride": 14, "of": 167_555},
                                  "analysed_samples": {"n": 168_000, "of": 1_440_000,
                                                       "windows": 18}},
                          sample_hold=None, n_samples=12000)
    text = counts_sentence(part, cal, totals)
    assert "167\u2009555 of the 1\u2009440\u2009000 restored samples" in text
    assert "sees 168\u2009000 magnetometer samples in 18 windows of it" in text
    # 445 of the windows' samples were not predicted: only those lie near the ends
    assert "the 445 others lie too close" in text
    short = SimpleNamespace(checks={"fit_samples": {"n": 12000, "stride": 14, "of": 167_555}},
                            sample_hold=None, n_samples=12000)
    assert "windows of it" not in counts_sentence(part, short, totals)


def test_the_table_says_a_long_recordings_fit_saw_its_windows():
    """The calibration table's samples row names the analysed windows, not "every sample"."""
    from types import SimpleNamespace

    from stages.report import samples_text

    seen = {"n": 1765, "of": 8000, "windows": 13}
    long = SimpleNamespace(checks={"fit_samples": {"n": 1765, "stride": 1, "of": 1765},
                                   "analysed_samples": seen}, n_samples=1765)
    assert samples_text(long) == ("1765 (every sample with an attitude in the 13 analysed "
                                  "windows, 1765 of the recording's 8000 magnetometer samples)")
    short = SimpleNamespace(checks={"fit_samples": {"n": 1765, "stride": 1, "of": 1765}},
                            n_samples=1765)
    assert samples_text(short) == "1765 (every sample with an attitude)"


def test_a_percentage_below_one_is_not_printed_as_nothing():
    """The headline's fluctuation ratios: 0.031 % left is not "0 %"."""
    from stages.report import percent_text

    assert percent_text(41.43) == "41 %"
    assert percent_text(0.0312) == "0.031 %"
    assert percent_text(0.0) == "0 %"
    assert percent_text(1.0) == "1 %"
