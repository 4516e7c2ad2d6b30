"""Campaigns: configuration, executors (real process pool and Dask LocalCluster), resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from _pause import wait_paused

from pipeline.app.campaign import (
    DONE_MARKER,
    RecordingRole,
    campaign_for_input,
    load_campaign,
    make_task,
    output_dir,
    run_campaign,
)
from pipeline.app.executors import LocalExecutor, SerialExecutor
from pipeline.app.regress import recordings_in
from pipeline.core.config import TomlDoc
from pipeline.core.errors import ConfigError

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
DEMO = HERE.parent / "pipeline" / "demo"
sys.path.insert(0, str(HERE))  # make_golden holds the archived scenarios


def _cli(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.app.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=HERE.parent)


def _campaign(tmp: Path, body: str, name: str = "c.toml") -> Path:
    p = tmp / name
    p.write_text(body, encoding="utf-8")
    return p


HEAD = """\
[campaign]
name = "t"

[channels]
mag = "/mag"
attitude = "/novatel/oem7/inspva"

[outputs]
rerun = false
report = false
"""


# --------------------------------------------------------------------------- configuration

def test_demo_campaign_orders_calibration_first():
    c = load_campaign(DEMO / "campaign.toml")
    roles = [r.role for r in c.recordings]
    assert roles[0] is RecordingRole.CALIBRATION
    assert RecordingRole.CALIBRATION not in roles[1:]
    lines = [r for r in c.recordings if r.calibration_from]
    assert {r.name for r in lines} == {"line_01", "line_02", "line_03"}
    assert all(r.calibration_from == "calibration_rotation" for r in lines)
    assert len(c.recordings) == 5
    assert all(r.scenario and Path(r.scenario).is_file() for r in c.recordings)


def test_calibration_order_independent_of_file_order(tmp_path):
    body = HEAD + f"""
[[recordings]]
path = "{(DATA / 'line_restored.mcap').as_posix()}"
calibration = "rotation"

