"""Regenerate the archived test recordings (tests/data) and their baselines (tests/golden).

Run only through ``make golden`` (``python tests/make_golden.py``): the baselines are the
reference that ``magalign regress`` compares every later run with, so they change only when
someone decides the results should change.

- ``tests/data/*.mcap``: three tiny deterministic recordings simulated from the demo
  campaign's scenarios (``pipeline/demo``) with fixed seeds, shortened to about 30 s at 50 Hz
  (each well under 300 KB): a calibration rotation, a survey line restored with its
  calibration, and a survey line with a concealed disturbance (processed and diagnosed on its
  own). ``tests/data/campaign.toml`` says which is which.
- ``tests/golden/<name>/``: ``calibration.json``, ``diagnosis.json`` and ``metrics.json``
  (reduced to the whole-recording scope) of processing that campaign.
- ``tests/golden/real/<name>/``: the same for the real recordings in ``../shared/data/real``
  when that folder is present.

The scenario definitions here are also used by the campaign tests.
"""

from __future__ import annotations

import json
import re
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import tomllib

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "pipeline" / "demo"
DATA = ROOT / "tests" / "data"
GOLDEN = ROOT / "tests" / "golden"
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

RATE_HZ = 50.0

CAMPAIGN_TOML = """\
# Archived test campaign (written by tests/make_golden.py; regenerate with `make golden`).
[campaign]
name = "archived test logs"

[channels]
mag = "/mag"
attitude = "/novatel/oem7/inspva"

[outputs]
diagnose = true
rerun = false
report = false

[[recordings]]
path = "rotation.mcap"
role = "calibration"

[[recordings]]
path = "line_restored.mcap"
calibration = "rotation"

[[recordings]]
path = "line_disturbed.mcap"
"""

REAL_CAMPAIGN_TOML = """\
# The real lab recordings (see ../shared/data/real/README.md), each calibrated on its own.
[campaign]
name = "real lab recordings"

[outputs]
diagnose = true
rerun = false
report = false

[[recordings]]
glob = "{real}/*.mcap"
"""


def _sub(text: str, key: str, value: str) -> str:
    """Set ``key = value`` on the line that assigns ``key`` (the demo files have one each)."""
    pat = re.compile(rf"^{re.escape(key)}\s*=.*$", re.MULTILINE)
    assert pat.search(text), key
    return pat.sub(f"{key} = {value}", text, count=1)


def small_scenario_texts() -> dict[str, str]:
    """The three archived recordings as scenario TOML texts (name -> text), fixed seeds.

    Made from the demo campaign's scenario files: ``rotation`` (multi-axis calibration
    manoeuvre, 30 s), ``line_restored`` (survey line, 2 x 12 s legs + 6 s turn),
    ``line_disturbed`` (the same line with a 60 nT disturbance 10..16 s after the first
    sample), all at 50 Hz.
    """
    rate = f"{RATE_HZ}"
    rot = (DEMO / "calibration_rotation.toml").read_text(encoding="utf-8")
    rot = _sub(rot, "name", '"rotation"')
    rot = _sub(rot, "seed", "11")
    rot = _sub(rot, "duration_s", "30.0")
    rot = _sub(rot, "yaw_rate_deg_s", "24.0")  # two full turns in 30 s
    line = (DEMO / "line_01.toml").read_text(encoding="utf-8")
    line = _sub(line, "line_duration_s", "12.0")
    line = _sub(line, "turn_duration_s", "6.0")
    out = {}
    for name, text in (("rotation", rot), ("line_restored", line), ("line_disturbed", line)):
        text = _sub(text, "mag_rate_hz", rate)
        text = _sub(text, "attitude_rate_hz", rate)
        if name != "rotation":
            text = _sub(text, "name", f'"{name}"')
            text = _sub(text, "seed", "12" if name == "line_restored" else "13")
        if name == "line_disturbed":
            text += (
                "\n[effects.disturbance]\n"
                "windows_s = [[10.0, 16.0]]\npeak_nT = 60.0\ndirection_enu = [0.3, 0.2, 0.93]\n"
            )
        out[name] = text
    return out


