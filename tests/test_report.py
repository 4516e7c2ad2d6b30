"""Report: PNG figures and a self-contained report.html."""

from __future__ import annotations

import re

import numpy as np

from pipeline.calibration import Calibration
from pipeline.geometry import quat_normalize, rotvec_to_quat, so3_exp
from pipeline.recording import (
    AttitudeSeries,
    Context,
    Recording,
    Segment,
    SegmentKind,
    VectorSeries,
)
from stages.metrics import Metrics
from stages.report import Report, make_figures
from stages.restore import Restore

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
    ctx = Context(recording=rec, calibration=cal, segments=seg)
    return Metrics().run(Restore().run(ctx))


def test_figures_are_png(tmp_path):
    ctx = _ctx(tmp_path)
    figs = make_figures(ctx.recording, ctx.calibration, ctx.segments)
    assert set(figs) == {"fig_enu.png", "fig_residual.png", "fig_trajectory.png",
                         "fig_attitude.png"}
    assert all(b.startswith(PNG) and len(b) > 5000 for b in figs.values())


def test_report_is_self_contained(tmp_path):
    ctx = Report(str(tmp_path / "out")).run(_ctx(tmp_path))
    html = (tmp_path / "out" / "report.html").read_text()
    # every src/href is an inline data: URI; nothing to fetch
    refs = re.findall(r"""(?:src|href)\s*=\s*["']?([^"'\s>]+)""", html, re.I)
    assert refs and all(r.startswith("data:image/png;base64,") for r in refs)
    assert "<link" not in html.lower() and "<script" not in html.lower()
    assert "Metrics (Li et al. 2020, Table 4)" in html and "ratio %" in html
    assert "&lt;here&gt;" in html  # warnings are escaped
    assert "&infin;" in html  # the unobservable sigma
    assert (tmp_path / "out" / "fig_enu.png").read_bytes().startswith(PNG)
    assert ("report.html", str(tmp_path / "out" / "report.html")) in ctx.outputs


def test_diagnosis_section(tmp_path):
    from stages.report import render_html

    ctx = _ctx(tmp_path)
    diag = {
        "format": "magalign.diagnosis/1",
        "baseline": {"effects": [], "residual_rms_nT": 12.5, "heldout_rms_nT": 12.9},
        "final": {"effects": ["hard_iron_step"], "residual_rms_nT": 0.51,
                  "heldout_rms_nT": 0.52},
        "findings": [{
            "effect": "hard_iron_step",
            "params": {"windows_s": [[2.0, 4.0]], "offset_nT": [300.123456, -200.0, 100.0]},
            "sigma": {}, "evidence": {"delta_bic": -812.25, "rms_before_nT": 12.5,
                                      "rms_after_nT": 0.51},
            "where": {"windows_s": [[2.0, 4.0]], "axes": ["x"], "frame": "mag"},
            "explanation": "a magnet brought near the sensor",
        }],
        "not_identifiable": [{"effect": "time_offset", "reason": "constant rotation rate"}],
    }
    html = render_html(ctx.recording, ctx.calibration, ctx.metrics, diag, {})
    sec = html[html.index("<h2>Diagnosis</h2>"):]
    assert "hard_iron_step" in sec and "300.1" in sec and "300.123456" not in sec
    assert "-812.2" in sec and "constant rotation rate" in sec
