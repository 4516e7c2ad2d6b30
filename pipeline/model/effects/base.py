"""What every effect module provides, and the registry that collects them.

An effect is one physical cause ``diagnose`` can add to the forward model (CONVENTIONS,
"Effects"). Each lives in its own module of this package as one subclass of :class:`Effect`,
registered under its :class:`~pipeline.core.vocabulary.EffectKind` by :func:`register`; the
code that used to switch on the kind (the parameter count, the catalogue's words) asks the
registry instead, so that adding an effect is one module plus one line in
:mod:`pipeline.model.effects`.
"""

from __future__ import annotations

from typing import ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

from pipeline.core.vocabulary import EffectKind

F64 = NDArray[np.float64]


class TermShape(Protocol):
    """The shape of a model term that its parameter count depends on.

    ``stages.diagnose.model.Term`` satisfies it; the protocol keeps this layer from naming
    the diagnosis (``pipeline`` never imports ``stages``).
    """

    # read-only: the terms are frozen dataclasses
    @property
    def fit_yaw(self) -> bool:
        """Whether a ``local_source`` fits the bearing of the position frame."""
        ...

    @property
    def n_axis(self) -> tuple[int, ...]:
        """A ``field_map``'s modes per axis."""
        ...

    def knots(self) -> list[F64]:
        """Return the knot times of each window of a ``disturbance``."""
        ...

    def step_profile(self, t_s: F64) -> tuple[F64, F64]:
        """Return a ``hard_iron_step``'s plateau profile (N,) and transition basis (N, M)."""
        ...


class Effect:
    """One effect: its name, its words and the size of its parameter vector.

    Attributes
    ----------
    kind : EffectKind
        The CONVENTIONS name, the registry's key.
    physics : str
        What on a survey platform causes it.
    signature : str
        How it shows in the residual.
    frame : str
        Frame in which its residual lives (``mag`` or ``enu``).
    identifiable_in_part : bool
        Some of its directions are confounded with the model's other parameters by nature,
        and the rest still carry the physics: the term is admitted on its best-determined
        direction and fitted there (the confounded directions stay at zero), instead of
        being refused on its weakest one.
    n_fixed : int or None
        The number of parameters when it does not depend on the term's windows or options;
        None when :meth:`n_params` counts them.

    """

    kind: ClassVar[EffectKind]
    physics: ClassVar[str]
    signature: ClassVar[str]
    frame: ClassVar[str]
    identifiable_in_part: ClassVar[bool] = False
    n_fixed: ClassVar[int | None] = None

    def n_params(self, term: TermShape) -> int:
        """Return the number of parameters of ``term``, a term of this effect.

        Parameters
        ----------
        term : TermShape
            The term (its windows, transitions, options).

        Returns
        -------
        int

        Raises
        ------
        ValueError
            The effect is not a term of the forward model (``sample_hold`` is handled on
            the data).

        """
        if self.n_fixed is None:
            raise ValueError(f"{self.kind.value} is not a term of the forward model")
        return self.n_fixed


#: kind -> its effect, filled by :func:`register` as the modules are imported
EFFECTS: dict[EffectKind, Effect] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Register one instance of ``cls`` under its kind (a class decorator).

    Raises
    ------
    ValueError
        Two modules claim the same kind.

    """
    if cls.kind in EFFECTS:
        raise ValueError(f"effect {cls.kind.value} registered twice")
    EFFECTS[cls.kind] = cls()
    return cls