def small_scenarios() -> dict[str, dict[str, Any]]:
    """:func:`small_scenario_texts` parsed (name -> scenario dict)."""
    return {k: tomllib.loads(v) for k, v in small_scenario_texts().items()}


def write_scenario_recording(d: dict[str, Any], dest: Path) -> Path:
    """Simulate a scenario dict and write it as ``dest`` (an MCAP file)."""
    from pipeline.app.simulate import scenario_from_dict, simulate, write_simulated

    sim = simulate(scenario_from_dict(d, path=str(d.get("name", "<dict>"))))
    return write_simulated(sim, dest)


def write_data(dest: Path = DATA) -> list[Path]:
    """Write the archived recordings and their campaign.toml into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    out = [write_scenario_recording(d, dest / f"{name}.mcap")
           for name, d in small_scenarios().items()]
    (dest / "campaign.toml").write_text(CAMPAIGN_TOML, encoding="utf-8")
    return out


def reduce_metrics(d: dict[str, Any]) -> dict[str, Any]:
    """Keep only the whole-recording scope of a metrics.json (small and stable)."""
    if isinstance(d.get("scopes"), list):
        d = dict(d)
        d["scopes"] = [s for s in d["scopes"] if isinstance(s, dict) and s.get("scope") == "all"]
    return d


def store_baseline(results: Path, dest: Path) -> list[str]:
    """Copy the small JSON results of every finished recording into ``dest/<name>/``."""
    from pipeline.app.regress import recordings_in

    # notes kept beside a baseline (PROVENANCE.md: what each value was checked against)
    notes = {f.name: f.read_text(encoding="utf-8") for f in dest.glob("*.md")} \
        if dest.exists() else {}
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for fname, text in notes.items():
        (dest / fname).write_text(text, encoding="utf-8")
    names = recordings_in(results, need_marker=True)
    for name in names:
        (dest / name).mkdir(parents=True)
        for f in ("calibration.json", "diagnosis.json", "metrics.json"):
            src = results / name / f
            if not src.is_file():
                continue
            d = json.loads(src.read_text(encoding="utf-8"))
            if f == "metrics.json":
                d = reduce_metrics(d)
            (dest / name / f).write_text(json.dumps(d, indent=1) + "\n", encoding="utf-8")
    return names


def process(campaign: Path, out: Path, jobs: int = 2) -> int:
    """Run ``magalign process`` on ``campaign``; returns its exit status."""
    from pipeline.app.cli import main

    return main(["process", str(campaign), "--out", str(out), "--jobs", str(jobs),
                 "--no-progress"])


def main() -> int:
    """Regenerate tests/data and tests/golden (and tests/golden/real when present)."""
    files = write_data()
    for f in files:
        print(f"wrote {f.relative_to(ROOT)} ({f.stat().st_size / 1024:.0f} KB)")
    with tempfile.TemporaryDirectory() as tmp:
        status = process(DATA / "campaign.toml", Path(tmp) / "synthetic")
        if status != 0:
            print("processing the archived recordings failed; baseline not changed",
                  file=sys.stderr)
            return status
        real_dir = GOLDEN / "real"
        keep_real = None
        if real_dir.exists():
            keep_real = Path(tmp) / "real_keep"
            shutil.copytree(real_dir, keep_real)
        names = store_baseline(Path(tmp) / "synthetic", GOLDEN)
        print(f"baseline of {', '.join(names)} in {GOLDEN.relative_to(ROOT)}")
        if REAL.is_dir():
            camp = Path(tmp) / "real.toml"
            camp.write_text(REAL_CAMPAIGN_TOML.format(real=REAL.as_posix()), encoding="utf-8")
            status = process(camp, Path(tmp) / "real")
            if keep_real is not None:  # its notes (PROVENANCE.md) stay with the new baseline
                real_dir.mkdir(parents=True, exist_ok=True)
                for f in keep_real.glob("*.md"):
                    shutil.copy2(f, real_dir / f.name)
            names = store_baseline(Path(tmp) / "real", real_dir)
            print(f"baseline of the real recordings {', '.join(names)} in "
                  f"{real_dir.relative_to(ROOT)} (processing exit status {status})")
        elif keep_real is not None:
            shutil.copytree(keep_real, real_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
