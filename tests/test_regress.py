"""Regression runs: archived logs against their stored baselines; tolerances; exit codes."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.app.regress import REGRESSION, Tolerances, compare, format_table
from pipeline.core.errors import InputError
from pipeline.core.geometry import quat_to_matrix, rotvec_to_quat

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
GOLDEN = HERE / "golden"
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
sys.path.insert(0, str(HERE))  # make_golden


def _cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.app.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=HERE.parent)


@pytest.fixture(scope="module")
def archived_results(tmp_path_factory) -> Path:
    """tests/data processed now (the campaign tests/golden was made from)."""
    out = tmp_path_factory.mktemp("regress") / "results"
    r = _cli("process", str(DATA / "campaign.toml"), "--out", str(out), "--jobs", "2",
             "--no-progress")
    assert r.returncode == 0, r.stderr
    return out


#: Reproducibility of the archived recordings, in physical units. The simulation is seeded, but
#: the last bits of its floating-point values differ between numpy builds and CPUs (SIMD
#: sin/cos, FMA), so the files are compared by their decoded values, never by their bytes.
#: These bounds are far below the simulated sensor noise (0.5 nT, 0.01 deg) and far above
#: any rounding difference.
REPRO_MAG_NT = 1e-3
REPRO_ATTITUDE_DEG = 1e-6
REPRO_STAMP_S = 1e-6


def _decoded(path: Path) -> dict:
    from pipeline.io.mcap_read import read_raw_channels, read_recording

    rec = read_recording(path)
    raw = read_raw_channels(path)
    return {"rec": rec,
            "channels": [(c.topic, c.schema_name, c.message_encoding, len(c)) for c in raw]}


def test_archived_logs_are_small_and_deterministic(tmp_path):
    from make_golden import write_data

    from pipeline.core.geometry import quat_conj, quat_mul, quat_to_rotvec

    stored = sorted(DATA.glob("*.mcap"))
    assert 2 <= len(stored) <= 3
    for f in stored:
        assert f.stat().st_size < 300_000
    fresh = write_data(tmp_path)
    assert sorted(f.name for f in fresh) == [f.name for f in stored]
    for f in fresh:
        a, b = _decoded(f), _decoded(DATA / f.name)
        # same structure: channels, types, encodings, message counts
        assert a["channels"] == b["channels"], f.name
        ra, rb = a["rec"], b["rec"]
        assert (ra.mag_topic, ra.attitude_topic, ra.mag_frame_id) == (
            rb.mag_topic, rb.attitude_topic, rb.mag_frame_id), f.name
        # same values within bounds in nT, deg and s
        for sa, sb in ((ra.mag, rb.mag), (ra.attitude, rb.attitude)):
            assert len(sa.t_ns) == len(sb.t_ns) > 100, f.name
            dt = np.abs(sa.t_ns - sb.t_ns).max() * 1e-9
            assert dt <= REPRO_STAMP_S, f"{f.name}: stamps differ by {dt} s"
        dm = float(np.abs(ra.mag.values - rb.mag.values).max())
        assert dm <= REPRO_MAG_NT, f"{f.name}: magnetometer differs by {dm} nT"
        dq = quat_mul(quat_conj(ra.attitude.q_enu_body), rb.attitude.q_enu_body)
        dq = dq * np.where(dq[:, 3:] < 0, -1.0, 1.0)  # q and -q are one attitude
        dang = float(np.degrees(np.linalg.norm(quat_to_rotvec(dq), axis=-1)).max())
        assert dang <= REPRO_ATTITUDE_DEG, f"{f.name}: attitude differs by {dang} deg"


def test_archived_logs_match_golden(archived_results):
    r = _cli("regress", str(archived_results), "--baseline", str(GOLDEN))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 regression(s)" in r.stdout
    assert "rotation_deg" in r.stdout and "findings" in r.stdout


def _move_rotation(cal_file: Path, deg: float, axis=(0.0, 0.0, 1.0), *,
                   keep_rotvec: bool = False) -> None:
    """Turn a calibration's R_body_mag by ``deg``; its rotation vector follows unless kept."""
    from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec

    d = json.loads(cal_file.read_text())
    dR = quat_to_matrix(rotvec_to_quat(np.radians(deg) * np.asarray(axis)))
    R = dR @ np.asarray(d["R_body_mag"])
    d["R_body_mag"] = R.tolist()
    if not keep_rotvec:
        d["rotvec_body_mag_deg"] = np.degrees(quat_to_rotvec(matrix_to_quat(R))).tolist()
    cal_file.write_text(json.dumps(d))


