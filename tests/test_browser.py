"""report.html and summary.html in a real browser: headless Chromium (Debian's package).

``make chromium`` (run by ``make test``) installs it where apt-get can run as root; elsewhere
this test is skipped with the reason, except in CI (``.ci/run`` sets
``MAGALIGN_REQUIRE_BROWSER=1``), where a missing browser fails it. The pages are opened from
disk with the network cut off (they must be self-contained), the DOM is dumped and
screenshots are saved in the test's folder; the checks are on structure and on screenshot
sizes, never on pixel bytes.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
BROWSER = next((b for b in map(shutil.which, BROWSERS) if b), None)

#: Set by .ci/run: there, a missing browser is a failure, not a quiet skip.
REQUIRED = os.environ.get("MAGALIGN_REQUIRE_BROWSER") == "1"

pytestmark = pytest.mark.skipif(
    BROWSER is None and not REQUIRED,
    reason="no headless Chromium on this machine (make chromium installs Debian's package "
    "when apt-get can run as root)")

WIDTH = 1400


def _browser(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    if BROWSER is None:
        pytest.fail("no headless Chromium, and MAGALIGN_REQUIRE_BROWSER=1 (CI) requires one: "
                    "make chromium installs it where apt-get can run as root")
    cmd = [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           "--no-first-run", "--disable-extensions", "--mute-audio",
           # nothing may be fetched: every name resolves nowhere
           "--host-resolver-rules=MAP * ~NOTFOUND", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def _png_size(path: Path) -> tuple[int, int]:
    b = path.read_bytes()
    assert b[:8] == b"\x89PNG\r\n\x1a\n", path
    return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """A small campaign with reports: a calibration run, a line restored with it, a line alone."""
    tmp = tmp_path_factory.mktemp("browser")
    moving = _moving(tmp / "moving.mcap")
    toml = tmp / "c.toml"
    toml.write_text(f"""\
[campaign]
name = "browser test"

[channels]
mag = "/mag"
attitude = "/novatel/oem7/inspva"

[outputs]
diagnose = true
rerun = false
report = true

[[recordings]]
path = "{DATA / 'rotation.mcap'}"
role = "calibration"

[[recordings]]
path = "{DATA / 'line_restored.mcap'}"
calibration = "rotation"

[[recordings]]
path = "{DATA / 'line_disturbed.mcap'}"

