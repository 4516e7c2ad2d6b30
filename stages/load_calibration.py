"""Stage LoadCalibration: the calibration read from a calibration.json file."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from pipeline.model.calibration import Calibration
from stages.context import Context


@dataclass(frozen=True)
class LoadCalibration:
    """Stage: take the calibration from a calibration.json file instead of estimating it."""

    path: str

    requires: ClassVar[frozenset[str]] = frozenset()
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Load ``path``."""
        return ctx.replace(calibration=Calibration.load(self.path))
