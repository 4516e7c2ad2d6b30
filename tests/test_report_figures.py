"""The report's figures: what each panel holds, checked on the drawn matplotlib artists."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.core import style
from pipeline.core.recording import VectorSeries
from stages.diagnose.result import Finding, Signature
from stages.report import (
    _enu_caption_end,
    _map_html,
    finding_figures,
    make_figures,
    sphere_histogram_range_nT,
)
from stages.report_map import draw_map, draw_small_map
from tests.test_report import _ctx

T0 = 1_767_225_600_000_000_000


@pytest.fixture
def drawn(monkeypatch):
    """Keep every figure the report draws (instead of its PNG bytes), closed at the end."""
    figs: list = []

    def keep(fig):
        figs.append(fig)
        return b"\x89PNG"

    monkeypatch.setattr(style, "png", keep)
    yield figs
    plt = style.pyplot()
    for f in figs:
        plt.close(f)


def _finding(effect, frame, resid, contrib, regressor=None, windows=None, t_s=None):
    n = len(resid)
    t = np.arange(n) / 10.0 if t_s is None else t_s
    return Finding(effect=effect, params={}, sigma={}, evidence={},
                   where={"frame": frame, "windows_s": windows or [[0.0, float(t[-1])]]},
                   explanation="", signature=Signature(t, resid, contrib, regressor))


def _diag(*findings, duration_s=100.0):
    return SimpleNamespace(findings=tuple(findings), duration_s=duration_s)


def _texts(fig):
    from matplotlib.text import Text

    return " ".join(t.get_text() for t in fig.findobj(Text))


def test_sphere_histograms_share_one_range(tmp_path, drawn):
    """Raw and corrected histograms on one x range, so that the calibration's effect shows."""
    ctx = _ctx(tmp_path)
    make_figures(ctx.recording, ctx.calibration, ctx.segments)
    sphere = [f for f in drawn if "magnetometer frame" in _texts(f)][0]
    hists = [a for a in sphere.axes if "|reading|" in a.get_title()]
    assert len(hists) == 2
    assert hists[0].get_xlim() == pytest.approx(hists[1].get_xlim())


def test_sphere_histogram_range_is_not_stretched_by_far_raw_readings():
    """A magnet near the sensor for a while puts raw readings 30 uT off the sphere: the
    range still resolves the corrected spread (it was one bar on the raw's range)."""
    rng = np.random.default_rng(1)
    corrected = rng.normal(0, 700, 20_000)
    raw = np.r_[rng.normal(0, 300, 12_000), rng.uniform(-30_000, 30_000, 8_000)]
    lo, hi = sphere_histogram_range_nT(raw, corrected)
    assert lo < -1800 and hi > 1800  # 99 % of the corrected spread is inside
    assert hi - lo < 6000  # bins of at most 100 nT on 60 bins
    # a raw sphere shifted off |B| (an offset) is inside too, with zero
    lo, hi = sphere_histogram_range_nT(rng.normal(5000, 50, 1000), rng.normal(0, 50, 1000))
    assert lo < -50 and hi > 5050


def test_a_term_below_its_residual_gets_its_own_scale(drawn):
    """An offset of 300 nT under 3000 nT of residual: a second panel shows the term."""
    rng = np.random.default_rng(2)
    n = 2000
    term = np.tile([-300.0, 250.0, 190.0], (n, 1))
    resid = term + rng.normal(0, 1000, (n, 3))
    figs = finding_figures(_diag(_finding("hard_iron", "mag", resid, term)), T0)
    assert len(figs) == 1
    fig = drawn[-1]
    assert len(fig.axes) == 2
    lo, hi = fig.axes[1].get_ylim()
    assert lo < -300 and hi > 250 and hi - lo < 1200  # the term fills its panel
    # a term as large as its residual keeps one panel
    finding_figures(_diag(_finding("hard_iron", "mag", term + rng.normal(0, 10, (n, 3)),
                                   term)), T0)
    assert len(drawn[-1].axes) == 1


@pytest.mark.parametrize("effect", ["time_offset", "eddy_current"])
def test_rate_scatter_has_the_fitted_line(drawn, effect):
    """The residual against the reading's rate of change, with the fitted term as lines."""
    rng = np.random.default_rng(3)
    rate = rng.normal(0, 1e4, (500, 3))
    contrib = -0.015 * rate
    finding_figures(_diag(_finding(effect, "mag", contrib + rng.normal(0, 50, (500, 3)),
                                   contrib, regressor=rate)), T0)
    ax = drawn[-1].axes[0]
    lines = [ln for ln in ax.get_lines() if ln.get_label().startswith("fitted term")]
    assert len(lines) == 3 and all(ln.get_linestyle() == "-" for ln in lines)


def test_frame_words_agree_with_the_legend(drawn):
    """A finding in ENU names east, north, up in its axis label and its legend alike."""
    rng = np.random.default_rng(4)
    c = np.cumsum(rng.normal(0, 5, (300, 3)), axis=0)
    finding_figures(_diag(_finding("field_gradient", "enu", c + rng.normal(0, 20, (300, 3)),
                                   c)), T0)
    fig = drawn[-1]
    text = _texts(fig)
    assert "enu frame" not in text and "east, north, up" in fig.axes[0].get_ylabel()
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert any("east" in x for x in labels) and not any(x.endswith(" x") for x in labels)