def test_regress_passes_against_itself_and_fails_on_moved_rotation(archived_results, tmp_path):
    r = _cli("regress", str(archived_results), "--baseline", str(archived_results))
    assert r.returncode == 0, r.stdout + r.stderr
    base = tmp_path / "base"
    shutil.copytree(archived_results, base)
    _move_rotation(base / "rotation" / "calibration.json", 0.5, axis=(0.6, 0.0, 0.8))
    r = _cli("regress", str(archived_results), "--baseline", str(base))
    assert r.returncode == 1, r.stdout + r.stderr
    bad = [ln for ln in r.stdout.splitlines() if REGRESSION in ln]
    assert len(bad) == 1 and bad[0].startswith("rotation ") and "rotation_deg" in bad[0]
    assert "0.5" in bad[0]
    assert "rotation" in r.stderr and r.stderr.count("\n") == 1  # one line on stderr
    # 0.05 deg is about 60 of this calibration's sigmas (0.0004-0.0008 deg): a regression
    shutil.rmtree(base)
    shutil.copytree(archived_results, base)
    _move_rotation(base / "rotation" / "calibration.json", 0.05)
    r = _cli("regress", str(archived_results), "--baseline", str(base))
    assert r.returncode == 1, r.stdout + r.stderr
    bad = [ln for ln in r.stdout.splitlines() if REGRESSION in ln]
    assert len(bad) == 1 and bad[0].startswith("rotation ") and "rotation_deg" in bad[0]


def test_baseline_whose_matrix_and_vector_disagree_is_refused(archived_results, tmp_path):
    """The table shows the rotation vector and compares the matrix: they must agree."""
    base = tmp_path / "base"
    shutil.copytree(archived_results, base)
    cal = base / "rotation" / "calibration.json"
    _move_rotation(cal, 0.5, axis=(0.6, 0.0, 0.8), keep_rotvec=True)
    r = _cli("regress", str(archived_results), "--baseline", str(base))
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert str(cal) in r.stderr and "rotvec_body_mag_deg" in r.stderr
    assert "R_body_mag" in r.stderr
    with pytest.raises(InputError, match="rotvec_body_mag_deg"):
        compare(archived_results, base)


def test_unfinished_recording_is_a_regression(archived_results, tmp_path):
    res = tmp_path / "res"
    shutil.copytree(archived_results, res)
    (res / "line_restored" / ".magalign-done.json").unlink()  # as if killed midway
    rows = compare(res, GOLDEN)
    bad = [r for r in rows if r.status == REGRESSION]
    assert [(r.recording, r.quantity) for r in bad] == [("line_restored", "recording")]


def test_regress_bad_input_exits_2(tmp_path):
    r = _cli("regress", str(tmp_path / "nope"), "--baseline", str(GOLDEN))
    assert r.returncode == 2 and "results folder not found" in r.stderr
    assert "Traceback" not in r.stderr
    base = tmp_path / "base"
    (base / "rec").mkdir(parents=True)
    (base / "rec" / "calibration.json").write_text("{not json")
    res = tmp_path / "res"
    (res / "rec").mkdir(parents=True)
    (res / "rec" / "calibration.json").write_text("{}")
    (res / "rec" / ".magalign-done.json").write_text("{}")
    r = _cli("regress", str(res), "--baseline", str(base))
    assert r.returncode == 2 and "not valid JSON" in r.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no recording"):
        compare(res, empty)


# --------------------------------------------------------------------------- tolerances

