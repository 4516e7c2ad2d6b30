"""The command line itself: version, help texts, shared options, inputs that are not MCAP."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from pipeline.app.cli import build_parser, main

#: Markup that must not reach a user's terminal: rst roles, double backticks, and references
#: to the project's internal conventions file.
MARKUP = re.compile(r"``|:(func|mod|class|meth|attr|data|ref):|CONVENTIONS")


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError("no subcommands")


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings}


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"magalign {version('magalign')}"


def test_every_help_text_is_plain_words():
    parser = build_parser()
    subs = _subparsers(parser)
    assert {"info", "calibrate", "diagnose", "process", "export", "view"} <= set(subs)
    texts = {"magalign": parser.format_help()}
    texts |= {name: p.format_help() for name, p in subs.items()}
    for name, text in texts.items():
        bad = MARKUP.search(text)
        assert bad is None, f"magalign {name} --help shows {bad.group(0)!r}:\n{text}"
        assert len(text.splitlines()) >= 3, name


def test_help_through_the_program_exits_zero_with_plain_text():
    r = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "process", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "--reference-field" in r.stdout
    assert MARKUP.search(r.stdout) is None


def test_one_spelling_per_option_across_subcommands():
    subs = _subparsers(build_parser())
    seen: dict[str, tuple[str, str | tuple, str]] = {}
    for name, p in subs.items():
        for opt, a in _options(p).items():
            if opt in ("-h", "--help"):
                continue
            key = (a.metavar, a.help)
            if opt in seen and opt in ("--mag", "--attitude", "--reference-field", "--igrf"):
                assert key == seen[opt][1:], f"{opt} differs between {seen[opt][0]} and {name}"
            seen.setdefault(opt, (name, *key))
    for name in ("calibrate", "diagnose", "process"):
        opts = _options(subs[name])
        for opt, metavar in (("--mag", "TOPIC"), ("--attitude", "TOPIC"),
                             ("--reference-field", "E,N,U"),
                             ("--igrf", "LAT,LON,ALT_M,DATE")):
            assert opt in opts, f"magalign {name} lacks {opt}"
            assert opts[opt].metavar == metavar


def test_usage_error_names_the_subcommand(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("(see magalign calibrate -h)")
    with pytest.raises(SystemExit):
        main(["nonsense-command"])
    assert capsys.readouterr().err.strip().endswith("(see magalign -h)")


def test_field_options_parse_and_refuse():
    from pipeline.app.commands._options import field_from_args
    from pipeline.core.errors import UsageError

    ns = argparse.Namespace
    assert field_from_args(ns(reference_field=None, igrf=None)) is None
    b = field_from_args(ns(reference_field="1000, 20000,-40000", igrf=None))
    assert b.tolist() == [1000.0, 20000.0, -40000.0]
    # IGRF at Berlin: total field ~49,800 nT, pointing down (negative Up) and north.
    g = field_from_args(ns(reference_field=None, igrf="52.5,13.4,50,2024-06-01"))
    assert 45_000 < float((g**2).sum() ** 0.5) < 55_000 and g[2] < 0 < g[1]
    for bad in ("1,2", "1,2,nan", "a,b,c"):
        with pytest.raises(UsageError, match="--reference-field"):
            field_from_args(ns(reference_field=bad, igrf=None))
    with pytest.raises(UsageError, match="--igrf"):
        field_from_args(ns(reference_field=None, igrf="52.5,13.4,2024-06-01"))


# ------------------------------------------------------------------ inputs that are not MCAP

def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.app.cli", *args], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


@pytest.mark.parametrize("command", ["info", "calibrate", "diagnose", "process", "view"])
@pytest.mark.parametrize("name", ["table.csv", "renamed.mcap"])
def test_not_mcap_is_one_line_exit_2_and_no_output(tmp_path, command, name):
    src = tmp_path / name
    src.write_text("t,x,y,z\n0,1,2,3\n1,1,2,3\n")
    out = tmp_path / "out"
    args = [command, str(src)]
    if command in ("calibrate", "diagnose", "process"):
        args += ["--out", str(out)]
    if command == "process":
        args.append("--no-progress")
    if command == "view":
        args.append("--web")
    r = _run(*args, cwd=tmp_path)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr
    assert len(err) == 1, r.stderr
    if command == "view" and name.endswith(".csv"):
        assert re.search(r"not a \.rrd or \.mcap file", err[0])
    else:
        assert "not an MCAP file" in err[0]
    assert str(src) in err[0] and "Traceback" not in r.stderr
    assert not out.exists()


# ------------------------------------------------------------------ what the help says

def _command_list(help_text: str) -> list[str]:
    """Names in the top-level help's command list (indented under COMMAND)."""
    block = help_text.split("  COMMAND\n", 1)[1].split("\n\n", 1)[0]
    return [ln.split()[0] for ln in block.splitlines() if ln.strip()]


