"""Outputs on a real lab recording (../shared/data/real): skipped when it is absent."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from mcap.reader import make_reader

from pipeline.run.runner import ProcessOptions, process_recording

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
LAB = REAL / "lab_03.mcap"

pytestmark = [
    pytest.mark.real,
    pytest.mark.skipif(not LAB.is_file(), reason=f"real lab recordings not present ({LAB})"),
]


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_lab_recording_outputs(tmp_path):
    from pipeline.core.vocabulary import EstimateTerm

    before = _sha(LAB)
    terms = frozenset({EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON, EstimateTerm.TIME_OFFSET})
    opts = ProcessOptions(terms=terms, diagnose=False,
                          write_rerun=False, write_report=False)
    row = process_recording(LAB, tmp_path, options=opts)
    assert _sha(LAB) == before  # the input is never touched
    m = json.loads(Path(row["paths"]["metrics.json"]).read_text())
    # motion capture loses the markers now and then: those samples are left out and counted
    assert 0 < m["n_without_attitude"] < 0.2 * m["n_samples"]
    # offset, soft iron and the time offset (about 15 ms in this recording) make the restored
    # field steadier than the attitude-only rotation
    for c in "xyz":
        assert row[f"ratio_pct_{c}"] < 95.0, row
    with open(row["paths"]["corrected_mcap"], "rb") as f:
        summary = make_reader(f, validate_crcs=True).get_summary()
    by_topic = {ch.topic: summary.statistics.channel_message_counts[cid]
                for cid, ch in summary.channels.items()}
    for suffix in ("calibrated", "enu", "residual"):
        assert by_topic[f"/imu/mag/{suffix}"] == m["n_samples"] == by_topic["/imu/mag"]


@pytest.mark.parametrize("name", [f"lab_0{i}.mcap" for i in range(1, 6)])
def test_scan_chunk_times_on_lab_recordings(name):
    """On files another tool wrote, the scan's chunk start and end times (which the long
    recording's plan and pass-through use instead of re-reading the mapping) are the chunk
    indexes mcap's own reader gives."""
    from pipeline.io.mcap_scan import scan_file

    p = REAL / name
    if not p.is_file():
        pytest.skip(f"{p} not present")
    with open(p, "rb") as fh:
        idx = {ci.chunk_start_offset: (ci.message_start_time, ci.message_end_time)
               for ci in make_reader(fh).get_summary().chunk_indexes}
    scan = scan_file(p)
    assert idx and {ch.offset: (ch.start_ns, ch.end_ns) for ch in scan.chunks} == idx
