"""Stage protocol and pipeline runner.

A stage is a frozen dataclass of parameters (scikit-learn style: the constructor holds
configuration only) with ``run(ctx) -> ctx``. It declares the context fields it ``requires``
and those it ``provides``; :class:`Pipeline` checks at build time, before any file is read,
that every requirement is provided by the initial context or an earlier stage, and names the
stage that does not fit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import ClassVar, Protocol, runtime_checkable

from pipeline.core.errors import MagalignError, PipelineBuildError
from pipeline.core.recording import Context


@runtime_checkable
class Stage(Protocol):
    """What every stage is.

    Attributes
    ----------
    requires : frozenset of str
        Context fields the stage reads.
    provides : frozenset of str
        Context fields the stage sets.

    """

    requires: ClassVar[frozenset[str]]
    provides: ClassVar[frozenset[str]]

    def run(self, ctx: Context) -> Context:
        """Return a new context with this stage's results; never mutate ``ctx``."""
        ...


def stage_name(stage: object) -> str:
    """Name of a stage for messages: its class name."""
    return type(stage).__name__


class Pipeline:
    """An ordered list of stages, checked when built.

    Parameters
    ----------
    stages : sequence of Stage
    initial : iterable of str
        Context fields available before the first stage (``"source"`` by default).

    Raises
    ------
    PipelineBuildError
        If a stage requires a field nothing earlier provides.

    """

    def __init__(self, stages: Sequence[Stage], initial: Iterable[str] = ("source",)):
        self.stages = tuple(stages)
        available = set(initial)
        for st in self.stages:
            if not isinstance(st, Stage):
                raise PipelineBuildError(stage_name(st), ("a run(ctx) method",), tuple(available))
            missing = tuple(sorted(set(st.requires) - available))
            if missing:
                raise PipelineBuildError(stage_name(st), missing, tuple(sorted(available)))
            available |= set(st.provides)
        self.provides = frozenset(available)

    def run(
        self, ctx: Context, progress: Callable[[str, int, int], None] | None = None
    ) -> Context:
        """Run every stage in order.

        Parameters
        ----------
        ctx : Context
            The input data; never modified.
        progress : callable, optional
            Called as ``progress(stage_name, index, total)`` before each stage.

        Returns
        -------
        Context
            The context after the last stage; ``ctx`` itself is unchanged.

        """
        for i, st in enumerate(self.stages):
            if progress is not None:
                progress(stage_name(st), i, len(self.stages))
            out = st.run(ctx)
            if out is ctx or not isinstance(out, Context):
                raise MagalignError(
                    f"stage {stage_name(st)} returned {'its input' if out is ctx else type(out)}"
                    " instead of a new Context",
                    hint="this is a bug in the stage",
                )
            ctx = out
        return ctx