[[recordings]]
path = "{(DATA / 'rotation.mcap').as_posix()}"
role = "calibration"
"""
    c = load_campaign(_campaign(tmp_path, body))
    assert [r.name for r in c.recordings] == ["rotation", "line_restored"]
    first, rest = c.stages()
    assert [r.name for r in first] == ["rotation"] and [r.name for r in rest] == ["line_restored"]


BAD = [
    # (body after HEAD, key in message, line of the offending key, words in the message)
    ('[[recordings]]\npath = "x.mcap"\nrole = "rotation"\n', "recordings[0].role", 14,
     "calibration or survey"),
    ('[[recordings]]\nscenario = "{demo}/line_01.toml"\n\n[[recordings]]\n'
     'scenario = "{demo}/line_02.toml"\ncalibraton = "line_01"\n',
     "recordings[1].calibraton", 17, "unknown key"),
    ('[[recordings]]\nscenario = "{demo}/line_01.toml"\ncalibration = "nope"\n',
     "recordings[0].calibration", 14, "not a calibration recording"),
    ('[[recordings]]\nglob = "nothing_here/*.mcap"\n', "recordings[0].glob", 13, "matches no"),
    ('[[recordings]]\nscenario = "{demo}/line_01.toml"\nseed = -3\n', "recordings[0].seed", 14,
     "non-negative"),
]


@pytest.mark.parametrize(("body", "key", "line", "words"), BAD)
def test_config_errors_name_file_key_line(tmp_path, body, key, line, words):
    p = _campaign(tmp_path, HEAD + "\n" + body.format(demo=DEMO.as_posix()))
    with pytest.raises(ConfigError) as ei:
        load_campaign(p)
    e = ei.value
    msg = e.one_line()
    assert str(p) in msg and key in msg and f"line {line}" in msg and words in msg
    assert e.key == key and e.line == line
    # the line really holds the key (the reported line is not a guess)
    assert key.split(".")[-1] in p.read_text().splitlines()[line - 1]


@pytest.mark.parametrize(("text", "key"), [
    ('[estimator]\nkind = "magic"\n', "estimator.kind"),
    ('[estimator]\nterms = ["offset", "gremlins"]\n', "estimator.terms"),
    ('[campaign]\ndata_dir = "../outside"\n', "campaign.data_dir"),
    ('[reference_field]\nmode = "fixed"\nenu_nT = [0.2, 0.1, -0.5]\n', "reference_field.enu_nT"),
    ('[outputs]\nrerun = "yes"\n', "outputs.rerun"),
    ('[bogus]\nx = 1\n', "bogus"),
])
def test_config_errors_in_tables(tmp_path, text, key):
    body = text + f'\n[[recordings]]\nscenario = "{(DEMO / "line_01.toml").as_posix()}"\n'
    p = _campaign(tmp_path, body)
    with pytest.raises(ConfigError) as ei:
        load_campaign(p)
    assert ei.value.key == key
    assert ei.value.line == TomlDoc.parse(body, str(p)).line_of(key) is not None
    assert str(p) in ei.value.one_line()


def test_config_syntax_error_names_line(tmp_path):
    p = _campaign(tmp_path, '[campaign]\nname = "x"\n[[recordings]\npath = 1\n')
    with pytest.raises(ConfigError) as ei:
        load_campaign(p)
    assert ei.value.line == 3 and str(p) in ei.value.one_line()


def test_config_is_data_not_code(tmp_path):
    # Python in a string value stays a string: it names a file that does not exist.
    body = HEAD + '\n[[recordings]]\npath = "__import__(\'os\').system(\'false\')"\n'
    with pytest.raises(ConfigError, match="file not found"):
        load_campaign(_campaign(tmp_path, body))


@pytest.mark.parametrize("hostile", ["../../escape", "/etc/passwd", "..", "a/../../b", "~x"])
def test_hostile_names_stay_inside_output(tmp_path, hostile):
    body = HEAD + (
        f'\n[[recordings]]\nname = "{hostile}"\nscenario = "{(DEMO / "line_01.toml").as_posix()}"'
        f'\nrole = "calibration"\n'
        f'\n[[recordings]]\nscenario = "{(DEMO / "line_02.toml").as_posix()}"\n'
        f'calibration = "{hostile}"\n')
    c = load_campaign(_campaign(tmp_path, body))
    out = (tmp_path / "out").resolve()
    for spec in c.recordings:
        task = make_task(spec, out, c.data_dir, None)
        for p in (output_dir(task), Path(task.input_path)):
            assert out in p.resolve().parents
            assert ".." not in p.relative_to(out).parts
    assert c.recordings[1].calibration_from == c.recordings[0].name


def test_output_name_collision_is_an_error(tmp_path):
    body = HEAD + "".join(
        f'\n[[recordings]]\nname = "{n}"\nscenario = "{(DEMO / "line_01.toml").as_posix()}"\n'
        for n in ("a/b", "a_b"))
    with pytest.raises(ConfigError, match="same output name|output name") as ei:
        load_campaign(_campaign(tmp_path, body))
    assert ei.value.line == 16  # the second [[recordings]] header


# --------------------------------------------------------------------------- running

def _tiny_campaign(tmp: Path, hostile: bool = False) -> Path:
    rot = (DATA / "rotation.mcap").as_posix()
    line = (DATA / "line_restored.mcap").as_posix()
    dist = (DATA / "line_disturbed.mcap").as_posix()
    third = f'path = "{dist}"' if not hostile else (
        f'name = "../../escape"\nscenario = "{tmp.as_posix()}/s.toml"')
    if hostile:
        from make_golden import small_scenario_texts

        (tmp / "s.toml").write_text(small_scenario_texts()["line_disturbed"], encoding="utf-8")
    body = HEAD + f"""
[[recordings]]
path = "{rot}"
role = "calibration"

[[recordings]]
path = "{line}"
calibration = "rotation"