def test_sample_hold_has_a_panel(drawn):
    """A sample-and-hold finding (no term in the residual) gets a figure of its repeats."""
    n = 3000
    t = T0 + np.arange(n, dtype=np.int64) * 3_500_000
    conv = np.arange(n) - (np.arange(n) % 3 == 2)  # every third message repeats
    v = np.stack([1000 * np.sin(conv / 50.0), 500 * np.cos(conv / 70.0), conv * 0.0 + 4e4], -1)
    f = Finding(effect="sample_hold", params={"native_rate_hz": 190.0,
                                              "repeated_fraction": 0.33},
                sigma={}, evidence={}, where={"frame": "mag"}, explanation="")
    figs = finding_figures(_diag(f), T0, mag=VectorSeries(t, v))
    assert [title for title, _ in figs] == ["sample hold"]
    ax = drawn[-1].axes[0]
    repeats = [ln for ln in ax.get_lines() if "repeating" in ln.get_label()]
    assert repeats and len(repeats[0].get_xdata()) > 0
    # without the messages there is nothing to draw it from, and nothing fails
    assert finding_figures(_diag(f), T0) == []


def test_captions_name_only_what_is_drawn(tmp_path):
    """No event shading or closer scale in the caption when the figure has none."""
    ctx = _ctx(tmp_path)
    text = _enu_caption_end(ctx.recording, ctx.calibration, None, None)
    assert "events" not in text and "closer scale" not in text
    diag = {"findings": [{"effect": "disturbance", "where": {"windows_s": [[3.0, 5.0]]}}]}
    assert "in red the events" in _enu_caption_end(ctx.recording, ctx.calibration, None, diag)
    rec = SimpleNamespace(position=SimpleNamespace(frame="enu"), duration_s=30.0)
    plain = _map_html("<img>", rec, None)
    assert "Crosses" not in plain and "Stars" not in plain and "Open circle: start" in plain
    src = {"findings": [{"effect": "local_source", "params": {"position_m": [1, 2, 0]},
                         "where": {"windows_s": [[3.0, 5.0]]}}]}
    with_src = _map_html("<img>", rec, src)
    assert "Crosses" in with_src and "Stars" not in with_src
    assert "Stars" in _map_html("<img>", rec, diag)


def test_caption_speaks_of_the_closer_scale_when_drawn(tmp_path, drawn):
    ctx = _ctx(tmp_path)
    from stages.report import closer_scale_rows
    from stages.restore import view_data

    make_figures(ctx.recording, ctx.calibration, ctx.segments, restored=ctx.restored)
    enu = [f for f in drawn if "field in ENU" in _texts(f)][0]
    drawn_closer = "closer scale" in _texts(enu)
    assert drawn_closer == any(closer_scale_rows(view_data(ctx.restored,
                                                           ctx.calibration.R_body_mag)))
    text = _enu_caption_end(ctx.recording, ctx.calibration, ctx.restored, None)
    assert ("closer scale" in text) == drawn_closer


def _loop_map():
    th = np.linspace(0, 2 * np.pi, 200)  # a closed loop: it ends where it began
    path = [[float(i), float(np.cos(a)), float(np.sin(a)), 0.0, float(50 * np.sin(3 * a)),
             float(40 * np.sin(3 * a))] for i, a in enumerate(th)]
    return {"frame": "attitude_source_local", "origin": None, "median_nT": 44000.0,
            "samples_per_point": 1, "path": path, "sources": [], "events": []}


def test_start_and_end_both_show_where_they_coincide(drawn):
    draw_map(_loop_map())
    ax = drawn[-1].axes[0]
    start = [ln for ln in ax.get_lines() if ln.get_label() == "start"][0]
    end = [ln for ln in ax.get_lines() if ln.get_label() == "end"][0]
    assert np.allclose(start.get_xydata(), end.get_xydata(), atol=1e-9)
    # an open ring larger than the filled square: the square shows inside it
    assert start.get_markerfacecolor() == "none"
    assert start.get_markersize() > 1.5 * end.get_markersize()
    assert end.get_zorder() > start.get_zorder()


def test_summary_map_colour_bar_fits_beside_the_map(drawn):
    """The colour bar, its ticks and its label inside the figure, clear of the map."""
    draw_small_map(_loop_map(), 60.0, "line")
    fig = drawn[-1]
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    ax, cax = fig.axes[0], fig.axes[1]
    assert cax.get_ylabel()
    cb = cax.get_tightbbox(r)
    assert cb.x1 <= fig.bbox.x1 + 0.5 and cb.x0 >= fig.bbox.x0
    assert ax.get_tightbbox(r).x1 <= cb.x0 + 0.5


def test_targets_table_speaks_words_not_bic():
    """The targets table heads its evidence column in words; the caption says what it is."""
    from stages.report_grid import TABLE_COLUMNS

    assert "BIC" not in " ".join(h for _, h in TABLE_COLUMNS)
    assert dict(TABLE_COLUMNS)["delta_bic"] == "evidence"


def test_summary_map_caption_names_only_marks_present(tmp_path):
    """The campaign summary speaks of crosses and stars only when some map has them."""
    import json

    from pipeline.app.summary import maps_html

    m = _loop_map()
    (tmp_path / "map.json").write_text(json.dumps(m))
    row = {"name": "line", "map": "map.json", "verdict": "ok"}
    text = maps_html([row], tmp_path)
    assert "Crosses" not in text and "Stars" not in text and "Open circle: start" in text
    m["events"] = [{"effect": "disturbance", "start_s": 1.0, "end_s": 2.0, "x": 0.0,
                    "y": 0.0, "z": 0.0}]
    (tmp_path / "map.json").write_text(json.dumps(m))
    text = maps_html([row], tmp_path)
    assert "Stars" in text and "Crosses" not in text
