"""Ingest stage: read the magnetometer and attitude channels of an MCAP recording."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from pipeline.core.errors import InputError
from pipeline.io.mcap_read import read_recording
from stages.context import Context


@dataclass(frozen=True)
class Ingest:
    """Read ``ctx.source`` into a :class:`~pipeline.core.recording.Recording`.

    Channels are found by message type when there is exactly one candidate per role
    (CONVENTIONS); the topics given here override that. The data checks (NaN/Inf, zero and
    non-unit quaternions, stamps backwards/duplicated/jumping, wrong field unit, stuck or
    saturated sensor, too few samples) are those of :func:`pipeline.io.mcap_read.read_recording`.

    Parameters
    ----------
    mag_topic, attitude_topic, turntable_topic : str, optional

    """

    mag_topic: str | None = None
    attitude_topic: str | None = None
    turntable_topic: str | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"source"})
    provides: ClassVar[frozenset[str]] = frozenset({"recording"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with ``recording`` read from ``ctx.source``."""
        if ctx.source is None:
            raise InputError("no recording given to the Ingest stage")
        rec = read_recording(
            ctx.source,
            mag_topic=self.mag_topic,
            attitude_topic=self.attitude_topic,
            turntable_topic=self.turntable_topic,
        )
        return ctx.replace(recording=rec)
