"""Where a ``local_source`` candidate starts: a point dipole located by a grid search.

A source fixed in the surroundings adds ``B = P(r) m``
(:func:`pipeline.model.forward.dipole_matrix`) to the ENU field at the sensor, with
``r = Rz(psi) (p - c)`` from the source at ``c`` to the sensor at ``p``. The reading changes
by ``G(t) B`` with ``G = dy/dB_enu`` of the current model, so for a fixed position ``c`` and
bearing ``psi`` the moment ``m`` is a linear least-squares problem. The position enters as
``1/r^3``: a Gauss-Newton fit from far away does not find it, and at zero moment the
position has no gradient at all. The grid puts ``c`` on shells around the place where the
residual peaks (the sensor is closest there), solves for ``m`` at each, and starts the
joint fit from the best.

What tells a fixed source from the other local terms (the report says which): a
``hard_iron_step`` is constant in the mag frame (it turns with the platform); a
``disturbance`` is a function of time, the same wherever the sensor is; a source is fixed in
ENU and falls off as ``1/r^3`` with the distance to one place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model import parallel
from pipeline.model.dipole_kernels import dipole_grid_sums
from pipeline.model.forward import dipole_field
from stages.diagnose.fit import FitResult, fit
from stages.diagnose.model import (
    F64,
    FitData,
    ModelState,
    Term,
    evaluate,
    moved_last_to,
    rot_z,
    source_offset_enu,
    without_term,
)
from stages.diagnose.statistics import robust_sigma

#: distances (m) of the grid's shells from the place of the strongest residual
SHELLS_M = (0.02, 0.04, 0.07, 0.12, 0.2, 0.35, 0.6, 1.0, 1.7, 3.0)

#: bearings (deg) of the position frame tried when it is not known (a motion-capture room)
YAW_GRID_DEG = tuple(range(0, 360, 30))

#: a source is told from a smooth field only where the sensor passes it closer than this
#: fraction of its farthest distance in the window: the field then changes by at least
#: (1 / 0.5)^3 = 8 times along the path, which no linear gradient does
MAX_NEAR_FAR_RATIO = 0.5


def _directions() -> F64:
    """Return the 26 directions to the corners, edges and faces of a cube, unit vectors (26, 3)."""
    g = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                  if (i, j, k) != (0, 0, 0)], dtype=float)
    return g / np.linalg.norm(g, axis=1)[:, None]


def locate_source(cur: FitResult, data: FitData, window_s: tuple[float, float],
                  *, max_samples: int = 1500) -> tuple[F64, bool] | None:
    """Start values of a ``local_source`` seen in ``window_s``, or None without positions.

    Parameters
    ----------
    cur : FitResult
        The current model; its residual holds the source's field.
    data : FitData
        With positions (``p_m``).
    window_s : (float, float)
        Where the scan saw the excess, s from the first magnetometer sample; the grid uses
        the samples of this window widened by half its length on each side.
    max_samples : int
        The grid's sample budget (every k-th sample of the widened window).

    Returns
    -------
    (ndarray, bool) or None
        The term's values ``[c (3), m (3)]`` plus ``psi`` when the bearing is fitted, and
        whether it is (positions in a frame of unknown bearing).

    """
    if data.p_m is None:
        return None
    a, b = window_s
    pad = max(2.0, 0.5 * (b - a))
    sel = np.flatnonzero((data.t_s >= a - pad) & (data.t_s < b + pad))
    if sel.size < 20:
        return None
    sel = sel[:: max(1, sel.size // max_samples)]
    r = (cur.residual_nT if cur.raw_residual_nT is None else cur.raw_residual_nT)[sel]
    mask = np.zeros(len(data), dtype=bool)
    mask[sel] = True
    sub = data.subset(mask)
    ev = evaluate(cur.state, sub, jacobian=False)
    G = ev.G  # dy/dB_enu, (n, 3, 3)
    p = np.asarray(sub.p_m, dtype=float)
    norm = np.linalg.norm(r, axis=1)
    centre = p[int(np.argmax(norm))]
    # what the model may still lack around the window, taken out of every candidate's fit:
    # a constant field, a linear field in space (any 3x3 map of the positions, whatever the
    # frame's bearing) and a lag (the rate of the reading); a compact source is what is left
    n = len(p)
    dp = p - p.mean(axis=0)
    nuis = [G[:, :, k] for k in range(3)]
    nuis += [G[:, :, k] * dp[:, j:j + 1] for k in range(3) for j in range(3)]
    nuis.append(ev.ydot0_nT_s)
    Nm = np.stack([c.reshape(-1) for c in nuis], axis=1)  # (3n, 13)
    Qn, _ = np.linalg.qr(Nm / np.maximum(np.linalg.norm(Nm, axis=0), 1e-30))
    rf = r.reshape(-1)
    r_perp = (rf - Qn @ (Qn.T @ rf)).reshape(n, 3)
    fit_yaw = data.position_frame == "attitude_source_local"
    yaws = np.radians(YAW_GRID_DEG) if fit_yaw else np.array([0.0])
    dirs = _directions()
    best: tuple[float, F64, float] | None = None
    # coarse to fine: shells around the strongest residual, then twice around the best
    # point with shells a third and a ninth as large (the first grid's spacing is about
    # 45 deg of arc: up to 0.7 of the shell radius)
    shells = np.asarray(SHELLS_M)
    for level in range(3):
        cands = centre[None, :] + (shells[:, None, None] * dirs[None, :, :]).reshape(-1, 3)
        if level:
            cands = np.vstack([centre[None, :], cands])
        for psi in (yaws if level == 0 or best is None else np.array([best[2]])):
            gains, moments = _dipole_fits(G, p, cands, float(psi), Qn, r_perp)
            # the first of the largest gains, as a scan in candidate order keeps it
            k = int(np.argmax(gains))
            if np.isfinite(gains[k]) and (best is None or gains[k] > best[0]):
                best = (float(gains[k]), np.r_[cands[k], moments[k]], float(psi))
        if best is None:
            return None
        centre = best[1][:3]
        d_path = float(np.min(np.linalg.norm(p - centre, axis=1)))
        shells = np.geomspace(0.05, 0.7, 5) * max(d_path, 0.01)
    if best is None or best[0] <= 0:
        return None
    value = best[1] if not fit_yaw else np.r_[best[1], best[2]]
    return value, fit_yaw


def _dipole_fits(G: F64, p: F64, cands: F64, psi: float, Qn: F64, r_perp: F64
                 ) -> tuple[F64, F64]:
    """Moment and gain of a dipole at each candidate place, the nuisance columns taken out.

    For each candidate ``c`` (K, 3) in the position frame turned by ``psi``: the columns
    ``X = G P(r)`` (3n, 3) of the moment, ``r = Rz(psi) (p - c)``, ``u = r / |r|`` and ``P``
    of :func:`pipeline.model.forward.dipole_matrix`, so ``X = s (3 (G u) u' - G)`` with
    ``s = 100 / |r|^3``; less their projection on the orthonormal nuisance columns ``Qn``
    (3n, q); the moment ``m`` solving ``(A + 1e-12 tr(A) I) m = X' r_perp``; the gain
    ``m' X' r_perp``, the decrease of the residual sum of squares. ``A`` is the projected
    ``X'X``, formed in closed form per sample, never as the (3n, 3) columns: with
    ``M = G'G``, ``v = M u``, ``H_j = G' Q_j`` (``Q_j``: nuisance column ``j`` as (n, 3))

    - ``X'X = sum s^2 (9 (u'v) u u' - 3 (u v' + v u') + M)``,
    - ``Q_j' X = sum s (3 (H_j . u) u - H_j)``, ``A = X'X - sum_j (Q_j' X)' (Q_j' X)``,
    - ``X' r_perp = sum s (3 (w . u) u - w)``, ``w = G' r_perp`` (``r_perp`` is already
      orthogonal to ``Qn``, so the projection leaves it).

    The sums over the samples are one compiled pass per candidate
    (:func:`pipeline.model.dipole_kernels.dipole_grid_sums`). Returns the gains (K,),
    ``-inf`` where the system is singular, and the moments (K, 3), A m^2 in ENU.
    """
    n, K = len(p), len(cands)
    M = np.einsum("nik,nil->nkl", G, G)
    w = np.einsum("nik,ni->nk", G, r_perp)
    H = np.einsum("nik,nij->njk", G, Qn.reshape(n, 3, -1))  # (n, q, 3)
    XtX, W, g = dipole_grid_sums(p, cands, rot_z(psi), M, H, w)
    A = XtX - W.transpose(0, 2, 1) @ W
    Ar = A + (1e-12 * np.trace(A, axis1=1, axis2=2))[:, None, None] * np.eye(3)
    try:
        m = np.linalg.solve(Ar, g[:, :, None])[:, :, 0]
        ok = np.ones(K, dtype=bool)
    except np.linalg.LinAlgError:  # one singular system: solve them one by one
        m, ok = np.zeros((K, 3)), np.zeros(K, dtype=bool)
        for j in range(K):
            try:
                m[j] = np.linalg.solve(Ar[j], g[j])
                ok[j] = True
            except np.linalg.LinAlgError:
                continue
    gain = np.sum(g * m, axis=1)
    return np.where(ok & np.isfinite(gain), gain, -np.inf), m


def near_far_ratio(term: Term, value: F64, data: FitData) -> float:
    """Closest over farthest distance from the source to the sensor while it acts (0..1).

    Where the sensor's distance to the source hardly changes, the dipole's ``1/r^3`` is not
    sampled: the fit then describes a smooth field (a gradient or a field map does that)
    and says nothing about a compact object.
    """
    if data.p_m is None:
        return 1.0
    here = term.presence(data.t_s) > 0
    if not here.any():
        return 1.0
    d = np.linalg.norm(source_offset_enu(term, value, data.p_m[here]), axis=1)
    return float(d.min() / max(float(d.max()), 1e-12))


#: approaches to a source whose field stands above the noise: at least one. A single pass
#: can locate an object (three components along a tracked path sample its 1/r^3 and its
#: direction); whether a bump in time (a step, a disturbance) fits as well is decided by the
#: evidence of those look-alikes against it (:func:`stages.diagnose.nested.told_apart`), not
#: by a count
MIN_VISITS = 1


def source_visits(term: Term, value: F64, data: FitData, floor_nT: float = 0.0) -> int:
    """Separate approaches of the sensor to a source while it is there.

    The source's field magnitude at the sensor, in time (smoothed over 0.1 s), has one
    bump per approach. An approach counts when its bump rises above ``floor_nT`` (the
    noise) and a tenth of the strongest, and the field falls to half the bump's height
    between it and the next: the distance changed by at least ``2^(1/3)``, a real retreat.
    """
    if data.p_m is None:
        return 0
    here = term.presence(data.t_s) > 0
    if np.count_nonzero(here) < 3:
        return 0
    t = data.t_s[here]
    r = source_offset_enu(term, value, data.p_m[here])
    b = np.linalg.norm(dipole_field(r, value[3:6]), axis=1)
    dt = float(np.median(np.diff(t)))
    w = max(1, int(round(0.1 / max(dt, 1e-6))))
    bs = np.convolve(b, np.ones(w) / w, mode="same")
    height = max(floor_nT, 0.1 * float(bs.max()))
    from scipy.signal import find_peaks  # pipeline.core.warm.LATE_IMPORTS

    _, props = find_peaks(bs, height=height, prominence=0.0)
    return int(np.count_nonzero(props["prominences"] >= 0.5 * props["peak_heights"]))


def active_windows(term: Term, value: F64, data: FitData) -> tuple[tuple[float, float], ...]:
    """Return where a source stands out: its windows, or the span of its strong field.

    A source present throughout stands out from the first to the last sample at which its
    field exceeds a tenth of its peak (within ``10^(1/3)`` times the closest distance).
    """
    if term.windows_s or data.p_m is None:
        return term.windows_s
    d = np.linalg.norm(source_offset_enu(term, value, np.asarray(data.p_m)), axis=1)
    idx = np.flatnonzero((d.min() / d) ** 3 > 0.1)
    return ((float(data.t_s[idx[0]]), float(data.t_s[idx[-1]]) + 1e-6),)


def source_term(fit_yaw: bool, windows_s: tuple[tuple[float, float], ...] = ()) -> Term:
    """Return the ``local_source`` term, present in ``windows_s`` (empty: the whole recording)."""
    return Term(EffectKind.LOCAL_SOURCE, windows_s, fit_yaw=fit_yaw)


def with_values(state_term: Term, value: F64, cur: FitResult) -> ModelState:
    """Return ``cur.state`` with ``state_term`` appended at ``value`` (not at zero)."""
    st = cur.state.with_term(state_term)
    return replace(st, values=st.values[:-1] + (np.asarray(value, dtype=float),))


def plausible(res: FitResult, data: FitData, i: int = -1) -> bool:
    """Keep a fitted ``local_source`` only where the sensor sampled its ``1/r^3``.

    Other terms pass. A source the fit moved far from the path, so that the sensor's
    distance to it hardly changes where it acts, describes a smooth field, not an object;
    one whose field never stands above the noise is not seen at all.
    """
    term = res.state.terms[i]
    if term.kind is not EffectKind.LOCAL_SOURCE:
        return True
    value = res.state.values[i]
    if not np.all(np.isfinite(value)):
        return False
    near = near_far_ratio(dataclasses.replace(term, windows_s=active_windows(term, value, data)),
                          value, data)
    # a pass of a few tenths of a second holds tens of samples: one noise sigma per sample
    # is already a clear signal over it
    visits = source_visits(term, value, data, robust_sigma(res.residual_nT))
    return near <= MAX_NEAR_FAR_RATIO and visits >= MIN_VISITS


def pulled_away(start: ModelState | None, res: FitResult, data: FitData) -> bool:
    """Whether the joint fit moved a located source by more than half its closest distance.

    The grid locates a source with the smooth field, a lag and a constant taken out around
    it; a joint fit that then drags it away is fitting what the model still lacks (a
    gradient, a time offset) with the source. It is tried again once the model has those.
    """
    if start is None or res.state.terms[-1].kind is not EffectKind.LOCAL_SOURCE:
        return False
    c0, c1 = start.values[-1][:3], res.state.values[-1][:3]
    d0 = float(np.min(np.linalg.norm(np.asarray(data.p_m) - c0, axis=1)))
    return float(np.linalg.norm(c1 - c0)) > 0.5 * max(d0, 0.02)


def relocated(cur: FitResult, data: FitData) -> FitResult:
    """Locate each ``local_source`` again on what the rest of the model now leaves.

    A source located while much was unmodelled (a gradient, a time offset) may sit where
    it absorbed part of them, a local minimum the joint fit does not leave. With the
    source taken out, the grid of :func:`locate_source` runs on the residual of the other
    terms (around the source's own strongest pass), and the joint fit from there replaces
    the model when its weighted RSS is lower.
    """
    sources = [i for i, t in enumerate(cur.state.terms) if t.kind is EffectKind.LOCAL_SOURCE]
    # the next sources' relocations beside the one asked for: needed unless it moves the model
    moves: parallel.Ahead[int, FitResult | None] = parallel.Ahead(
        lambda i: _relocation(cur, data, i))
    for n, i in enumerate(sources):
        res = moves.get(sources, n)
        if res is not None and res.rss < cur.rss and plausible(res, data, i):
            cur = res
            moves.forget()
    return cur


def _relocation(cur: FitResult, data: FitData, i: int) -> FitResult | None:
    """Return the joint fit from source ``i`` located again without it (:func:`relocated`)."""
    term = cur.state.terms[i]
    wins = active_windows(term, cur.state.values[i], data)
    without = fit(without_term(cur.state, i), data, max_iter=10)
    loc = locate_source(without, data, (wins[0][0], wins[-1][1]))
    if loc is None:
        return None
    # keep the term's place in the model (findings are listed in the model's order)
    return fit(moved_last_to(with_values(term, loc[0], without), i), data)


def rivals(res: FitResult, data: FitData) -> tuple[str, list[tuple[Term, str]]]:
    """Return what tells the new source of ``res`` apart, and the terms that could replace it.

    A source seen on passes by one place could also be a magnet riding on the platform (an
    offset in the sensor's frame) or a field changing in time, each over the windows where
    the source's field stands out (above a tenth of its peak). Returns the words on what
    the source alone explains and each rival with what it would mean.
    """
    wins = active_windows(res.state.terms[-1], res.state.values[-1], data)
    a, b = wins[0][0], wins[-1][1]
    ks = min(2.0, max(0.75, (b - a) / 6))
    return (
        "Told apart by the data: the field stays where the object is and falls off with the "
        f"cube of the distance as the sensor moves (checked in {a:.1f}-{b:.1f} s)",
        [(Term(EffectKind.HARD_IRON_STEP, ((a, b),)),
          "a magnet riding on the platform (an offset that turns with it)"),
         (Term(EffectKind.DISTURBANCE, ((a, b),), knot_step_s=ks),
          "a field changing in time, the same everywhere nearby")])
