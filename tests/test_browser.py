"""report.html and summary.html in a real browser: headless Chromium (Debian's package).

``make chromium`` (run by ``make test``) installs it where apt-get can run as root; elsewhere
this test is skipped with the reason. The pages are opened from disk with the network cut
off (they must be self-contained), the DOM is dumped and screenshots are saved in the test's
folder; the checks are on structure and on screenshot sizes, never on pixel bytes.
"""

from __future__ import annotations

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

pytestmark = pytest.mark.skipif(
    BROWSER is None,
    reason="no headless Chromium on this machine (make chromium installs Debian's package "
    "when apt-get can run as root)")

WIDTH = 1400


def _browser(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
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
""", encoding="utf-8")
    out = tmp / "out"
    res = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", str(toml), "--out",
                          str(out)], capture_output=True, text=True, timeout=900,
                         cwd=HERE.parent)
    assert res.returncode == 0, res.stderr
    return out


def _open(page: Path, shot: Path, height: int) -> str:
    url = page.resolve().as_uri()
    dom = _browser("--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    res = _browser(f"--screenshot={shot}", f"--window-size={WIDTH},{height}", url)
    assert res.returncode == 0 and shot.is_file(), res.stderr[-2000:]
    return dom.stdout


@pytest.mark.parametrize("name", ["rotation", "line_restored", "line_disturbed"])
def test_report_in_browser(campaign, name, tmp_path):
    folder = campaign / name
    figs = sorted(folder.glob("fig_*.png"))
    assert {f.name for f in figs} == {"fig_enu.png", "fig_residual.png", "fig_sphere.png",
                                      "fig_attitude.png"}
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
    n_findings = body.count("modelled as ")
    assert len(imgs) >= 4 + (1 if n_findings else 0)
    for f in figs:  # drawn at 100 px per inch: about the size they are shown at
        w, h = _png_size(f)
        assert w >= 1100 and h >= 350, (f.name, w, h)
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
    assert body.count("<tr>") == 3  # one row per recording
    for name in ("rotation", "line_restored", "line_disturbed"):
        assert f'href="{name}/report.html"' in body
    assert len(re.findall(r"<img [^>]*src=\"data:image/png;base64,", dom)) == 1  # campaign fig
    assert _png_size(tmp_path / "summary.png") == (WIDTH, 1000)
    assert (tmp_path / "summary.png").stat().st_size > 50_000
