"""calibration.json (and diagnosis.json when diagnosed)."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.core.atomic import write_text_atomic
from pipeline.core.style import unsigned_zeros_in
from pipeline.model.calibration import Calibration
from stages.diagnose.result import Diagnosis


def write_results(out_dir: str | Path, calibration: Calibration,
                  diagnosis: Diagnosis | None = None) -> tuple[tuple[str, str], ...]:
    """Write the JSON results atomically into ``out_dir``; return ``(name, path)`` pairs."""
    out = Path(out_dir)
    p = write_text_atomic(out / "calibration.json", calibration.to_json())
    outputs: tuple[tuple[str, str], ...] = (("calibration.json", str(p)),)
    if diagnosis is not None:
        text = json.dumps(unsigned_zeros_in(diagnosis.to_dict()), indent=2)
        p = write_text_atomic(out / "diagnosis.json", text)
        outputs += (("diagnosis.json", str(p)),)
    return outputs
