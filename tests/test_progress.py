"""Progress per stage: a redrawn line with the time left on a terminal, else one plain line
per stage of each recording; -v prints each stage's time."""

from __future__ import annotations

import contextlib
import io
import os
import pty
import re
import select
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from pipeline.core import progress as pg
from tests import corpus

MAGALIGN = [sys.executable, "-c", "import sys; from pipeline.app.cli import main; sys.exit(main())"]


def _env(**kw: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in (pg.ENV_MODE, pg.ENV_DIR)}
    env.update(kw)
    return env


def _run_on_pty(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[int, str]:
    """Run with stderr on a pseudo-terminal; return the exit status and what it showed."""
    master, slave = pty.openpty()
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=slave,
                            stdin=subprocess.DEVNULL)
    os.close(slave)
    chunks: list[bytes] = []
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        r, _, _ = select.select([master], [], [], 0.5)
        if r:
            try:
                data = os.read(master, 65536)
            except OSError:  # the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    rc = proc.wait(timeout=60)
    os.close(master)
    return rc, b"".join(chunks).decode("utf-8", "replace")


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return corpus.valid(tmp_path_factory.mktemp("progress"))


@contextlib.contextmanager
def _diagnosing(disp: pg.ProgressDisplay, name: str, detail: str) -> Iterator[None]:
    """``name`` half-way through its diagnosis (stage 2 of 3), reported to ``disp``."""
    with pg.use_sink(pg.DirectSink(name, disp.update)):
        pg.stage("Ingest", 0, 3, ["Ingest", "Diagnose", "Report"])
        pg.stage("Diagnose", 1, 3)
        pg.detail(detail, 0.5, 1.0)
        yield


def test_line_names_stage_and_time_left():
    disp = pg.ProgressDisplay(2, "magalign process", enabled=False)
    disp.started -= 10.0
    with _diagnosing(disp, "line_04", "search 1, candidate 3/9"):
        line = disp.line(width=200)
        assert "[0/2]" in line and "line_04: diagnosing (2/3): search 1, candidate 3/9" in line
        assert "left ~" in line and "elapsed 0:10" in line
        # the stage weights decide the fraction: half of the diagnosis is most of this run
        w = pg.STAGE_WEIGHTS
        expect = (w["Ingest"] + 0.5 * w["Diagnose"]) / (w["Ingest"] + w["Diagnose"] + w["Report"])
        assert f"{100 * expect / 2:3.0f}%" in line
    disp.run_done("line_04")
    assert "[1/2]" in disp.line() and "line_04" not in disp.line()


def test_line_fits_80_columns_with_the_time_left():
    """A long name and stage are shortened; the percentage and both times stay whole."""
    disp = pg.ProgressDisplay(12, "magalign process", enabled=False)
    disp.started -= 3725.0
    with _diagnosing(disp, "a_recording_with_a_very_long_name_2026-11-20",
                     "search 3, candidate 17/40: local source near 41.2 s"):
        for width in (79, 60):
            line = disp.line(width=width)
            assert len(line) <= width, line
            assert re.search(r"elapsed 1:02:05  left ~\d+:\d\d:\d\d$", line), line
            assert "..." in line and "%" in line
        assert len(disp.line()) <= 79  # the default: 80 columns, less one


def test_library_calls_without_sink_do_nothing():
    assert pg.current() is None
    pg.stage("Ingest", 0, 1)
    pg.detail("nothing listens")


def test_redrawn_line_only_on_a_terminal(monkeypatch):
    monkeypatch.delenv(pg.ENV_MODE, raising=False)
    assert not pg.enabled_for(io.StringIO())
    assert pg.mode_for(io.StringIO()) == pg.LOG  # a log of the stages instead
    monkeypatch.setenv(pg.ENV_MODE, "always")
    assert pg.enabled_for(io.StringIO())
    monkeypatch.setenv(pg.ENV_MODE, "lines")
    assert pg.mode_for(io.StringIO()) == pg.LOG
    monkeypatch.setenv(pg.ENV_MODE, "never")
    assert not pg.enabled_for(io.StringIO()) and pg.mode_for(io.StringIO()) == pg.OFF
    monkeypatch.setenv(pg.ENV_MODE, "always")
    assert pg.mode_for(io.StringIO(), disable=True) == pg.OFF  # --no-progress wins


