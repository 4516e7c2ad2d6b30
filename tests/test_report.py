"""Report: PNG figures and a self-contained report.html."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np

from pipeline.core.geometry import quat_normalize, rotvec_to_quat, so3_exp
from pipeline.core.recording import AttitudeSeries, Recording, Segment, SegmentKind, VectorSeries
from pipeline.model.calibration import Calibration
from stages.metrics import compute_metrics
from stages.report import make_figures, write_report
from stages.restore import restore_samples

T0 = 1_767_225_600_000_000_000
PNG = b"\x89PNG\r\n\x1a\n"


def _ctx(tmp_path):
    n = 600
    t = T0 + np.arange(n, dtype=np.int64) * 50_000_000
    ts = np.arange(n) / 20.0
    q = quat_normalize(rotvec_to_quat(np.stack(
        [0.4 * np.sin(0.5 * ts), 0.3 * np.sin(0.8 * ts), 0.4 * ts], -1)))
    cal = Calibration(R_body_mag=so3_exp([0.02, -0.01, 0.03]),
                      sigma_rotvec_deg=[0.01, 0.02, np.inf],
                      B_enu_nT=[1300.0, 15000.0, -49000.0], estimator="ml", residual_rms_nT=0.5,
                      n_samples=n, unobservable_axes_body=([0.0, 0.0, 1.0],),
                      warnings=("rotation about body z is not observable <here>",))
    y = cal.predict(t, AttitudeSeries(t, q))
    y = y + 0.5 * np.random.default_rng(0).standard_normal((n, 3))
    rec = Recording(path=str(tmp_path / "rec.mcap"), channels=(), mag=VectorSeries(t, y),
                    mag_topic="/mag", attitude=AttitudeSeries(t, q), attitude_topic="/att")
    seg = (Segment(int(t[0]), int(t[300]), SegmentKind.ROTATION),)
    rs = restore_samples(rec, cal)
    return SimpleNamespace(recording=rec, calibration=cal, segments=seg, restored=rs,
                           metrics=compute_metrics(rs, seg))


def test_figures_are_png(tmp_path):
    ctx = _ctx(tmp_path)
    figs = make_figures(ctx.recording, ctx.calibration, ctx.segments)
    assert set(figs) == {"fig_enu.png", "fig_residual.png", "fig_sphere.png",
                         "fig_attitude.png"}
    assert all(b.startswith(PNG) and len(b) > 5000 for b in figs.values())


def _png_size(b: bytes) -> tuple[int, int]:
    return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")


def test_band_keeps_the_full_range():
    """A long series is drawn as bins: min and max of every sample, the mean between."""
    from stages.report import bins

    t = np.arange(100_000) / 285.0
    v = np.sin(t) + np.where(np.arange(t.size) == 51_234, 50.0, 0.0)  # one spike
    v[10:20] = np.nan
    tm, lo, hi, mean, k = bins(t, v, 1000)
    assert len(tm) <= 1000 and k == 100
    assert np.nanmax(hi) == np.nanmax(v)  # the spike survives decimation
    assert np.nanmin(lo) == np.nanmin(v)
    assert np.all((lo <= mean) & (mean <= hi))


def test_own_scale_panel_only_when_it_shows_more():
    """The "after alone" panel is drawn only when "before" spans far more than "after"."""
    from stages.report import needs_own_scale

    rng = np.random.default_rng(1)
    after = 15000 + rng.standard_normal(5000)
    assert needs_own_scale(after + np.linspace(0, 500, 5000), after)
    assert not needs_own_scale(after + 0.1 * rng.standard_normal(5000), after)
    assert not needs_own_scale(np.full(10, np.nan), after)


def test_report_is_self_contained(tmp_path):
    ctx = _ctx(tmp_path)
    path = write_report(tmp_path / "out", ctx.recording, ctx.calibration, ctx.metrics, None,
                        ctx.segments, restored=ctx.restored)
    html = (tmp_path / "out" / "report.html").read_text()
    # every src/href is an inline data: URI; nothing to fetch
    refs = re.findall(r"""(?:src|href)\s*=\s*["']?([^"'\s>]+)""", html, re.I)
    assert refs and all(r.startswith("data:image/png;base64,") for r in refs)
    assert "<link" not in html.lower() and "<script" not in html.lower()
    assert "Metrics (Li et al. 2020, Table 4)" in html and "ratio %" in html
    assert "&lt;here&gt;" in html  # warnings are escaped
    assert "\u00b1 &infin;" not in html
    assert (tmp_path / "out" / "fig_enu.png").read_bytes().startswith(PNG)
    assert path == tmp_path / "out" / "report.html"
    # zoom without script: every figure toggles with a checkbox
    assert html.count("<input type=checkbox class=zoom") == html.count("<img ") == 4
    # provenance
    sec = html[html.index("<h2>Provenance</h2>"):]
    assert "input sha256" in sec and "magalign</dt>" in sec
    import hashlib

    digest = hashlib.sha256(open(ctx.recording.path, "rb").read()).hexdigest() \
        if __import__("os").path.exists(ctx.recording.path) else "unreadable"
    assert digest in sec


def test_times_units_and_minus(tmp_path):
    from stages.report import render_html

    ctx = _ctx(tmp_path)
    cal = ctx.calibration.replace(time_offset_s=0.0152, sigma_time_offset_s=0.0004)
    html = render_html(ctx.recording, cal, ctx.metrics, None, {}, prov={})
    assert "time offset &tau; (ms)" in html and "15.20 \u00b1 0.40" in html
    assert "(s)</th>" not in html  # tau only in ms
    # the metrics table names each segment's start and end, with UTC beside
    assert "<th rowspan=2>start</th>" in html and "00:00:15 </small>" not in html
    assert "15.0 s <small>00:00:15</small>" in html  # segment end at 300 samples of 20 Hz
    assert "\u221249000.0" in html and "-49000" not in html  # a true minus sign


def _diag():
    return {
        "format": "magalign.diagnosis/1",
        "baseline": {"effects": [], "residual_rms_nT": 12.5, "heldout_rms_nT": 12.9},
        "final": {"effects": ["hard_iron_step"], "residual_rms_nT": 0.51,
                  "heldout_rms_nT": 0.52},
        "findings": [
            {
                "effect": "hard_iron_step",
                "params": {"windows_s": [[w, w + 1.0]], "offset_nT": [300.123456, -200.0, o]},
                "sigma": {}, "evidence": {"delta_bic": -812.25, "rms_before_nT": 12.5 - i,
                                          "rms_after_nT": 11.5 - i,
                                          "heldout_rms_before_nT": 12.9 - i,
                                          "heldout_rms_after_nT": 11.9 - i},
                "where": {"windows_s": [[w, w + 1.0]], "axes": ["x"], "frame": "mag"},
                "explanation": "a magnet brought near the sensor",
            }
            for i, (w, o) in enumerate(((2.0, 100.0), (3.0, 90.0), (4.0, 80.0), (5.0, 70.0)))
        ] + [{
            "effect": "time_offset", "params": {"time_offset_s": -0.0021},
            "sigma": {"time_offset_s": 0.0001},
            "evidence": {"delta_bic": -40.0, "heldout_rms_before_nT": 8.9,
                         "heldout_rms_after_nT": 0.52},
            "where": {"windows_s": [[0.0, 30.0]], "axes": ["x"], "frame": "mag"},
            "explanation": "clocks"}],
        "not_identifiable": [{"effect": "soft_iron", "reason": "constant rotation rate"}],
    }


def test_diagnosis_section(tmp_path):
    from stages.report import render_html

    ctx = _ctx(tmp_path)
    html = render_html(ctx.recording, ctx.calibration, ctx.metrics, _diag(), {}, prov={})
    sec = html[html.index("<h2>What the diagnosis found</h2>"):html.index("<h2>Field")]
    # four steps of one magnet are one event with its edges, in seconds and UTC
    assert sec.count("A magnet or magnetised object") == 1
    assert "found as 4 steps" in sec and "between 2.0 s and 6.0 s" in sec
    assert "2.0 s to 6.0 s (00:00:02 to 00:00:06 UTC)" in sec
    assert "edges 2.0\u20133.0 s; 3.0\u20134.0 s" in sec
    assert "on held-out data from 12.9 to 8.9 nT" in sec  # first before, last after
    # a global effect as a sentence with units; no raw JSON, no BIC jargon in the rows
    assert "early by 2.10 \u00b1 0.10 ms" in sec  # the calibration table's digits
    assert "windows_s" not in sec and "{" not in sec and "BIC</th>" not in sec
    assert "very strong" in sec and "constant rotation rate" in sec


def test_findings_in_the_order_the_evidence_was_measured():
    """The table, diagnosis.json and the terminal: one order, the magnet found first first."""
    from stages.diagnose.result import Diagnosis, Finding
    from stages.report_text import rows

    d = _diag()
    rs = rows(d, 0)
    assert [r.effects for r in rs] == [["hard_iron_step"], ["time_offset"]]
    # the improvements chain: each row starts where the one before it ended
    assert "from 12.9 to 8.9 nT" in rs[0].fit and "from 8.9 to 0.5 nT" in rs[1].fit
    diag = Diagnosis(d["baseline"], d["final"], tuple(
        Finding(f["effect"], f["params"], f["sigma"], f["evidence"], f["where"],
                f["explanation"]) for f in d["findings"]), (("soft_iron", "constant"),))
    text = diag.table(80)
    assert text.index("1. hard_iron_step") < text.index("2. time_offset")
    assert all(len(line) <= 80 for line in text.splitlines()), text
    for jargon in ("dBIC", "stat", " > "):
        assert jargon not in text, jargon


def test_headline_first(tmp_path):
    from stages.report import render_html

    ctx = _ctx(tmp_path)
    html = render_html(ctx.recording, ctx.calibration, ctx.metrics, _diag(), {}, prov={})
    body = html[html.index("<body>"):]
    assert body.index("Verdict:") < body.index("id=headline") < body.index("<h2>")
    assert "found 2 effects" in body  # one event and one time offset


def test_metrics_table_folds_hundreds_of_segments():
    """Hours of data hold hundreds of segments: the whole recording's rows stay in view and
    the segments fold into a <details> element; a few segments stay in the table."""
    from stages.metrics import STATS, MetricsResult, ScopeMetrics
    from stages.report import MAX_SEGMENT_ROWS, _metrics_html

    comp = {c: {"calibrated": dict.fromkeys(STATS, 1.0), "uncalibrated": dict.fromkeys(STATS, 2.0),
                "ratio_pct": dict.fromkeys(STATS, 50.0)} for c in "xyz"}

    def result(n_seg: int) -> MetricsResult:
        scopes = [ScopeMetrics("all", "all", 0.0, 100.0, 1000, comp)] + [
            ScopeMetrics(f"segment_{i}", "rotation", i, i + 1.0, 10, comp) for i in range(n_seg)]
        return MetricsResult(1000, 0, 1000, tuple(scopes))

    many = _metrics_html(result(MAX_SEGMENT_ROWS + 5))
    assert many.count("<details>") == 1 and f"{MAX_SEGMENT_ROWS + 5} segments" in many
    assert many.index("whole recording") < many.index("<details>") < many.index("segment_0")
    few = _metrics_html(result(3))
    assert "<details>" not in few and "segment_2" in few


def test_a_gradient_reads_in_the_unit_that_shows_it():
    from pipeline.core.words import per_metre
    from stages.report_text import what

    assert per_metre(2.0) == "2.0 nT/m" and per_metre(250.0) == "250 nT/m"
    assert per_metre(3470.0) == "3.47 \u00b5T/m"
    text = what({"effect": "field_gradient", "params": {
        "G_nT_per_m": [[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        "position_frame": "enu"}})
    assert "2.0 nT/m" in text and "0.00" not in text and "Frobenius" not in text