[[recordings]]
{third}
"""
    return _campaign(tmp, body)


def test_dask_local_campaign_gives_three_rows(tmp_path):
    camp = _tiny_campaign(tmp_path, hostile=True)
    out = tmp_path / "out"
    r = _cli("process", str(camp), "--out", str(out), "--dask-local", "2")
    assert r.returncode == 0, r.stderr
    assert "Dask LocalCluster of 2" in r.stdout
    t = pq.read_table(out / "summary.parquet").to_pylist()
    assert len(t) == 3
    assert [row["status"] for row in t] == ["ok", "ok", "ok"]
    assert [row["name"] for row in t] == ["rotation", "line_restored", "_.._escape"]
    assert t[1]["calibration_from"] == "rotation"
    # the survey line is restored with exactly the rotation's calibration
    assert t[1]["rotvec_deg_x"] == t[0]["rotvec_deg_x"]
    # the hidden disturbance of the third recording is found (known answer of the scenario)
    assert "disturbance" in t[2]["findings"]
    # truth of the scenarios: misalignment rotvec (1.2, -1.0, 1.2) deg
    for a, v in zip("xyz", (1.2, -1.0, 1.2), strict=True):
        assert abs(t[0][f"rotvec_deg_{a}"] - v) < 0.05
    # nothing escaped the output folder: every file is under out
    assert not (tmp_path.parent / "escape").exists()
    assert (out / "_.._escape" / DONE_MARKER).is_file()
    assert (out / "data" / "_.._escape.mcap").is_file()
    html = (out / "summary.html").read_text()
    assert html.split("<tbody>")[1].count("<tr>") == 3  # one row per recording


def test_failure_does_not_stop_the_rest(tmp_path):
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 50)
    good = tmp_path / "good.mcap"
    good.write_bytes((DATA / "line_restored.mcap").read_bytes())
    out = tmp_path / "out"
    # a folder is every *.mcap directly in it, named after the file
    folder = campaign_for_input(tmp_path, out_dir=out)
    assert [r.name for r in folder.recordings] == ["broken", "good"]
    camp = _campaign(tmp_path, HEAD + '\n[[recordings]]\nglob = "*.mcap"\n')
    r = _cli("process", str(camp), "--out", str(out), "--jobs", "2", "--no-progress")
    assert r.returncode == 3, r.stderr
    assert "FAILED broken" in r.stderr and "broken.mcap" in r.stderr
    rows = {row["name"]: row for row in pq.read_table(out / "summary.parquet").to_pylist()}
    assert rows["good"]["status"] == "ok" and rows["broken"]["status"] == "failed"
    assert rows["broken"]["error"]
    assert not (out / "broken" / DONE_MARKER).exists()
    # inputs are never modified
    assert good.read_bytes() == (DATA / "line_restored.mcap").read_bytes()


def test_failed_calibration_run_fails_its_lines(tmp_path):
    bad = tmp_path / "rot.mcap"
    bad.write_bytes(b"not an mcap at all")
    body = HEAD + f"""
[[recordings]]
path = "{bad.as_posix()}"
role = "calibration"