def test_development_commands_are_apart_from_the_others():
    parser = build_parser()
    text = parser.format_help()
    listed = _command_list(text)
    assert {"info", "calibrate", "diagnose", "process", "export", "view"} <= set(listed)
    assert "reproduce" not in listed and "score" not in listed
    dev = text.split("development commands", 1)[1]
    assert "reproduce" in dev and "score" in dev
    subs = _subparsers(parser)  # still there to run
    assert {"reproduce", "score"} <= set(subs)
    assert "Development" in subs["reproduce"].format_help()


def test_every_command_describes_itself():
    for name, p in _subparsers(build_parser()).items():
        assert p.description and len(p.description.split()) >= 8, name
    text = _subparsers(build_parser())["view"].format_help()
    assert "rerun viewer" in text and "--web" in text and ".rrd" in text


def test_one_word_for_the_offset():
    """--estimate spells it offset in every command; hard_iron is the effect name, explained."""
    subs = _subparsers(build_parser())
    helps = {name: _options(subs[name])["--estimate"].help for name in ("calibrate", "process")}
    assert len(set(helps.values())) == 1, helps
    text = next(iter(helps.values()))
    assert "offset (" in text and "hard_iron" in text


@pytest.mark.parametrize("command", ["calibrate", "process"])
def test_estimate_takes_no_other_spelling(tmp_path, capsys, command):
    args = [command, str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "out"),
            "--estimate", "hard_iron"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--estimate" in err[0] and "offset" in err[0], err


def test_summary_title_names_magalign_once():
    import tomllib

    from pipeline.app.commands.process import summary_title

    demo = Path(__file__).resolve().parents[1] / "pipeline" / "demo" / "campaign.toml"
    name = tomllib.loads(demo.read_text())["campaign"]["name"]
    title = summary_title(name)
    assert title.lower().count("magalign") == 1, title
    assert summary_title("coast survey 2024") == "magalign: coast survey 2024"


@pytest.mark.parametrize("columns", [None, "60", "80", "132"])
def test_final_summary_in_words_within_the_terminal(tmp_path, monkeypatch, columns):
    """Each recording's verdict, why, findings and warnings: wrapped to the terminal's width
    (80 columns when unknown), never cutting a number."""
    import json as _json

    from pipeline.app.commands.process import recording_summary

    if columns is None:
        monkeypatch.delenv("COLUMNS", raising=False)
    else:
        monkeypatch.setenv("COLUMNS", columns)
    WIDTH = int(columns or 80)

    folder = tmp_path / "line_07"
    folder.mkdir()
    reason = ("The model leaves 1162 nT, 1.8 times the sensor's noise (632 nT). What to do: "
              "exclude the stretches the diagnosis names with --exclude, or record again.")
    (folder / "calibration.json").write_text(_json.dumps({
        "verdict": {"status": "QUESTIONABLE", "reason": reason},
        "warnings": ["sample-and-hold: 29 % of the magnetometer messages repeat the previous "
                     "one (native rate 202.2 Hz, messages 285.7 Hz); the repeats were left out"]
    }), encoding="utf-8")
    (folder / "diagnosis.json").write_text(_json.dumps({"findings": [
        {"effect": "time_offset", "params": {"time_offset_s": 0.0174},
         "sigma": {"time_offset_s": 0.0005}, "evidence": {}, "where": {}},
        {"effect": "disturbance", "params": {"windows_s": [[54.9, 67.0]], "peak_nT": 59.3},
         "sigma": {}, "evidence": {}, "where": {"windows_s": [[54.9, 67.0]]}}]}),
        encoding="utf-8")
    line = ("misalignment 0.79 +- 4.35 deg about body [-0.32, +0.19, -0.93]; time offset "
            "+17.4 ms; residual 1162 nT vs noise 632 nT; QUESTIONABLE")
    lines = recording_summary({"name": "line_07", "row": {"verdict_line": line}}, {}, tmp_path)
    assert all(len(x) <= WIDTH for x in lines), lines
    text = "\n".join(lines)
    assert lines[0].startswith("line_07: misalignment") and "  why: The model leaves" in text
    assert "The magnetometer's time stamps are late by 17.40" in " ".join(text.split())
    assert "  found: A passing disturbance of 59 nT" in text
    assert "  warning: sample-and-hold: 29 %" in text