def _cal(rotvec_deg, sigma=(0.01, 0.01, 0.02), **kw):
    R = quat_to_matrix(rotvec_to_quat(np.radians(rotvec_deg)))
    d = {"format": "magalign.calibration/1", "R_body_mag": R.tolist(),
         "rotvec_body_mag_deg": list(rotvec_deg), "sigma_rotvec_deg": list(sigma),
         "B_enu_nT": [500.0, 17000.0, -48000.0], "residual_rms_nT": 10.0, "offset_nT": None,
         "D": None, "time_offset_s": None, "estimator": "ml", "n_samples": 1500}
    d.update(kw)
    return d


def _diag(*findings):
    return {"format": "magalign.diagnosis/1", "findings": [
        {"effect": e, "params": p} for e, p in findings]}


def _write(folder: Path, name: str, cal: dict, diag: dict | None = None, marker=True) -> None:
    d = folder / name
    d.mkdir(parents=True, exist_ok=True)
    (d / "calibration.json").write_text(json.dumps(cal))
    if diag is not None:
        (d / "diagnosis.json").write_text(json.dumps(diag))
    if marker:
        (d / ".magalign-done.json").write_text("{}")


CASES = [
    # (result calibration overrides, result findings, expected regressed quantities)
    ({}, [("disturbance", {"windows_s": [[10.0, 16.0]], "peak_nT": 60.0})], []),
    ({"rotvec": (1.2, -1.0, 1.7)}, None, ["rotation_deg"]),
    ({"rotvec": (1.25, -1.0, 1.2)}, None, ["rotation_deg"]),  # 0.05 deg: 5 sigma about x
    ({"rotvec": (1.205, -1.0, 1.2)}, None, []),  # 0.5 sigma
    ({"sigma": (0.01, 0.01, None)}, None, ["sigma_rotvec_deg.z"]),
    ({"sigma": (0.0105, 0.009, 0.021)}, None, []),
    ({"sigma": (0.02, 0.01, 0.02)}, None, ["sigma_rotvec_deg.x"]),
    ({"offset_nT": [1.0, 2.0, 3.0]}, None, ["offset_nT"]),
    ({"residual_rms_nT": 10.4}, None, []),
    ({"residual_rms_nT": 12.0}, None, ["residual_rms_nT"]),
    ({}, [], ["findings"]),
    ({}, [("disturbance", {"windows_s": [[10.5, 16.2]], "peak_nT": 66.0})], []),
    ({}, [("disturbance", {"windows_s": [[12.0, 16.0]], "peak_nT": 60.0})],
     ["findings.disturbance.windows_s"]),
    ({}, [("disturbance", {"windows_s": [[10.0, 16.0]], "peak_nT": 90.0})],
     ["findings.disturbance.peak_nT"]),
    ({}, [("disturbance", {"windows_s": [[10.0, 16.0]], "peak_nT": 60.0}),
          ("hard_iron", {"offset_nT": [5.0, 0.0, 0.0]})], ["findings"]),
]


@pytest.mark.parametrize(("change", "findings", "expected"), CASES)
def test_tolerances_per_quantity(tmp_path, change, findings, expected):
    base_f = [("disturbance", {"windows_s": [[10.0, 16.0]], "peak_nT": 60.0})]
    _write(tmp_path / "base", "rec", _cal((1.2, -1.0, 1.2)), _diag(*base_f), marker=False)
    change = dict(change)
    rv = change.pop("rotvec", (1.2, -1.0, 1.2))
    sg = change.pop("sigma", (0.01, 0.01, 0.02))
    res_f = base_f if findings is None else findings
    _write(tmp_path / "res", "rec", _cal(rv, sg, **change), _diag(*res_f))
    rows = compare(tmp_path / "res", tmp_path / "base")
    got = sorted(r.quantity for r in rows if r.status == REGRESSION)
    assert got == sorted(expected), format_table(rows)


def test_tolerances_file_overrides(tmp_path):
    _write(tmp_path / "base", "rec", _cal((1.2, -1.0, 1.2)), marker=False)
    _write(tmp_path / "res", "rec", _cal((1.2, -1.0, 1.5)))
    assert any(r.status == REGRESSION for r in compare(tmp_path / "res", tmp_path / "base"))
    (tmp_path / "base" / "tolerances.toml").write_text("[tolerances]\nrotation_deg = 0.5\n")
    assert not any(r.status == REGRESSION for r in compare(tmp_path / "res", tmp_path / "base"))
    (tmp_path / "base" / "tolerances.toml").write_text("[tolerances]\nrotaton_deg = 0.5\n")
    from pipeline.core.errors import ConfigError

    with pytest.raises(ConfigError) as ei:
        compare(tmp_path / "res", tmp_path / "base")
    assert ei.value.line == 2 and "rotaton_deg" in ei.value.one_line()
    assert Tolerances().rotation_deg < 0.5


