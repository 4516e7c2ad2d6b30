"""One runner: a recording held in memory as one chunk and as many chunks gives every output
alike (calibration, diagnosis, metrics, corrected MCAP, rerun recording, report, map).

The analysis is made once; its second pass then restores the recording into the sinks
whole, and again cut into chunks (pipeline/run/runner.py). The restore of a chunk waits for
the attitude, positions and sensing-time context after it, so each row is restored as in
the whole recording: numbers agree to rounding (1e-9 relative, 1e-6 nT), counts exactly.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import semireal
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from test_outputs import rrd_columns
from test_scale import make
from test_stream_process import walk_json

from pipeline.run.options import ProcessOptions
from pipeline.run.runner import Steps, analyse_source, restore_into_sinks
from pipeline.run.source import MemorySource, open_source

LAB5 = semireal.REAL_DIR / "lab_05.mcap"


def _channels(path: Path) -> dict[str, np.ndarray]:
    """The corrected MCAP's new channels, decoded: (N, 4) rows of log time and values."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
        for _s, ch, msg, dec in reader.iter_decoded_messages():
            if ch.metadata.get("magalign") != "1" or ch.topic == "/tf_static":
                continue
            v = dec.magnetic_field if hasattr(dec, "magnetic_field") else None
            row = [v.x, v.y, v.z] if v is not None else [dec.data, 0.0, 0.0]
            out.setdefault(ch.topic, []).append([float(msg.log_time), *row])
    return {k: np.array(v) for k, v in out.items()}


def _report_text(path: Path) -> str:
    """The report without its images and the minute it was written."""
    text = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "", path.read_text())
    return re.sub(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", "", text)


def _numbers_alike(a: str, b: str) -> None:
    num = re.compile(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
    assert num.split(a) == num.split(b)  # the words are the same
    for x, y in zip(num.findall(a), num.findall(b), strict=True):
        if x != y:  # a printed number may round the other way in its last digit
            digits = len(x.replace("-", "").replace(".", "").lstrip("0"))
            assert abs(float(x) - float(y)) <= 1.01 * 10.0 ** (1 - digits) * abs(float(x)), (x, y)


def _process_both(path: Path, tmp_path: Path, chunk_samples: int, options: ProcessOptions):
    source = open_source(path, options)
    assert isinstance(source, MemorySource)
    analysis = analyse_source(source, options, Steps())
    out = {}
    for name, chunks in (("one", None), ("many", chunk_samples)):
        src = MemorySource(analysis.source.recording, chunks)
        assert src.one_chunk == (chunks is None)
        rec_dir = tmp_path / name
        rec_dir.mkdir()
        done = restore_into_sinks(type(analysis)(analysis.ctx, analysis.plan, src,
                                                 analysis.segments, None), rec_dir, Steps())
        out[name] = dict(done.outputs)
    return out


def _compare(out: dict[str, dict[str, str]]) -> None:
    one, many = out["one"], out["many"]
    assert set(one) == set(many)
    for name in ("calibration.json", "diagnosis.json", "metrics.json"):
        if name in one:
            walk_json(json.loads(Path(one[name]).read_text()),
                      json.loads(Path(many[name]).read_text()), rel=1e-9)
    a, b = _channels(Path(one["corrected_mcap"])), _channels(Path(many["corrected_mcap"]))
    assert set(a) == set(b) and len(a) == 4
    for topic in a:
        np.testing.assert_array_equal(a[topic][:, 0], b[topic][:, 0])  # stamps
        np.testing.assert_array_equal(np.isnan(a[topic]), np.isnan(b[topic]))
        scale = 1.0 if topic.endswith("magnitude") else 1e9  # nT; tesla in MagneticField
        np.testing.assert_allclose(b[topic][:, 1:] * scale, a[topic][:, 1:] * scale,
                                   atol=1e-6, equal_nan=True)
    if "rrd" in one:
        ca, cb = rrd_columns(Path(one["rrd"])), rrd_columns(Path(many["rrd"]))
        assert set(ca) == set(cb)
        for ent in ("/field/calibrated/east", "/residual/z", "/attitude/roll_deg"):
            va = np.concatenate([np.ravel(x) for x in ca[ent]["Scalars:scalars"]])
            vb = np.concatenate([np.ravel(x) for x in cb[ent]["Scalars:scalars"]])
            np.testing.assert_allclose(vb, va, atol=1e-6)
    if "report.html" in one:
        _numbers_alike(_report_text(Path(one["report.html"])),
                       _report_text(Path(many["report.html"])))
        map_one = Path(one["report.html"]).parent / "map.json"
        if map_one.exists():
            walk_json(json.loads(map_one.read_text()),
                      json.loads((Path(many["report.html"]).parent / "map.json").read_text()),
                      rel=1e-9)


def test_one_chunk_and_many_chunks_give_every_output_alike(tmp_path):
    """A 2 ms attitude lag (the diagnosis' time offset), segments, every output."""
    path, _ = make(tmp_path / "rec.mcap", n=6_000)
    out = _process_both(path, tmp_path, 700, ProcessOptions())
    cal = json.loads(Path(out["one"]["calibration.json"]).read_text())
    assert cal["time_offset_s"] is not None or "time_offset" in cal["effects"]
    _compare(out)


@pytest.mark.slow
@pytest.mark.skipif(not LAB5.exists(), reason="real recordings absent: ../shared/data/real "
                    "not found")
@pytest.mark.filterwarnings("ignore::pipeline.core.errors.RecoveredDataWarning")
def test_a_lab_recording_as_one_chunk_and_many(tmp_path):
    """lab_05: positions (a field gradient), eddy currents, a sample-and-hold sensor whose
    rows are restored at their sensing times: each chunk waits for what follows it."""
    out = _process_both(LAB5, tmp_path, 4_000, ProcessOptions(write_rerun=False))
    effects = json.loads(Path(out["one"]["calibration.json"]).read_text())["effects"]
    assert {"sample_hold", "eddy_current", "field_gradient"} <= set(effects)
    _compare(out)
