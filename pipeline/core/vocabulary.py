"""The words the options are spelled in: estimators, estimated terms, robust losses, windows.

Every layer names these (the command line and the campaign files read them, the runner plans
with them, the stages act on them), so they live in the framework: the program and the runner
take them from here, never from the stages that implement them. Each name is the one of
CONVENTIONS (``--estimator``, ``--estimate``, ``--robust``, ``--exclude``).
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass
from datetime import datetime, timezone


class EstimatorKind(str, enum.Enum):
    """Which estimator fits the calibration (``--estimator``), in the order shown to users.

    The implementations are the stages' (``stages.estimators.registry.ESTIMATORS`` maps each
    kind to its class and refuses to import unless it names exactly these kinds, in this
    order): adding an estimator is one member here and one line there.
    """

    ML = "ml"
    LI2020 = "li2020"
    ELLIPSOID = "ellipsoid"
    DPI = "dpi"


class EstimateTerm(str, enum.Enum):
    """Optional model terms estimated beside the rotation (CONVENTIONS names)."""

    OFFSET = "offset"
    SOFT_IRON = "soft_iron"
    TIME_OFFSET = "time_offset"


class RobustLoss(enum.Enum):
    """Loss on the whitened per-sample residual norm (IRLS weights)."""

    NONE = "none"
    HUBER = "huber"
    CAUCHY = "cauchy"


_SECONDS = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*:\s*([0-9]+(?:\.[0-9]*)?)\s*$")
_ISO = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d+)?(?:Z|[+-]\d\d:\d\d)"
_UTC = re.compile(rf"^\s*({_ISO})\s*:\s*({_ISO})\s*$")


@dataclass(frozen=True)
class ExcludeWindow:
    """One stretch left out of the analysis, half-open ``[start, end)`` (``--exclude``).

    Attributes
    ----------
    start, end : float
        Seconds from the first magnetometer sample, or (``utc``) seconds since the Unix
        epoch.
    utc : bool

    """

    start: float
    end: float
    utc: bool = False

    @classmethod
    def parse(cls, text: str) -> ExcludeWindow:
        """Read ``START:END`` (seconds, or two ISO 8601 UTC times); ValueError says why."""
        m = _SECONDS.match(text)
        if m:
            a, b, utc = float(m.group(1)), float(m.group(2)), False
        else:
            m = _UTC.match(text)
            if not m:
                raise ValueError(f"{text!r} is not START:END in seconds from the first "
                                 "magnetometer sample (12.5:30) or in UTC "
                                 "(2026-11-20T10:03:00Z:2026-11-20T10:04:30Z)")
            a, b = (datetime.fromisoformat(g.replace("Z", "+00:00")).timestamp()
                    for g in m.groups())
            utc = True
        if not b > a:
            raise ValueError(f"{text!r}: the end must come after the start")
        return cls(a, b, utc)

    def ns(self, t0_ns: int) -> tuple[int, int]:
        """Return the window in ns since the Unix epoch, given the first magnetometer stamp."""
        if self.utc:
            return int(round(self.start * 1e9)), int(round(self.end * 1e9))
        return t0_ns + int(round(self.start * 1e9)), t0_ns + int(round(self.end * 1e9))

    def seconds(self, t0_ns: int) -> list[float]:
        """Return ``[start, end]`` in seconds from the first magnetometer sample."""
        a, b = self.ns(t0_ns)
        return [(a - t0_ns) * 1e-9, (b - t0_ns) * 1e-9]

    def text(self) -> str:
        """Return the window as the command line spells it."""
        if not self.utc:
            return f"{self.start:g}:{self.end:g}"
        a, b = (datetime.fromtimestamp(x, tz=timezone.utc).isoformat().replace("+00:00", "Z")
                for x in (self.start, self.end))
        return f"{a}:{b}"


class EffectKind(str, enum.Enum):
    """The effects ``diagnose`` can name, spelled as in CONVENTIONS ("Effects").

    The key of the effect registry (``pipeline.model.effects.EFFECTS``: one module per
    member); the diagnosis' findings and ``calibration.json`` carry the values.
    """

    HARD_IRON = "hard_iron"
    SOFT_IRON = "soft_iron"
    TIME_OFFSET = "time_offset"
    EDDY_CURRENT = "eddy_current"
    FIELD_DRIFT = "field_drift"
    DISTURBANCE = "disturbance"
    HARD_IRON_STEP = "hard_iron_step"
    AXIS_TILT = "axis_tilt"
    FIELD_GRADIENT = "field_gradient"
    SAMPLE_HOLD = "sample_hold"  # a timing effect handled on the data, not a model term
    HEADING_DRIFT = "heading_drift"
    LOCAL_SOURCE = "local_source"
    LEVER_ARM = "lever_arm"
    FIELD_MAP = "field_map"
