"""``--exclude START:END``: stretches a user knows are bad leave the fit and the verdict,
not the restore (stages/exclude.py), alike in calibrate, diagnose, process and the two-pass
path, and they are written into calibration.json."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from indep_gen import Spec, write

from pipeline.core.vocabulary import ExcludeWindow
from pipeline.run.runner import ProcessOptions, process_recording

DIST = {"disturbance": {"windows_s": [[20.0, 30.0]], "peak_nT": 3000.0,
                        "direction_enu": [0.6, 0.0, 0.8]}}


def _rec(tmp_path: Path) -> tuple[Path, Spec]:
    spec = Spec("dist", seed=9, duration_s=60.0, mag_noise_nT=2.0, effects=DIST)
    return write(spec, tmp_path / "dist.mcap"), spec


def test_windows_parse_in_seconds_and_utc():
    w = ExcludeWindow.parse("12.5:30")
    assert (w.start, w.end, w.utc) == (12.5, 30.0, False)
    assert w.ns(1_000) == (1_000 + 12_500_000_000, 1_000 + 30_000_000_000)
    u = ExcludeWindow.parse("2026-11-20T10:03:00Z:2026-11-20T10:04:30.5Z")
    assert u.utc and u.end - u.start == pytest.approx(90.5)
    assert ExcludeWindow.parse(u.text()) == u
    for bad in ("30:12.5", "12.5", "a:b", "2026-11-20T10:03:00:2026-11-20T10:04:00"):
        with pytest.raises(ValueError):
            ExcludeWindow.parse(bad)


def test_a_malformed_window_is_one_line_and_exit_2(tmp_path):
    path, _ = _rec(tmp_path)
    for cmd in ("calibrate", "diagnose", "process"):
        out = tmp_path / f"o_{cmd}"
        r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", cmd, str(path), "--out",
                            str(out), "--exclude", "30:12"], capture_output=True, text=True)
        assert r.returncode == 2, (cmd, r.stderr)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "--exclude" in lines[0] and "end must come after" in lines[0]
        assert not out.exists()


def _angle_err_deg(cal: dict, spec: Spec) -> float:
    from scipy.spatial.transform import Rotation

    got = Rotation.from_rotvec(np.radians(cal["rotvec_body_mag_deg"]))
    want = Rotation.from_rotvec(np.radians(spec.rotvec_body_mag_deg))
    return float(np.degrees((got * want.inv()).magnitude()))


def test_excluding_a_disturbance_removes_it_from_the_fit_not_from_the_restore(tmp_path):
    """A 3,000 nT disturbance at 20-30 s: left out, the diagnosis has nothing to name there,
    the rotation is the truth's, and every sample is still restored and measured."""
    path, spec = _rec(tmp_path)
    base = dict(write_rerun=False, write_report=False)
    whole = process_recording(path, tmp_path / "whole", options=ProcessOptions(**base))
    assert "disturbance" in whole["findings"]
    cut = process_recording(path, tmp_path / "cut", options=ProcessOptions(
        exclude=(ExcludeWindow.parse("19.5:30.5"),), **base))
    assert "disturbance" not in cut["findings"], cut["findings"]
    cal = json.loads(Path(cut["paths"]["calibration.json"]).read_text())
    assert cal["checks"]["excluded_windows_s"] == [[pytest.approx(19.5), pytest.approx(30.5)]]
    assert cal["checks"]["excluded_samples"] == pytest.approx(1100, abs=2)  # 11 s at 100 Hz
    assert any("--exclude" in w for w in cal["warnings"])
    assert _angle_err_deg(cal, spec) < 0.01  # deg
    assert cut["n_samples"] == whole["n_samples"]  # restored and measured: every sample


def test_a_long_recording_excludes_alike(tmp_path, monkeypatch):
    import pipeline.run.plan as plan
    import pipeline.run.source as source

    monkeypatch.setattr(plan, "DECIMATED_SAMPLES", 6_000)
    monkeypatch.setattr(source, "RANGE_MESSAGES", 2_000)
    path, spec = _rec(tmp_path)
    rows = {}
    for name, scale in (("mem", None), ("two", 1_000)):
        rows[name] = process_recording(path, tmp_path / name, options=ProcessOptions(
            scale_samples=scale, write_rerun=False, write_report=False,
            exclude=(ExcludeWindow.parse("19.5:30.5"),)))
    assert "EstimateFromSums" in rows["two"]["timings_s"]  # analysed as a long recording
    cals = {k: json.loads(Path(r["paths"]["calibration.json"]).read_text())
            for k, r in rows.items()}
    assert cals["two"]["checks"]["excluded_samples"] == cals["mem"]["checks"]["excluded_samples"]
    np.testing.assert_allclose(cals["two"]["checks"]["excluded_windows_s"],
                               cals["mem"]["checks"]["excluded_windows_s"], atol=1e-9)  # s
    for c in cals.values():
        assert _angle_err_deg(c, spec) < 0.01  # deg
    assert "disturbance" not in rows["two"]["findings"]


def test_a_campaign_names_its_exclusions_per_recording(tmp_path):
    from pipeline.app.campaign import load_campaign
    from pipeline.core.errors import ConfigError

    path, _ = _rec(tmp_path)
    toml = tmp_path / "c.toml"
    toml.write_text(f'[[recordings]]\npath = "{path.name}"\nexclude = ["19.5:30.5"]\n')
    (rec,) = load_campaign(toml).recordings
    assert rec.options.exclude == ("19.5:30.5",)
    toml.write_text(f'[[recordings]]\npath = "{path.name}"\nexclude = ["30:20"]\n')
    with pytest.raises(ConfigError, match="exclude"):
        load_campaign(toml)
