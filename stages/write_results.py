"""Stage WriteResults: calibration.json (and diagnosis.json when diagnosed)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from pipeline.core.atomic import write_text_atomic
from pipeline.core.recording import Context


@dataclass(frozen=True)
class WriteResults:
    """Stage: write calibration.json (and diagnosis.json when diagnosed) into ``out_dir``."""

    out_dir: str

    requires: ClassVar[frozenset[str]] = frozenset({"calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"outputs"})

    def run(self, ctx: Context) -> Context:
        """Write the JSON results atomically."""
        out = Path(self.out_dir)
        outputs = ctx.outputs
        p = write_text_atomic(out / "calibration.json", ctx.need_calibration().to_json())
        outputs += (("calibration.json", str(p)),)
        if ctx.diagnosis is not None:
            d = ctx.diagnosis.to_dict() if hasattr(ctx.diagnosis, "to_dict") else ctx.diagnosis
            p = write_text_atomic(out / "diagnosis.json", json.dumps(d, indent=2))
            outputs += (("diagnosis.json", str(p)),)
        return ctx.replace(outputs=outputs)
