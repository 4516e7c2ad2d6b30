"""Stage RequireObservable: an estimate that no rotation axis determines is refused."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from pipeline.core.errors import NotObservableError
from stages.context import Context


@dataclass(frozen=True)
class RequireObservable:
    """Stage: refuse an estimate that no rotation axis of the recording's motion determines.

    A platform that did not rotate gives an arbitrary rotation; every output written from it
    (and every survey line restored with it) would look like a result. The ``calibrate``
    command refuses the same case. Not used when a calibration file is given: a survey line
    that never turns is restored with the calibration run's result.
    """

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset()

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` as it is, or raise when nothing about the rotation is observable.

        Raises
        ------
        NotObservableError
            All three rotation axes unobservable.

        """
        if len(ctx.need_calibration().unobservable_axes_body) >= 3:
            raise NotObservableError(
                "the platform did not rotate: nothing about the misalignment is observable",
                path=ctx.need_recording().path,
                hint="record rotations about at least two different axes, or restore this "
                "recording with a calibration run's result (--calibration FILE)")
        return ctx.replace()  # a new Context, as every stage returns