[[recordings]]
path = "{moving}"
""", encoding="utf-8")
    out = tmp / "out"
    res = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", str(toml), "--out",
                          str(out)], capture_output=True, text=True, timeout=900,
                         cwd=HERE.parent)
    assert res.returncode == 0, res.stderr
    return out


def _moving(path: Path) -> Path:
    """A recording with positions (INSPVA fixes) moving through a field gradient."""
    from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated

    g = [[300.0, 100.0, 0.0], [100.0, -200.0, 50.0], [0.0, 50.0, -100.0]]  # nT/m
    sc = {"name": "moving", "timing": {"duration_s": 40.0, "mag_rate_hz": 50.0,
                                       "attitude_rate_hz": 50.0},
          "motion": {"profile": "multiaxis"}, "field": {"enu_nT": [0.0, 20000.0, -40000.0]},
          "trajectory": {"amplitude_m": [3.0, 2.0, 0.2]},
          "effects": {"field_gradient": {"G_nT_per_m": g}}, "noise": {"mag_sigma_nT": 1.0},
          "output": {"attitude_type": "novatel_oem7_msgs/msg/INSPVA",
                     "attitude_topic": "/novatel/oem7/inspva"}}
    return write_simulated(simulate(scenario_from_dict(sc)), path)


def _open(page: Path, shot: Path, height: int) -> str:
    url = page.resolve().as_uri()
    dom = _browser("--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    res = _browser(f"--screenshot={shot}", f"--window-size={WIDTH},{height}", url)
    assert res.returncode == 0 and shot.is_file(), res.stderr[-2000:]
    return dom.stdout


@pytest.mark.parametrize("name", ["rotation", "line_restored", "line_disturbed", "moving"])
def test_report_in_browser(campaign, name, tmp_path):
    folder = campaign / name
    figs = sorted(folder.glob("fig_*.png"))
    # a plan view only where the recording has positions
    assert {f.name for f in figs} == {"fig_enu.png", "fig_residual.png", "fig_sphere.png",
                                      "fig_attitude.png"} | (
                                          {"fig_map.png"} if name == "moving" else set())
    dom = _open(folder / "report.html", tmp_path / f"{name}.png", 4000)
    # the verdict box and the headline come first
    body = dom[dom.index("<body"):]
    assert re.search(r"<b>Verdict: (OK|QUESTIONABLE|REFUSED)</b>", body)
    assert body.index("Verdict:") < body.index('id="headline"') < body.index("<h2")
    assert "The magnetometer is turned by" in body
    # every figure is in the page: the four of the report and one per diagnosis finding
    imgs = re.findall(r'<img alt="([^"]+)" src="data:image/png;base64,', body)
    assert {"fig_enu.png", "fig_residual.png", "fig_sphere.png", "fig_attitude.png"} <= set(
        imgs)
    n_findings = body.count("in diagnosis.json: ")
    # an effect's key is named as the file's, not as words for a person
    assert not re.search(r"modelled as [a-z]+_[a-z_]+", body)
    assert len(imgs) >= 4 + (1 if n_findings else 0)
    for f in figs:  # drawn at 100 px per inch: about the size they are shown at
        w, h = _png_size(f)
        assert w >= 1100 and h >= 350, (f.name, w, h)
    # every sample counted in one place: received = without attitude + restored
    m = re.search(r'<p id="counts">Of ([\d\u2009]+) magnetometer samples received, '
                  r'([\d\u2009]+) (?:have|has) no usable attitude and ([\d\u2009]+) are restored',
                  body)
    assert m is not None
    n_all, n_without, n_restored = (int(x.replace("\u2009", "")) for x in m.groups())
    assert n_all == n_without + n_restored
    # the field the model predicts is drawn, and the caption says what a step means
    assert "field the fitted model\npredicts" in body or "field the fitted model predicts" in body
    assert "not a calibration error" in body
    if name == "moving":
        sec = body[body.index('id="map"'):]
        assert re.search(r'<img alt="fig_map.png" src="data:image/png;base64,', sec)
        assert (folder / "map.json").is_file()
    else:
        assert 'id="map"' not in body and not (folder / "map.json").exists()
    w, h = _png_size(tmp_path / f"{name}.png")
    assert (w, h) == (WIDTH, 4000)
    # a page of text, tables and four figures is not blank: a blank one compresses to a few kB
    assert (tmp_path / f"{name}.png").stat().st_size > 150_000


def test_disturbance_reads_as_one_event(campaign, tmp_path):
    dom = _open(campaign / "line_disturbed" / "report.html", tmp_path / "d.png", 1500)
    sec = dom[dom.index("What the diagnosis found"):dom.index("Field before and after")]
    assert "A passing disturbance of" in sec and " nT" in sec and " UTC" in sec
    assert "windows_s" not in sec
    dom = _open(campaign / "line_restored" / "report.html", tmp_path / "r.png", 1500)
    sec = dom[dom.index("What the diagnosis found"):dom.index("Field before and after")]
    assert "restored with the calibration from calibration.json" in sec


def test_summary_in_browser(campaign, tmp_path):
    dom = _open(campaign / "summary.html", tmp_path / "summary.png", 1000)
    body = dom[dom.index("<tbody>"):]
    assert body.count("<tr>") == 4  # one row per recording
    for name in ("rotation", "line_restored", "line_disturbed", "moving"):
        assert f'href="{name}/report.html"' in body
    # the campaign figure, and one map: the only recording with positions, with its verdict
    assert len(re.findall(r"<img [^>]*src=\"data:image/png;base64,", dom)) == 2
    maps = dom[dom.index('<div class="maps">'):]
    (fig,) = re.findall(r'<figure class="map" id="map-(\w+)">', maps)
    assert fig == "moving"
    assert re.search(r'<span class="verdict v-(OK|QUESTIONABLE|REFUSED)">', maps)
    assert '<small class="reason">' in maps
    assert _png_size(tmp_path / "summary.png") == (WIDTH, 1000)
    assert (tmp_path / "summary.png").stat().st_size > 50_000
