"""The context the analysis stages pass along: the recording and what they make of it."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.recording import AlignedSeries, Recording, Segment
from pipeline.core.stage import BaseContext, needed
from pipeline.model.calibration import Calibration
from stages.diagnose.result import Diagnosis
from stages.estimators.streaming import SampleSums


@dataclass(frozen=True)
class Context(BaseContext):
    """What the stages read and provide. Every field is optional; a stage declares its own.

    Attributes
    ----------
    source : str or None
        The recording's path.
    recording : Recording or None
        The recording, or the part of it the analysis sees (a long recording's windows).
    aligned : AlignedSeries or None
        Its magnetometer samples with the attitude on their stamps.
    segments : tuple of Segment or None
        The motion's segments.
    calibration : Calibration or None
        The model fitted (or loaded), then diagnosed and judged.
    diagnosis : Diagnosis or None
    sums : SampleSums or None
        The sums of every sample of a long recording (the runner's first pass).

    """

    source: str | None = None
    recording: Recording | None = None
    aligned: AlignedSeries | None = None
    segments: tuple[Segment, ...] | None = None
    calibration: Calibration | None = None
    diagnosis: Diagnosis | None = None
    sums: SampleSums | None = None

    def need_recording(self) -> Recording:
        """Return ``recording``, which the calling stage requires (raises when absent)."""
        return needed(self.recording, "recording")

    def need_aligned(self) -> AlignedSeries:
        """Return ``aligned``, which the calling stage requires (raises when absent)."""
        return needed(self.aligned, "aligned")

    def need_calibration(self) -> Calibration:
        """Return ``calibration``, which the calling stage requires (raises when absent)."""
        return needed(self.calibration, "calibration")

    def need_sums(self) -> SampleSums:
        """Return ``sums``, which the calling stage requires (raises when absent)."""
        return needed(self.sums, "sums")
