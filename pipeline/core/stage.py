"""Stage protocol, the context base and the checked pipeline.

A stage is a frozen dataclass of parameters (scikit-learn style: the constructor holds
configuration only) with ``run(ctx) -> ctx``. It declares the context fields it ``requires``
and those it ``provides``; :class:`Pipeline` checks at build time, before any file is read,
that every requirement is provided by the initial context or an earlier stage, and names the
stage that does not fit. What the fields are is the stages' business (``stages.context``):
the core knows a context only as a frozen dataclass of optional fields.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Sequence
from typing import Any, ClassVar, Generic, Protocol, TypeVar, runtime_checkable

from pipeline.core.errors import MagalignError, PipelineBuildError

C = TypeVar("C", bound="BaseContext")
T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class BaseContext:
    """What stages pass along: a frozen dataclass whose fields are all optional.

    Subclasses name the fields; stages never mutate a context, they return
    ``ctx.replace(field=new_value)``.
    """

    def replace(self: C, **changes: Any) -> C:
        """Return a new context with ``changes`` applied."""
        return dataclasses.replace(self, **changes)

    def provided(self) -> frozenset[str]:
        """Names of the fields that hold a value."""
        return frozenset(
            f.name for f in dataclasses.fields(self) if getattr(self, f.name) not in (None, ())
        )


def needed(value: T | None, name: str) -> T:
    """Return ``value``, or raise naming the missing context field (a stage run out of order)."""
    if value is None:
        raise MagalignError(f"the context has no {name!r}: a stage that provides it must run first")
    return value


@runtime_checkable
class Stage(Protocol[C]):
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

    def run(self, ctx: C) -> C:
        """Return a new context with this stage's results; never mutate ``ctx``."""
        ...


def stage_name(stage: object) -> str:
    """Name of a stage for messages: its class name."""
    return type(stage).__name__


class Pipeline(Generic[C]):
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

    def __init__(self, stages: Sequence[Stage[C]], initial: Iterable[str] = ("source",)):
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

    def run(self, ctx: C, progress: Callable[[str, int, int], None] | None = None) -> C:
        """Run every stage in order.

        Parameters
        ----------
        ctx : BaseContext
            The input data; never modified.
        progress : callable, optional
            Called as ``progress(stage_name, index, total)`` before each stage.

        Returns
        -------
        BaseContext
            The context after the last stage; ``ctx`` itself is unchanged.

        """
        for i, st in enumerate(self.stages):
            if progress is not None:
                progress(stage_name(st), i, len(self.stages))
            out = st.run(ctx)
            if out is ctx or not isinstance(out, type(ctx)):
                raise MagalignError(
                    f"stage {stage_name(st)} returned {'its input' if out is ctx else type(out)}"
                    " instead of a new context",
                    hint="this is a bug in the stage",
                )
            ctx = out
        return ctx