# --------------------------------------------------------------------------- real recordings

@pytest.mark.real
@pytest.mark.slow
@pytest.mark.skipif(not REAL.is_dir(), reason=f"real recordings not present ({REAL})")
@pytest.mark.skipif(not (GOLDEN / "real").is_dir(),
                    reason="no stored baseline of the real recordings (run make golden)")
def test_real_recordings_match_golden(real_outputs):
    # make_golden's campaign of the real recordings, processed once for the suite
    out = real_outputs.out
    assert real_outputs.returncode in (0, 3), real_outputs.stderr
    r = _cli("regress", str(out), "--baseline", str(GOLDEN / "real"))
    assert r.returncode == 0, r.stdout + r.stderr
    # each calibration says of the repeated messages what its own fit did with them: lab_01
    # and lab_02's final models fit every message (their diagnosis names no sample_hold),
    # lab_03-05's leave the repeats out
    for name in ("lab_01", "lab_02", "lab_03", "lab_04", "lab_05"):
        cal = json.loads((out / name / "calibration.json").read_text(encoding="utf-8"))
        said = [w for w in cal["warnings"] if w.startswith("sample-and-hold:")]
        left_out = "repeats left out" in cal["checks"]["fit_samples"].get("note", "")
        assert len(said) == 1 and said[0].endswith("the repeats were left out") == left_out, (
            name, said, cal["checks"]["fit_samples"])
        assert left_out == (name not in ("lab_01", "lab_02")), name


# --------------------------------------------------------------------------- tolerances in sigmas

#: A value moved by this many of its own sigmas must be caught; by the second, not.
CAUGHT_SIGMAS, PASSED_SIGMAS = 5.0, 0.5


def _cal_with_sigmas() -> dict:
    return _cal((1.2, -1.0, 1.2), offset_nT=[-300.0, 250.0, 190.0],
                sigma_offset_nT=[30.0, 18.0, 18.0],
                D=[[1.0006, 0.0086, -0.0056], [0.0086, 0.9991, -0.0075],
                   [-0.0056, -0.0075, 1.0003]],
                sigma_D=[[7e-4, 6e-4, 5e-4], [6e-4, 6e-4, 4e-4], [5e-4, 4e-4, 5e-4]],
                time_offset_s=0.0152, sigma_time_offset_s=2.3e-4,
                sigma_B_enu_nT=[30.0, 39.0, 23.0])


def _shift(cal: dict, diag: dict, what: str, k: float) -> None:
    """Move one quantity by ``k`` of its own sigmas (in place)."""
    if what == "rotation_deg":
        s = cal["sigma_rotvec_deg"][1]
        dR = quat_to_matrix(rotvec_to_quat(np.radians([0.0, k * s, 0.0])))
        R = dR @ np.asarray(cal["R_body_mag"])
        from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec

        cal["R_body_mag"] = R.tolist()
        cal["rotvec_body_mag_deg"] = np.degrees(quat_to_rotvec(matrix_to_quat(R))).tolist()
    elif what == "D":
        d = np.asarray(cal["D"])
        d[0, 1] += k * cal["sigma_D"][0][1]
        d[1, 0] = d[0, 1]
        cal["D"] = d.tolist()
    elif what == "time_offset_s":
        cal["time_offset_s"] += k * cal["sigma_time_offset_s"]
    elif what in ("offset_nT", "B_enu_nT"):
        v = list(cal[what])
        v[2] += k * cal[f"sigma_{what}"][2]
        cal[what] = v
    else:  # a finding's parameter, with the sigma the finding carries
        f = diag["findings"][0]
        f["params"]["peak_nT"] += k * f["sigma"]["peak_nT"]


