"""``field_map``: a smooth field over the area (Laplace eigenfunctions, GP prior, ``F(t)``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.geometry import right_times, rot_z
from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import vec
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    RestorePart,
    Samples,
    TermShape,
    register,
    standard_deviations,
)
from pipeline.model.field_map import FieldMapBasis, map_field_enu, map_points, weighted_field


@dataclass(frozen=True, eq=False)
class MapPart(RestorePart):
    """A fitted ``field_map`` in the restore: ``F = Q sum_j w_j g_j(x)``, ``x = p + Q.T C l``.

    Its basis (the box and the modes per axis), its weights and the position frame's bearing
    ``Q = Rz(yaw)`` (:mod:`pipeline.model.field_map`).
    """

    needs_positions: ClassVar[bool] = True
    basis: FieldMapBasis
    weights: F64
    yaw_rad: float

    def field_enu(self, t_s: F64, p_m: F64 | None, lever_enu: F64 | None) -> F64 | None:
        """Return the map's field (see :meth:`RestorePart.field_enu`)."""
        if p_m is None:
            return None
        x = map_points(p_m, self.yaw_rad, lever_enu)
        return np.asarray(map_field_enu(self.basis, self.weights, self.yaw_rad, x))


@register
class FieldMap(Effect):
    """The ``field_map`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.FIELD_MAP
    physics: ClassVar[str] = (
        "a field that varies smoothly but not linearly over the area the sensor covers "
        "(steel in the building's structure, a distant vehicle or pipe, a geological "
        "anomaly): the gradient is only its first order"
    )
    signature: ClassVar[str] = (
        "an ENU residual, left after the linear gradient, that follows the sensor's position "
        "and repeats wherever the sensor comes back, smooth over the whole area"
    )
    frame: ClassVar[str] = "enu"
    # the field beyond the gradient's first order, in the gradient's bearing
    acts_through: ClassVar[frozenset[EffectKind]] = frozenset({EffectKind.FIELD_GRADIENT})
    absorbing: ClassVar[bool] = True
    # a map along a path leaves combinations of its basis unobserved (the GP prior holds
    # them): admitted on its best-determined directions
    identifiable_in_part: ClassVar[bool] = True

    def n_params(self, term: TermShape) -> int:
        """Return one weight per basis function (the product of the modes per axis)."""
        return int(np.prod(term.n_axis))

    def add_field(self, term: Any, value: F64, at: Samples, B_enu: F64) -> Any:
        """Add ``-Q grad phi(x) = Q sum_j w_j g_j(x)``, ``x = p + Q.T C l`` (CONVENTIONS).

        See :meth:`Effect.add_field` and :mod:`pipeline.model.field_map`.
        """
        if at.p_m is None:
            return None
        B_enu += weighted_field(at.map_field(term), value) @ rot_z(term.yaw_rad).T
        return None

    def gradient_enu(self, term: Any, value: F64, at: Samples) -> F64 | None:
        """Return the map's ENU gradient ``Q (dB_x/dx) Q.T`` (see :meth:`Effect.gradient_enu`)."""
        if at.p_m is None:
            return None
        Qm = rot_z(term.yaw_rad)
        x = map_points(at.p_m, term.yaw_rad, at.lever_enu)
        return np.asarray(Qm @ term.basis().field_gradient(x, value) @ Qm.T)

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dw_j = G Q g_j(x)``: linear in the weights (see :meth:`Effect.columns`)."""
        if lin.p_m is None:
            return
        # (G Q) g_j: the turn joins G as one product, not a loop over the samples
        np.matmul(right_times(lin.G, rot_z(term.yaw_rad)), lin.map_field(term), out=out)

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return fit.map_params(term, value)

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"weights": sd.tolist(), "peak_to_peak_nT": fit.map_range_sigma(term, cov)}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        pp = [float(x) for x in params["peak_to_peak_nT"]]
        dom = np.asarray(params["domain_m"], dtype=float)
        frame = ("the attitude source's own frame (the motion-capture room)"
                 if params.get("position_frame") == "attitude_source_local" else "local ENU")
        text += (
            f". Beyond the linear gradient the field changes by up to {max(pp):.0f} nT "
            "(range of E, N, U over the places visited: " + ", ".join(f"{x:.0f}" for x in pp)
            + f" nT), modelled as minus the gradient of a potential in {params['n_basis']} "
            "Laplace eigenfunctions of a box of " + " x ".join(
                f"{b - a:.2f}" for a, b in dom) + f" m in {frame} (Solin et al. 2018), "
            f"GP length scale {params['length_scale_m']:.2f} m. It belongs to the "
            "surroundings, not to the sensor: the restored field keeps it. Calibrate where the "
            "field is uniform (or turn the sensor in place), or keep the positions and this "
            "term in the model"
        )
        return text

    def restorable(self, params: dict[str, Any]) -> bool:
        """Return whether the basis is there beside the weights (:meth:`Effect.restorable`).

        The weights need their basis: the box, the modes per axis (written by diagnose
        beside the CONVENTIONS params) and the position frame's bearing.
        """
        return all(k in params for k in ("domain_m", "n_per_axis", "weights"))

    def restore_part(self, params: dict[str, Any]) -> MapPart:
        """Return the map for the restore (see :meth:`Effect.restore_part`)."""
        return MapPart(FieldMapBasis.of(params["domain_m"], params["n_per_axis"]),
                       np.asarray(params["weights"], dtype=float).reshape(-1),
                       float(np.radians(params.get("frame_yaw_deg") or 0.0)))

    def prior_precision(self, term: Any) -> F64:
        """Return ``noise^2 / var(w_j)`` for each weight (see :meth:`Effect.prior_precision`).

        The GP prior of :mod:`pipeline.model.field_map` (squared exponential, length scale
        ``length_scale_m``, field components of standard deviation ``prior_nT``) weighed
        against the residual noise ``noise_nT``.
        """
        var = term.basis().prior_variance(term.length_scale_m, term.prior_nT)
        return np.asarray((term.noise_nT**2) / np.maximum(var, 1e-300))

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the map's size, basis and scale (see :meth:`Effect.sentence`)."""
        p2p = np.asarray(params["peak_to_peak_nT"], float)
        return (f"Beyond the linear gradient the field varies smoothly over the area the "
                f"sensor covered, by {vec(p2p)} nT peak to peak (east, north, up), mapped with "
                f"{int(params['n_basis'])} basis functions (length scale "
                f"{float(params['length_scale_m']):.2f} m). The restored field keeps it.")