def _three_stages(disp: pg.ProgressDisplay, name: str) -> None:
    with pg.use_sink(pg.DirectSink(name, disp.update)):
        pg.stage("Ingest", 0, 3, ["Ingest", "Diagnose", "Report"])
        for _ in range(50):
            pg.detail("search 1, candidate 3/9", 0.5, 1.0)  # never a line of its own
        pg.stage("Diagnose", 1, 3)
        pg.stage("Report", 2, 3)
        disp.run_done(name)


def test_log_waits_then_tells_every_stage_once():
    """Without a terminal: nothing while the command is young, then each stage once."""
    buf = io.StringIO()
    disp = pg.ProgressDisplay(1, "magalign calibrate", stream=buf, log=True, log_after_s=60.0)
    _three_stages(disp, "lab_03")
    disp.draw()
    assert buf.getvalue() == ""  # the run ended within its first minute: nothing yet
    disp.started -= 61.0
    disp.draw()
    disp.draw()  # a second poll prints nothing new
    assert buf.getvalue().splitlines() == [
        "magalign: lab_03: reading (1/3), 1:01 elapsed",
        "magalign: lab_03: diagnosing (2/3), 1:01 elapsed",
        "magalign: lab_03: writing report (3/3), 1:01 elapsed",
        "magalign: lab_03: done, 1:01 elapsed"]


def test_log_of_a_command_that_ends_at_once_is_empty():
    """A command that ends (or refuses its input) before the log starts prints no stage."""
    buf = io.StringIO()
    with pg.ProgressDisplay(1, "magalign calibrate", stream=buf, log=True,
                            log_after_s=pg.LOG_AFTER_S) as disp:
        with pg.use_sink(pg.DirectSink("empty", disp.update)):
            pg.stage("Ingest", 0, 1)
    assert buf.getvalue() == ""