def test_calibrate_refusal_says_its_other_doubts_instead_of_pointing_at_a_report():
    """calibrate writes no report: its refusal names every doubt in its one line."""
    import numpy as np

    from pipeline.app.commands.calibrate import refusal_reason
    from pipeline.core.verdict import judge
    from pipeline.model.calibration import Calibration

    refusals = ["the result depends on where the fit starts: two starts end 3.1 deg apart"]
    doubts = ["the two halves of the recording disagree by 1.20 deg, more than their sigmas "
              "allow",
              "the motion cannot determine hard iron: its columns trade against B_enu"]
    verdict = judge(400.0, 20.0, refusals=refusals, doubts=doubts)
    assert "in the report" in verdict.reason  # what the verdict says for outputs with one
    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=[0.1] * 3,
                      B_enu_nT=[0.0, 20000.0, -40000.0], estimator="ml",
                      residual_rms_nT=400.0, n_samples=1000, verdict=verdict,
                      checks={"refusals": refusals, "doubts": doubts})
    line = refusal_reason(cal)
    assert "report" not in line, line
    assert "\n" not in line
    assert "halves" in line and "hard-magnetic" in line, line


def test_the_terminal_width_is_80_when_unknown_and_numbers_are_never_cut(monkeypatch):
    from pipeline.core.style import GLUE, terminal_width, wrap

    monkeypatch.delenv("COLUMNS", raising=False)
    assert terminal_width() == 80  # pytest's captured output is no terminal
    monkeypatch.setenv("COLUMNS", "120")
    assert terminal_width() == 120
    text = "a residual of 58431.123456789 nT and " + "12345678901234567890" * 5
    lines = wrap(text, "  why: ", "       ", 40)
    assert "58431.123456789" in " ".join(lines) and "12345678901234567890" * 5 in lines[-1]
    assert wrap(f"x = 1.0{GLUE}\u00b1{GLUE}0.1", "", "", 40) == ["x = 1.0 \u00b1 0.1"]
    assert all(len(line) <= 40 for line in wrap("word " * 40, "", "  ", 40))


def test_calibrate_summary_fits_any_width_and_keeps_each_number_whole():
    import numpy as np

    from pipeline.app.commands.calibrate import summary
    from pipeline.core.verdict import judge
    from pipeline.model.calibration import Calibration

    cal = Calibration(R_body_mag=np.eye(3), sigma_rotvec_deg=np.array([0.476, 0.383, 0.102]),
                      B_enu_nT=np.array([94.5, 15537.4, -41382.8]), estimator="diagnose",
                      residual_rms_nT=716.7, n_samples=9126, offset_nT=np.array([-308.5, 256.2,
                                                                                  191.8]),
                      sigma_offset_nT=np.array([30.5, 17.8, 17.7]), time_offset_s=0.01525,
                      sigma_time_offset_s=0.00023, n_eff=982.0)
    cal = cal.replace(verdict=judge(716.7, 663.0, heldout_rms_nT=718.4))
    for width in range(50, 101, 7):
        text = summary(cal, width)
        assert all(len(line) <= width for line in text.splitlines()), (width, text)
        flat = " ".join(text.split())
        assert "9 126 samples" in flat and "of 9 126" in flat
        assert "\u2212308.5 \u00b1 30.5" in flat and "+15.25 \u00b1 0.23 ms" in flat
        assert "estimator diagnose" not in flat and "\u00a0" not in text