@pytest.mark.parametrize("what", ["rotation_deg", "offset_nT", "D", "time_offset_s",
                                  "B_enu_nT", "findings.disturbance.peak_nT"])
@pytest.mark.parametrize("k", [CAUGHT_SIGMAS, PASSED_SIGMAS])
def test_change_in_own_sigmas(tmp_path, what, k):
    """5 sigma of a quantity's own uncertainty is a regression, 0.5 sigma is not."""
    def diag() -> dict:
        return {"format": "magalign.diagnosis/1", "findings": [
            {"effect": "disturbance", "params": {"windows_s": [[10.0, 16.0]], "peak_nT": 60.0},
             "sigma": {"peak_nT": 5.0}}]}

    _write(tmp_path / "base", "rec", _cal_with_sigmas(), diag(), marker=False)
    cal, dg = _cal_with_sigmas(), diag()
    _shift(cal, dg, what, k)
    _write(tmp_path / "res", "rec", cal, dg)
    rows = compare(tmp_path / "res", tmp_path / "base")
    got = sorted(r.quantity for r in rows if r.status == REGRESSION)
    assert got == ([what] if k == CAUGHT_SIGMAS else []), format_table(rows)


def _golden_copy(src: Path, dst: Path) -> list[str]:
    """A stored baseline as a finished results folder; its recordings' names."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.md", "*.toml"))
    names = sorted(p.name for p in dst.iterdir() if (p / "calibration.json").is_file())
    for n in names:
        (dst / n / ".magalign-done.json").write_text("{}")
    return names


@pytest.mark.parametrize("golden", ["demo", "real"])
@pytest.mark.parametrize("k", [CAUGHT_SIGMAS, PASSED_SIGMAS])
def test_stored_baselines_hold_their_own_sigmas(tmp_path, golden, k):
    """On every stored calibration (sigmas from 0.0004 deg to 6 deg, from 40 us to 0.8 ms):
    the rotation moved by 5 of its own sigmas about y, and the time offset (calibration and
    finding) by 5 of theirs, are caught; by 0.5 of them, not."""
    src = GOLDEN if golden == "demo" else GOLDEN / "real"
    res = tmp_path / "res"
    names = _golden_copy(src, res)
    assert names
    expected = []
    for n in names:
        cal = json.loads((res / n / "calibration.json").read_text())
        dgf = res / n / "diagnosis.json"
        dg = json.loads(dgf.read_text()) if dgf.is_file() else {"findings": []}
        _shift(cal, dg, "rotation_deg", k)
        expected.append((n, "rotation_deg"))
        if cal.get("time_offset_s") is not None:
            _shift(cal, dg, "time_offset_s", k)
            expected.append((n, "time_offset_s"))
        for f in dg["findings"]:
            if f["effect"] == "time_offset":
                f["params"]["time_offset_s"] += k * f["sigma"]["time_offset_s"]
                expected.append((n, "findings.time_offset.time_offset_s"))
                break
        (res / n / "calibration.json").write_text(json.dumps(cal))
        if dgf.is_file():
            dgf.write_text(json.dumps(dg))
    rows = compare(res, src)
    got = sorted((r.recording, r.quantity) for r in rows if r.status == REGRESSION)
    assert got == (sorted(expected) if k == CAUGHT_SIGMAS else []), format_table(
        rows, failures_only=True)


def test_real_baseline_says_where_each_recording_was_checked():
    """Beside the real goldens, a note names for every recording what confirmed its values
    from outside the code, and says where nothing did."""
    if not (GOLDEN / "real").is_dir():
        pytest.fail("tests/golden/real is part of the repository and missing")
    text = (GOLDEN / "real" / "PROVENANCE.md").read_text(encoding="utf-8")
    names = sorted(p.name for p in (GOLDEN / "real").iterdir() if p.is_dir())
    assert names
    for n in names:
        assert n in text, n
    for value in ("time_offset_s", "B_enu_nT", "R_body_mag", "offset_nT", "D",
                  "sample_hold", "field_gradient", "hard_iron_step", "local_source"):
        assert f"`{value}" in text, value
    assert "## Values with no outside check" in text
