"""``hard_iron_step``: a magnetised object near the sensor for a while (windowed offset, (M5))."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    RestorePart,
    TermShape,
    register,
    standard_deviations,
)
from pipeline.model.forward import (
    in_windows,
    ramp_modes,
    ramp_profile,
    window_rows,
    windows_span,
)


@dataclass(frozen=True, eq=False)
class StepPart(RestorePart):
    """A fitted ``hard_iron_step`` in the restore: the plateau and its transitions, (M5).

    Attributes
    ----------
    windows_s : tuple of (float, float)
        Where the offset is held, s from the first sample (half-open).
    plateau_nT : ndarray (3,)
        The plateau, mag frame.
    ramps_s : tuple of (float, float)
        The transitions while the magnet moved (empty: a plain step).
    modes_nT : ndarray (M, 3)
        The transitions' sine modes (:func:`~pipeline.model.forward.ramp_profile`).
    mode_step_s : float
        One mode per this much of a transition, s.

    """

    windows_s: tuple[tuple[float, float], ...]
    plateau_nT: F64
    ramps_s: tuple[tuple[float, float], ...]
    modes_nT: F64
    mode_step_s: float

    def offset_nT(self, t_s: F64) -> F64:
        """Return ``o_step s(t) + phi(t) c``, mag frame, (N, 3)."""
        t = np.asarray(t_s, dtype=float)
        if not self.ramps_s:
            out = np.zeros((len(t), 3))
            out[in_windows(t, self.windows_s)] += self.plateau_nT
            return out
        s, phi = ramp_profile(t, self.windows_s[0], self.ramps_s, self.mode_step_s)
        return np.asarray(s[:, None] * self.plateau_nT + phi @ self.modes_nT)


def _rows(term: Any, t_s: F64) -> slice | np.ndarray:
    """Return the samples from the first window's start to the last one's end (``window_rows``)."""
    if not term.windows_s:
        return slice(None)
    return window_rows(t_s, *windows_span(term.windows_s))


@register
class HardIronStep(Effect):
    """The ``hard_iron_step`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.HARD_IRON_STEP
    physics: ClassVar[str] = (
        "a magnetised object moved close to the sensor for a while (a tool, a phone, a "
        "payload switched on): an offset that turns with the platform, present only then"
    )
    signature: ClassVar[str] = (
        "a constant mag-frame residual inside a time window"
    )
    frame: ClassVar[str] = "mag"
    event: ClassVar[bool] = True
    # an object brought near the sensor and left there for a while; a shorter excess (the
    # closest pass by a magnet in the room, where its dipole field is least exact; a knock)
    # is no object riding on the platform
    min_window_s: ClassVar[float] = 0.5
    # pieces of one offset that abut along seconds are one event (a magnet moved a little
    # while it rested, or an offset the scan saw in parts)
    merges: ClassVar[bool] = True

    def n_params(self, term: TermShape) -> int:
        """Return 3 for the plateau's offset plus 3 per mode of the transitions."""
        return 3 + 3 * term.step_profile(np.zeros(1))[1].shape[1]

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"windows_s": [[float(a), float(b)] for a, b in term.windows_s],
                "offset_nT": np.asarray(value[:3], dtype=float).tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"offset_nT": sd[:3].tolist()}

    def offset_nT(self, term: Any, value: F64, t_s: F64) -> F64:
        """Return ``o_step s(t) + phi(t) c`` of (M5), mag frame, (N, 3)."""
        out = np.zeros((np.size(t_s), 3))
        rows = _rows(term, t_s)  # the profile is zero outside the windows
        s, phi = term.step_profile(np.asarray(t_s)[rows])
        out[rows] = s[:, None] * value[:3] + phi @ np.asarray(value[3:]).reshape(-1, 3)
        return out

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write the plateau's and each transition mode's columns (see :meth:`Effect.columns`)."""
        rows = _rows(term, lin.t_s)
        s_step, phi = term.step_profile(lin.t_s[rows])
        block = out[rows] if isinstance(rows, slice) else np.zeros((len(s_step), *out.shape[1:]))
        # component r_ of the plateau's offset and of each transition mode's (3 each)
        for r_ in range(3):
            block[:, r_, r_] = s_step
            block[:, r_, 3 + r_ : 3 + 3 * phi.shape[1] : 3] = phi
        if not isinstance(rows, slice):
            out[rows] = block

    def column_windows(self, term: Any) -> tuple[tuple[int, int, float, float], ...]:
        """Return the plateau's columns over the window, each transition's over its ramp.

        See :meth:`Effect.column_windows`; ``ramp_profile`` is zero outside both.
        """
        if not term.windows_s:
            return ()
        out = [(0, 3, *windows_span(term.windows_s))]
        i = 3
        for r0, r1 in term.ramps_s or ():
            j = i + 3 * ramp_modes((r0, r1), term.knot_step_s)
            out.append((i, j, float(r0), float(r1)))
            i = j
        return tuple(out)

    def restore_part(self, params: dict[str, Any]) -> StepPart:
        """Return the step for the restore (see :meth:`Effect.restore_part`)."""
        return StepPart(tuple(tuple(w) for w in params.get("windows_s") or ()),
                        np.asarray(params["offset_nT"], dtype=float).reshape(3),
                        tuple(tuple(r) for r in params.get("ramps_s") or ()),
                        np.asarray(params.get("ramp_modes_nT") or np.zeros((0, 3)),
                                   dtype=float).reshape(-1, 3),
                        float(params.get("ramp_mode_step_s") or 1.0))

    def merged_start(self, a: tuple[Any, F64], b: tuple[Any, F64], merged: Any) -> F64:
        """Return the pieces' duration-weighted mean offset, no transition mode (see base)."""
        (ta, va), (tb, vb) = a, b
        da = max(ta.windows_s[0][1] - ta.windows_s[0][0], 1e-9)
        db = max(tb.windows_s[0][1] - tb.windows_s[0][0], 1e-9)
        start = np.zeros(self.n_params(merged))
        start[:3] = (da * np.asarray(va)[:3] + db * np.asarray(vb)[:3]) / (da + db)
        return start

    def prior_precision(self, term: Any) -> F64 | None:
        """Return none on the plateau, a GP on the transitions' modes; None without any.

        The transition's departure from a straight ramp is a squared-exponential GP of
        time scale ``ramp_scale_s`` and size ``prior_nT`` on each ramp of length ``L``; in
        the Dirichlet eigenbasis ``sin(k pi u)`` its coefficients are independent with
        variance ``(2 / L) S(k pi / L)``, ``S(w) = prior^2 sqrt(2 pi) l exp(-w^2 l^2 / 2)``
        (Solin & Sarkka 2020, Eq. 20, the basis without its ``sqrt(2 / L)`` norm). See
        :meth:`Effect.prior_precision`.
        """
        if not term.ramps_s:
            return None
        out = [np.zeros(3)]
        ell = term.ramp_scale_s
        for r0, r1 in term.ramps_s:
            L = float(r1) - float(r0)
            k = np.arange(1, ramp_modes((r0, r1), term.knot_step_s) + 1)
            w = k * np.pi / L
            var = (2.0 / L) * term.prior_nT**2 * np.sqrt(2 * np.pi) * ell * np.exp(
                -0.5 * (w * ell) ** 2)
            out.append(np.repeat(term.noise_nT**2 / np.maximum(var, 1e-300), 3))
        return np.concatenate(out)