[[recordings]]
path = "{(DATA / 'line_restored.mcap').as_posix()}"
calibration = "rot"
"""
    c = load_campaign(_campaign(tmp_path, body))
    res = run_campaign(c, tmp_path / "out", SerialExecutor())
    assert [r["status"] for r in res] == ["failed", "failed"]
    assert "calibration run rot failed" in res[1]["error"]


def test_reuse_and_invalidation(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    (src / "a.mcap").write_bytes((DATA / "rotation.mcap").read_bytes())
    c = load_campaign(_campaign(tmp_path, HEAD + '\n[[recordings]]\npath = "in/a.mcap"\n'))
    out = tmp_path / "out"
    ex = LocalExecutor(1)
    try:
        assert run_campaign(c, out, ex)[0]["status"] == "ok"
        marker = out / "a" / DONE_MARKER
        stamp = marker.stat().st_mtime_ns
        assert run_campaign(c, out, ex)[0]["status"] == "reused"
        assert marker.stat().st_mtime_ns == stamp
        # a partial output (no marker) is processed again, never taken as finished
        marker.unlink()
        assert recordings_in(out, need_marker=True) == []
        assert run_campaign(c, out, ex)[0]["status"] == "ok"
        # a deleted output file is made again
        (out / "a" / "metrics.json").unlink()
        assert run_campaign(c, out, ex)[0]["status"] == "ok"
        # a changed configuration is processed again
        c2 = load_campaign(_campaign(tmp_path, HEAD.replace('rerun = false', 'rerun = false\n'
                                     'diagnose = false') + '\n[[recordings]]\npath = "in/a.mcap"\n',
                                     "c2.toml"))
        assert run_campaign(c2, out, ex)[0]["status"] == "ok"
        # changed input bytes are processed again
        (src / "a.mcap").write_bytes((DATA / "line_restored.mcap").read_bytes())
        assert run_campaign(c2, out, ex)[0]["status"] == "ok"
        assert run_campaign(c2, out, ex)[0]["status"] == "reused"
    finally:
        ex.close()


def _marker_state(out: Path) -> dict[str, tuple[int, str]]:
    st = {}
    for m in out.glob(f"*/{DONE_MARKER}"):
        st[m.parent.name] = (m.stat().st_mtime_ns, m.read_text())
    return st


def _check_finished_outputs_complete(out: Path) -> None:
    for name in recordings_in(out, need_marker=True):
        d = out / name
        json.loads((d / "calibration.json").read_text())
        json.loads((d / "metrics.json").read_text())
        assert (d / f"{name}.corrected.mcap").stat().st_size > 0


def test_killed_run_resumes_without_redoing_or_trusting_partial_output(tmp_path):
    from pipeline.core.atomic import PAUSE_AT_ENV, PAUSE_DIR_ENV

    camp = _tiny_campaign(tmp_path)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "pipeline.app.cli", "process", str(camp), "--out", str(out),
           "--jobs", "1", "--no-progress"]
    # Kill points chosen by the test (the atomic-write hook), each with the markers that
    # must exist then: every output of rotation written but not its done-marker; rotation
    # finished and line_restored begun; line_restored finished and line_disturbed partway.
    stops = [("written rotation/.magalign-done.json", set()),
             ("created line_restored/calibration.json", {"rotation"}),
             ("renamed line_disturbed/metrics.json", {"rotation", "line_restored"})]
    states = []
    for k, (at, markers) in enumerate(stops):
        hook = tmp_path / f"hook{k}"
        hook.mkdir()
        env = {**os.environ, PAUSE_DIR_ENV: str(hook), PAUSE_AT_ENV: at}
        p = subprocess.Popen(cmd, cwd=HERE.parent, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True, env=env)
        try:
            assert wait_paused(p, hook).endswith(at)
        finally:
            os.killpg(p.pid, signal.SIGKILL)  # the run and its worker processes
            p.wait()
        state = _marker_state(out)
        assert set(state) == markers, (at, sorted(state))
        _check_finished_outputs_complete(out)
        states.append(state)
    # the partial outputs left by a kill are there, without a marker
    assert (out / "line_disturbed" / "metrics.json").is_file()
    # a finished recording is not redone by a later (killed) run
    assert states[2]["rotation"] == states[1]["rotation"]
    before = _marker_state(out)
    r = subprocess.run(cmd, cwd=HERE.parent, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    after = _marker_state(out)
    assert set(after) == {"rotation", "line_restored", "line_disturbed"}
    for name, state in before.items():
        assert after[name] == state, f"{name} was redone"
    table = pq.read_table(out / "summary.parquet").to_pylist()
    rows = {row["name"]: row["status"] for row in table}
    assert rows == {"rotation": "reused", "line_restored": "reused", "line_disturbed": "ok"}
    _check_finished_outputs_complete(out)
    # temporary files of the killed runs are gone; none was taken as a result
    assert not list(out.glob(".*.tmp")) and not list(out.glob("*/.*.tmp"))


def test_calibration_file_restores_survey_recording(tmp_path):
    from pipeline.app.campaign import RecordingOptions
    from pipeline.model.calibration import Calibration

    rot = tmp_path / "rot_out"
    opts = RecordingOptions(outputs=(("diagnose", False), ("report", False), ("rerun", False)))
    c_rot = campaign_for_input(DATA / "rotation.mcap", options=opts)
    assert run_campaign(c_rot, rot, SerialExecutor())[0]["status"] == "ok"
    cal_file = rot / "rotation" / "calibration.json"
    c_line = campaign_for_input(DATA / "line_restored.mcap", options=opts)
    out = tmp_path / "out"
    res = run_campaign(c_line, out, SerialExecutor(), calibration_path=cal_file)
    assert res[0]["status"] == "ok" and res[0]["calibration_from"] == "--calibration"
    used = Calibration.load(out / "line_restored" / "calibration.json")
    np.testing.assert_allclose(used.R_body_mag, Calibration.load(cal_file).R_body_mag)
    # a different calibration file is a different configuration: processed again
    d = json.loads(cal_file.read_text())
    d["residual_rms_nT"] += 1.0
    other = tmp_path / "other.json"
    other.write_text(json.dumps(d))
    assert run_campaign(c_line, out, SerialExecutor(), calibration_path=other)[0]["status"] == "ok"
    assert run_campaign(c_line, out, SerialExecutor(), calibration_path=other)[0]["status"] == \
        "reused"


def _blas_threads(_: int) -> list[int]:
    from threadpoolctl import threadpool_info

    return [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]


def test_local_workers_share_the_cores_among_their_blas_threads():
    """Each of N workers' BLAS gets cpu_count // N threads (no oversubscription)."""
    ex = LocalExecutor(2)
    try:
        got = [res for _, res in ex.map(_blas_threads, [0, 1, 2])]
    finally:
        ex.close()
    want = max(1, (os.cpu_count() or 1) // 2)
    assert all(not isinstance(r, BaseException) for r in got), got
    assert all(r and set(r) == {want} for r in got), got
