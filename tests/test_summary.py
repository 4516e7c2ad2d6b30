"""summary.html: grouped columns, one number format per quantity, the campaign figure."""

from __future__ import annotations

import re

from pipeline.app.summary import campaign_figure, render_html

PNG = b"\x89PNG\r\n\x1a\n"


def _row(name, *, frm=None, status="ok", rv=(1.2, -1.0, 1.2), sg=(0.01, 0.02, None),
         tau=None, error=None):
    r = {"name": name, "status": status, "role": "survey" if frm else "calibration",
         "calibration_from": frm, "report": f"{name}/report.html", "rrd": f"{name}/{name}.rrd",
         "verdict": None if status == "failed" else "OK", "error": error,
         "residual_rms_nT": 5.04, "time_offset_s": tau, "estimator": "diagnose",
         "findings": "hard_iron_step,disturbance", "elapsed_s": 12.34, "input_path": "/x.mcap"}
    for i, a in enumerate("xyz"):
        r[f"rotvec_deg_{a}"] = None if status == "failed" else rv[i]
        r[f"sigma_deg_{a}"] = None if status == "failed" else sg[i]
        r[f"offset_nT_{a}"] = None
        r[f"B_enu_nT_{a}"] = (1300.4, 15000.2, -49000.7)[i]
        r[f"ratio_pct_{a}"] = 3.456
    return r


def test_grouped_columns_and_formats():
    rows = [_row("cal", tau=0.0152), _row("line", frm="cal"),
            _row("bad", status="failed", error="bad.mcap: not an MCAP file")]
    # one calibration run: no campaign figure
    assert "<img " not in render_html(rows, list(rows[0]), "t")
    rows.insert(1, _row("cal2", rv=(1.1, -0.9, 1.3)))
    text = render_html(rows, list(rows[0]), "t")
    head = text[text.index("<thead>"):text.index("</thead>")]
    for group in ("recording", "misalignment", "offset o (nT, mag)", "field B (nT)",
                  "fluctuation, after / before (%)", "diagnosis"):
        assert group in head
    body = text[text.index("<tbody>"):]
    assert body.count("<tr>") == 4 and "<tr class=err>" in body  # error under its row
    assert "15.20" in body  # tau in ms, 2 decimals
    assert "\u221249001" in body and "-49001" not in body  # field: 0 decimals, true minus
    assert "1.200<small> \u00b1 0.010</small>" in body  # deg: 3 decimals with its sigma
    assert "\u00b1 \u221e" in body  # the axis without a sigma
    assert "3.5" in body and "3.456" not in body
    assert "hard iron step, disturbance" in body
    assert "input_path" not in head and "/x.mcap" not in body  # only in the parquet
    assert 'href="cal/report.html"' in body and 'href="cal/cal.rrd"' in body
    assert len(re.findall(r"<img [^>]*src='data:image/png;base64,", text)) == 1


def test_campaign_figure_only_calibration_runs():
    assert campaign_figure([_row("line", frm="cal")]) is None
    assert campaign_figure([_row("bad", status="failed")]) is None
    # one run: nothing to compare (the table holds its rotation)
    assert campaign_figure([_row("a"), _row("l", frm="a"), _row("bad", status="failed")]) is None
    png = campaign_figure([_row("a"), _row("b", rv=(1.1, -0.9, 1.3)), _row("l", frm="a")])
    assert png is not None and png.startswith(PNG)


def test_a_recording_that_is_not_ok_says_why_under_its_row():
    ok, doubt = _row("line_03"), _row("line_04")
    doubt["verdict"] = "QUESTIONABLE"
    doubt["verdict_reason"] = ("The two halves of the recording give rotations 0.85 deg apart, "
                               "more than their sigmas allow.")
    page = render_html([ok, doubt], list(ok), "demo")
    assert "<tr class=why>" in page and page.count("<tr class=why>") == 1
    assert "line_04 is QUESTIONABLE: The two halves of the recording give rotations 0.85" in page
