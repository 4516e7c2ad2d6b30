"""What to do with one recording: the options every command shares."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.vocabulary import EstimateTerm, EstimatorKind, ExcludeWindow


@dataclass(frozen=True)
class ProcessOptions:
    """What to do with one recording.

    Attributes
    ----------
    estimator : EstimatorKind, str or None
        Estimator; ``None`` means the default of :class:`stages.estimate.Estimate` (ML).
    terms : frozenset of EstimateTerm or str
        Terms estimated beside the rotation (offset, soft_iron, time_offset).
    reference_field_enu_nT : tuple of 3 float, optional
        Known background field (ENU, nT); estimated when ``None``.
    calibration_path : str, optional
        Use this calibration.json instead of estimating (survey lines restored with the
        calibration run's result).
    mag_topic, attitude_topic, turntable_topic : str, optional
        Channels to use when a recording has more than one candidate.
    diagnose : bool
        Run the Diagnose stage (when no calibration file is given).
    write_rerun : bool
        Write ``<stem>.rrd``.
    write_report : bool
        Write ``report.html`` and its PNG figures.
    max_gap_s : float or None
        Longest attitude gap (s) bridged by interpolation; None: the recording's own rule.
    scale_samples : int or None
        A recording with more magnetometer samples than this is analysed on windows of it
        (:mod:`pipeline.run.plan`), estimated from the sums of every sample and read chunk by
        chunk; restoring, metrics and the outputs always use every sample. ``None``: the
        analysis always sees the whole recording.
    robust : str
        Robust loss of the estimate: ``none``, ``huber`` or ``cauchy``.
    exclude : tuple of ExcludeWindow
        Stretches left out of the fit and the verdict (``--exclude``); restored like the rest.

    """

    estimator: EstimatorKind | str | None = None
    terms: frozenset[EstimateTerm | str] = frozenset()
    reference_field_enu_nT: tuple[float, float, float] | None = None
    calibration_path: str | None = None
    mag_topic: str | None = None
    attitude_topic: str | None = None
    turntable_topic: str | None = None
    diagnose: bool = True
    write_rerun: bool = True
    write_report: bool = True
    max_gap_s: float | None = None
    scale_samples: int | None = 600_000
    robust: str = "none"
    exclude: tuple[ExcludeWindow, ...] = ()