def test_log_line_never_cuts_a_number(monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    buf = io.StringIO()
    disp = pg.ProgressDisplay(12, "magalign process", stream=buf, log=True)
    disp.started -= 3725.0
    _three_stages(disp, "a_recording_with_a_very_long_name_from_the_second_survey_2026-11-20")
    disp.draw()
    lines = buf.getvalue().splitlines()
    assert all(len(ln) <= 80 for ln in lines), lines
    text = " ".join(ln.strip() for ln in lines)
    assert "_2026-11-20: writing report (3/3), 1:02:05 elapsed" in text
    assert "done (1 of 12 recordings), 1:02:05 elapsed" in text


def test_drawn_line_is_cleared():
    buf = io.StringIO()
    disp = pg.ProgressDisplay(1, "magalign", stream=buf, enabled=True)
    disp.update({"name": "r", "stages": ["Ingest"], "index": 0, "detail": "",
                 "fraction": 0.0, "stage_started": time.time()})
    disp.draw()  # what the display's thread does a few times a second
    disp.close()
    out = buf.getvalue()
    assert "r: reading (1/1)" in out
    assert out.endswith("\r")  # the line is blanked when done: the results print cleanly


def test_process_single_recording_on_terminal(recording, tmp_path):
    """One recording: the line goes through its stages (not a bar sitting at 0/1)."""
    rc, shown = _run_on_pty(MAGALIGN + ["-v", "process", str(recording), "--out",
                                        str(tmp_path / "out")], tmp_path, _env())
    assert rc == 0, shown
    frames = [f for f in shown.replace("\n", "\r").split("\r") if "magalign process" in f]
    assert frames and all("elapsed" in f for f in frames), shown
    # the recording's stage is on the line (the worker's progress file reached it), not a
    # bar of recordings sitting at 0/1 (the line is redrawn 4 times a second; a run with a
    # report takes seconds)
    assert any(re.search(r"valid: [a-z ]+ \(\d+/\d+\)", f) for f in frames), frames
    # -v: the time of each stage once the recording is done
    assert "valid: reading" in shown and " s, " in shown


#: one line of the log: the recording, the stage and its count, the time since the start
STAGE_LINE = re.compile(r"magalign: (?P<name>\w+): (?P<what>[A-Za-z ]+) \((?P<k>\d+)/(?P<n>\d+)\), "
                        r"\d+:\d\d elapsed")
END_LINE = re.compile(r"magalign: (?P<name>\w+): done( \(\d+ of \d+ recordings\))?, "
                      r"\d+:\d\d elapsed")


def _check_log(stderr: str, name: str, complete: bool) -> list[str]:
    """Check a log of the stages of run ``name``; return its stages' words in order.

    Every line plain (no carriage return, no escape code) and within 80 columns; each stage
    once, in order, with one total; the run's end last. ``complete``: from the first stage.
    """
    assert "\r" not in stderr and "\x1b" not in stderr, repr(stderr)
    lines = [ln for ln in stderr.splitlines() if ln.startswith(f"magalign: {name}: ")]
    assert all(len(ln) <= 80 for ln in stderr.splitlines()), stderr
    stages = [m for m in map(STAGE_LINE.fullmatch, lines) if m]
    if not complete and not lines:
        return []
    assert END_LINE.fullmatch(lines[-1]) and len(stages) == len(lines) - 1, lines
    counts = [int(m["k"]) for m in stages]
    assert counts == list(range(counts[0], counts[0] + len(counts))), lines
    assert len({m["n"] for m in stages}) == 1 and counts[-1] == int(stages[0]["n"]), lines
    if complete:
        assert counts[0] == 1, lines
    return [m["what"] for m in stages]


@pytest.mark.parametrize("command", ["process", "calibrate"])
def test_one_plain_line_per_stage_without_a_terminal(recording, tmp_path, command):
    """Not a terminal (a log, CI): one line per stage, in order, the same in every mode."""
    argv = MAGALIGN + [command, str(recording), "--out", str(tmp_path / "o")]
    res = subprocess.run(argv, cwd=tmp_path, env=_env(**{pg.ENV_MODE: "lines"}),
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    stages = _check_log(res.stderr, "valid", complete=True)
    assert stages[:7] == ["reading", "aligning", "segmenting", "estimating", "checking",
                          "diagnosing", "judging"], res.stderr
    if command == "process":
        assert stages[7:9] == ["restoring", "metrics"] and stages[-1] == "writing report"
    assert "elapsed" not in res.stdout  # stdout stays what other programs read
    # the default: the same lines, those of the first seconds held until the log starts
    res = subprocess.run(argv, cwd=tmp_path, env=_env(), capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr
    _check_log(res.stderr, "valid", complete=False)
    assert "elapsed" not in res.stdout
    res = subprocess.run(argv, cwd=tmp_path, env=_env(**{pg.ENV_MODE: "never"}),
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0 and res.stderr == "", res.stderr


def test_campaign_workers_log_each_stage_once(recording, tmp_path):
    """Recordings in worker processes: each one's stages once and in order, then its end."""
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("line_a", "line_b"):
        (folder / f"{name}.mcap").write_bytes(recording.read_bytes())
    res = subprocess.run(MAGALIGN + ["process", str(folder), "--out", str(tmp_path / "o"),
                                     "--jobs", "2"], cwd=tmp_path,
                         env=_env(**{pg.ENV_MODE: "lines"}), capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr
    for name in ("line_a", "line_b"):
        assert _check_log(res.stderr, name, complete=True)[-1] == "writing report"
    ends = [ln for ln in res.stderr.splitlines() if END_LINE.fullmatch(ln)]
    assert [e.split(" (")[1].split(" of")[0] for e in ends] == ["1", "2"], ends


def test_diagnose_reports_candidate_search(recording):
    """diagnose's steps and its candidate search reach the sink (the line shows them)."""
    from pipeline.app.commands.diagnose import diagnose_file

    seen: list[dict] = []
    with pg.use_sink(pg.DirectSink("valid", seen.append)) as sink:
        diagnose_file(recording)
    names = [s["stages"][s["index"]] for s in seen if 0 <= s["index"] < len(s["stages"])]
    steps = [n for i, n in enumerate(names) if i == 0 or n != names[i - 1]]
    # the analysis calibrate, diagnose and process share (Plan.analysis_stages)
    assert steps == ["Ingest", "Resample", "SegmentMotion", "Estimate", "RequireObservable",
                     "Diagnose", "Judge"]
    assert any(s["detail"].startswith("search 1, candidate 1/") for s in seen)
    assert set(sink.state.timings) >= {"Ingest", "Diagnose"}


def test_diagnose_on_terminal(recording, tmp_path):
    rc, shown = _run_on_pty(MAGALIGN + ["diagnose", str(recording), "--out",
                                        str(tmp_path / "d")], tmp_path,
                            _env(**{pg.ENV_MODE: "always"}))
    assert rc == 0, shown
    # each stage is drawn as it starts, however short
    for label in ("reading (1/7)", "aligning (2/7)", "estimating (4/7)", "diagnosing (6/7)"):
        assert f"magalign diagnose  valid: {label}" in shown, shown


def test_calibrate_on_terminal(recording, tmp_path):
    rc, shown = _run_on_pty(MAGALIGN + ["-v", "calibrate", str(recording), "--out",
                                        str(tmp_path / "c")], tmp_path,
                            _env(**{pg.ENV_MODE: "always"}))
    assert rc == 0, shown
    assert "magalign calibrate  valid: estimating (4/7)" in shown, shown
    assert "valid: reading" in shown and " s, estimating " in shown  # -v timings


def test_the_share_done_never_goes_back():
    """A run whose stage list grows after it started draws no smaller share than before."""
    disp = pg.ProgressDisplay(1, "magalign calibrate", enabled=False)
    disp.started -= 10.0

    def pct() -> int:
        return int(re.search(r"(\d+)%", disp.line(width=200)).group(1))

    with pg.use_sink(pg.DirectSink("lab_03", disp.update)):
        pg.stage("Ingest", 0, 3, ["Ingest", "Estimate", "Judge"])
        pg.stage("Judge", 2, 3)
        pg.detail("", 0.9, 1.0)
        high = pct()
        # the same run now learns of a long stage still to come
        pg.stage("Diagnose", 2, 4, ["Ingest", "Estimate", "Diagnose", "Judge"])
        assert pct() >= high


def test_a_recording_read_in_ranges_keeps_one_total(recording, tmp_path):
    """A long recording's first pass segments its motion before the analysis: the count a
    step shows keeps one total from the first step to the last (it read 2/13, then 3/14)."""
    from pipeline.run.options import ProcessOptions
    from pipeline.run.runner import process_recording

    seen: list[dict] = []
    with pg.use_sink(pg.DirectSink("valid", seen.append)):
        process_recording(recording, tmp_path / "o", options=ProcessOptions(
            scale_samples=100, write_rerun=False, write_report=False))
    shown = [s for s in seen if 0 <= s["index"] < len(s["stages"])]
    assert {len(s["stages"]) for s in shown} == {len(shown[-1]["stages"])}
    names = [s["stages"][s["index"]] for s in shown]
    steps = [n for i, n in enumerate(names) if i == 0 or n != names[i - 1]]
    assert steps[:3] == ["Ingest", "SegmentMotion", "Resample"], steps
    assert steps == shown[-1]["stages"][:len(steps)], steps
