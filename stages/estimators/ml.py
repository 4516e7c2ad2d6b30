"""Joint maximum likelihood of the misalignment, the field and the optional terms (default).

More in docs/modules.md, ``stages.estimators.ml``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np

from pipeline.core.errors import EstimationError
from pipeline.core.geometry import matrix_to_quat, quat_to_matrix, quat_to_rotvec, skew, so3_exp
from pipeline.core.recording import AttitudeSeries
from pipeline.core.vocabulary import EstimateTerm, RobustLoss
from pipeline.model.attitude import AttitudeInterpolator
from pipeline.model.calibration import Calibration
from pipeline.model.forward import (
    SOFT_IRON_BASIS,
    SOFT_IRON_BASIS_TRACE_FREE,
    Reading,
    field_jacobian,
    reading,
    soft_iron_jacobian,
    time_offset_jacobian,
)
from pipeline.model.solve import Linearised, minimise
from stages.estimators.base import (
    F64,
    RELATIVE_INFO_THRESHOLD,
    EstimationProblem,
    analyse,
    canonical_axis,
    cube_rotations,
    init_rotation,
    irls_weights,
    rotation_words,
    sigma_with_null,
    solve_many_truncated,
)
from stages.estimators.checks import (
    SplitCheck,
    apply_split,
    confounded,
    info_halves,
    per_sample_rot_info,
    sandwich_cov,
    undetermined_directions,
)
from stages.estimators.ellipsoid import fit_ellipsoid


@dataclass
class State:
    """Parameters of the model; ``R`` is updated on the manifold, the rest additively."""

    R: F64
    B: F64
    o: F64
    D: F64
    tau: float


class Model:
    """Prediction, Jacobian and weights of the ML problem for a given state.

    Parameters
    ----------
    problem : EstimationProblem
    estimate_B : bool
        False when a reference field fixes ``B``.

    """

    def __init__(self, problem: EstimationProblem, estimate_B: bool = True):
        self.p = problem
        self.estimate_B = estimate_B
        self.with_o = EstimateTerm.OFFSET in problem.terms
        self.with_D = EstimateTerm.SOFT_IRON in problem.terms
        self.with_tau = EstimateTerm.TIME_OFFSET in problem.terms
        self.basis = SOFT_IRON_BASIS_TRACE_FREE if (self.with_D and estimate_B) else SOFT_IRON_BASIS
        att = problem.attitude
        if att is None:
            # The aligned samples are the attitude at t - tau0: a series on those stamps.
            att = AttitudeSeries(
                problem.t_ns - np.int64(round(problem.time_offset0_s * 1e9)), problem.q_enu_body
            )
        self.attitude = att
        self.blocks: dict[str, slice] = {}
        n = 0
        for name, size, on in (
            ("rot", 3, True),
            ("B", 3, estimate_B),
            ("offset", 3, self.with_o),
            ("D", len(self.basis), self.with_D),
            ("tau", 1, self.with_tau),
        ):
            if on:
                self.blocks[name] = slice(n, n + size)
                n += size
        self.n_params = n
        self._C_cache: tuple[float, F64] | None = None
        self._interp: AttitudeInterpolator | None = None  # THE interpolator, built on first use
        self._C0 = problem.C_enu_body  # computed once: the property converts every call

    # ------------------------------------------------------------------ attitude
    def interpolator(self) -> AttitudeInterpolator:
        """Return THE interpolator of the attitude (every gap bridged, clamped at the ends)."""
        if self._interp is None:
            self._interp = AttitudeInterpolator.of(self.attitude, max_gap_s=np.inf, clamp=True)
        return self._interp

    def C(self, tau: float) -> F64:
        """Attitude matrices at ``t - tau``, (N, 3, 3)."""
        if not self.with_tau:
            return self._C0
        if self._C_cache is not None and self._C_cache[0] == tau:
            return self._C_cache[1]
        C = quat_to_matrix(self.interpolator().at(self.p.t_ns, tau).q_enu_body)
        self._C_cache = (tau, C)
        return C

    def Ct(self, tau: float) -> F64:
        """``C_enu_body(t - tau).T`` (N, 3, 3), the attitude piece of (M2)."""
        return np.swapaxes(self.C(tau), -1, -2)

    def omega_body(self, tau: float) -> F64:
        """Angular velocity of THE attitude interpolation at ``t - tau``, body, rad/s."""
        return self.interpolator().at(self.p.t_ns, tau).omega_body_rad_s

    def reading(self, s: State) -> Reading:
        """(M2)-(M4) and the offset at ``s``: :func:`pipeline.model.forward.reading`."""
        return reading(self.Ct(s.tau), s.B, s.R, s.D, (s.o,))

    def b_body(self, s: State, tau: float | None = None) -> F64:
        """Predicted body field ``C.T @ B``, (N, 3), (M2)."""
        return reading(self.Ct(s.tau if tau is None else tau), s.B, s.R).b_body_nT

    def predict(self, s: State) -> F64:
        """Predicted magnetometer readings, (N, 3), (M2)-(M5) without the diagnosed terms."""
        return self.reading(s).y_nT

    def jacobian(self, s: State) -> F64:
        """dy/dparams, (N, 3, P), in the order of ``blocks`` ((J2)-(J5) of the forward model).

        The rotation block is the left perturbation ``R <- exp([phi]x) R`` (docs/modules.md):
        ``D R.T [b]x``.
        """
        Ct = self.Ct(s.tau)
        rd = reading(Ct, s.B, s.R, s.D)
        b = rd.b_body_nT
        DRt = s.D @ s.R.T
        N = len(b)
        J = np.empty((N, 3, self.n_params))
        # D R_bar.T [b]x, row i = (DRt[i] x b)^T since a.(b x v) = v.(a x b); DRt[i] x b is
        # [DRt[i]]x b, so all N rows come from one (N, 3) x (3, 9) product.
        K = np.stack([skew(DRt[i]) for i in range(3)])  # (3 rows i, 3 params j, 3 k)
        J[:, :, self.blocks["rot"]] = (b @ K.reshape(9, 3).T).reshape(N, 3, 3)
        if "B" in self.blocks:
            J[:, :, self.blocks["B"]] = field_jacobian(Ct, s.R, s.D)  # (J2)
        if "offset" in self.blocks:
            J[:, :, self.blocks["offset"]] = np.eye(3)  # (J3), broadcast over N
        if "D" in self.blocks:
            J[:, :, self.blocks["D"]] = soft_iron_jacobian(self.basis, rd.m_nT, rd.mdot_nT_s)
        if "tau" in self.blocks:
            # (J5): the attitude re-interpolated at t - tau, db/dtau = omega x b
            J[:, :, self.blocks["tau"].start] = time_offset_jacobian(
                self.omega_body(s.tau), b, None, s.R, s.D)
        return J

    def weights(self, s: State) -> F64 | None:
        """Return the inverse per-sample covariances ``W_i``, (N, 3, 3).

        ``None`` (identity) without a noise model: the normal equations and the cost then
        skip every 3x3 product.
        """
        nm = self.p.noise
        if nm is None:
            return None
        C = self.C(s.tau)
        b = reading(np.swapaxes(C, -1, -2), s.B, s.R).b_body_nT  # (M2)
        A = s.D @ s.R.T @ skew(b)  # maps body attitude error to y
        S_att = nm.attitude_cov_body(C)
        Sig = np.matmul(np.matmul(A, S_att), np.swapaxes(A, 1, 2))
        Sig = Sig + nm.sigma_mag_nT**2 * np.eye(3)
        return inv_sym3(Sig)

    def step(self, s: State, delta: F64) -> State:
        """Apply a parameter increment."""
        R = so3_exp(delta[self.blocks["rot"]]) @ s.R
        B = s.B + delta[self.blocks["B"]] if "B" in self.blocks else s.B
        o = s.o + delta[self.blocks["offset"]] if "offset" in self.blocks else s.o
        D = s.D
        if "D" in self.blocks:
            D = D + np.einsum("k,kij->ij", delta[self.blocks["D"]], self.basis)
        tau = s.tau + float(delta[self.blocks["tau"]][0]) if "tau" in self.blocks else s.tau
        return State(R, B, o, D, tau)


def inv_sym3(S: F64) -> F64:
    """Inverses of symmetric positive-definite 3x3 matrices (N, 3, 3) by the adjugate.

    Closed form, vectorised: ~10x faster than the batched LAPACK call on N small matrices.
    """
    a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 0, 2]
    d, e, f = S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    Cc = b * e - c * d
    Dd = a * f - c * c
    Ee = b * c - a * e
    F = a * d - b * b
    det = a * A + b * B + c * Cc
    out = np.stack(
        [np.stack([A, B, Cc], -1), np.stack([B, Dd, Ee], -1), np.stack([Cc, Ee, F], -1)], -2
    )
    return out / det[:, None, None]


def _normal(J: F64, W: F64 | None, r: F64, w: F64) -> tuple[F64, F64]:
    # Batched matmul and one BLAS product over the stacked rows: einsum does not reach BLAS.
    P = J.shape[2]
    if W is None:  # isotropic: J.T diag(w) J without the identity products
        Jf = J.reshape(-1, P)
        WJf = Jf if np.all(w == 1.0) else (J * w[:, None, None]).reshape(-1, P)
        return Jf.T @ WJf, WJf.T @ r.reshape(-1)
    WJ = (W @ J) * w[:, None, None]
    WJf = WJ.reshape(-1, P)
    H = J.reshape(-1, P).T @ WJf
    g = WJf.T @ r.reshape(-1)
    return H, g


def _cost(r: F64, W: F64 | None, w: F64) -> tuple[float, F64]:
    if W is None:
        q = np.einsum("ij,ij->i", r, r)
    else:
        q = np.einsum("ij,ij->i", r, (W @ r[:, :, None])[:, :, 0])
    return float(np.sum(w * q)), np.sqrt(np.maximum(q, 0.0))


@dataclass(frozen=True)
class GNResult:
    """Where the solver core stopped: the state and its last linearisation.

    ``H`` is the normal matrix ``J.T W J`` of the last iteration (``relinearise_last=False``
    of :func:`pipeline.model.solve.minimise`), taken at the state before a
    final step smaller than :data:`STEP_TOL_SIGMA` standard deviations (or at ``s`` itself):
    the covariance computed from it differs from one at ``s`` by far less than its own
    uncertainty, and saves a full-data Jacobian.
    """

    s: State
    w: F64  # robust weights (N,)
    W: F64 | None  # per-sample inverse covariances (N, 3, 3); None = identity
    r: F64  # residuals at s (N, 3), nT
    H: F64  # (P, P)


#: Gauss-Newton stops once a step moves every parameter by less than this many of its standard
#: deviations: with quadratic convergence the error left is far smaller still.
STEP_TOL_SIGMA = 1e-4
#: First damping of THE solver core for the ML fit (relative to the diagonal of ``J.T W J``):
#: the first step is close to the Gauss-Newton step (fewer function evaluations than 1e-8).
ML_DAMPING = 1e-4


def gauss_newton(model: Model, s: State, max_iter: int = 60) -> GNResult:
    """Gauss-Newton (with step halving) to convergence, inside an IRLS loop when robust."""
    w = np.ones(model.p.n)
    s, W, r, H = _gn_fixed_weights(model, s, w, max_iter)
    if model.p.robust is not RobustLoss.NONE:
        scale = 1.0 if model.p.noise is not None else None
        for _ in range(20):
            _, rn = _cost(r, W, np.ones(model.p.n))
            w_new = irls_weights(rn, model.p.robust, scale)
            if np.max(np.abs(w_new - w)) < 1e-6:
                break
            w = w_new
            s, W, r, H = _gn_fixed_weights(model, s, w, max_iter)
    return GNResult(s, w, W, r, H)


def _gn_fixed_weights(model: Model, s: State, w: F64, max_iter: int
                      ) -> tuple[State, F64 | None, F64, F64]:
    """Minimise the weighted cost at fixed robust weights ``w`` with THE solver core.

    :func:`pipeline.model.solve.minimise`: damped Gauss-Newton, each step solved with the
    truncated pseudo-inverse (directions the motion does not observe stay where they are),
    stopped once a step moves every parameter by less than :data:`STEP_TOL_SIGMA` of its
    standard deviation.
    """
    y = model.p.mag_nT
    dof = max(3 * model.p.n - model.n_params, 1)
    eye = np.eye(model.n_params)

    last: list[tuple[State, Linearised]] = []  # the accepted step's cost, not computed twice

    def linearise(st: State, with_normal: bool) -> Linearised:
        if last and last[0][0] is st:
            lin = last[0][1]
        else:
            W = model.weights(st)
            r = y - model.predict(st)
            lin = Linearised(_cost(r, W, w)[0], aux=(W, r))
            last[:] = [(st, lin)]
        if not with_normal:
            return lin
        W, r = lin.aux
        H, g = _normal(model.jacobian(st), W, r, w)
        return Linearised(lin.cost, H, g, lin.aux)

    def solve_step(H: F64, g: F64, lam: float, scale: F64) -> F64:
        Hd = H + lam * np.diag(scale)
        return cast(F64, solve_many_truncated(Hd, g[:, None], RELATIVE_INFO_THRESHOLD)[:, 0])

    def converged(before: Linearised, after: Linearised, dx: F64) -> bool:
        # the step in units of each parameter's standard deviation (the noise scale as in
        # MLEstimator.finish)
        s2 = after.cost / dof if model.p.noise is None else 1.0
        H_pinv = solve_many_truncated(cast(F64, before.H), eye, RELATIVE_INFO_THRESHOLD)
        var = np.diag(H_pinv) * s2
        small = np.abs(dx) <= STEP_TOL_SIGMA * np.sqrt(np.maximum(var, 0.0))
        return bool(small.all() or np.max(np.abs(dx[model.blocks["rot"]])) < 1e-13)

    m = minimise(s, linearise, model.step, solve_step=solve_step, converged=converged,
                 max_iter=max_iter, rtol=1e-14, lam0=ML_DAMPING, accept_rtol=1e-12,
                 accept_atol=1e-300, max_tries=20, relinearise_last=False)
    W, r = m.at.aux
    return m.state, W, r, cast(F64, m.at.H)


@dataclass(frozen=True)
class MLEstimator:
    """Joint maximum likelihood (docs/modules.md).

    Attributes
    ----------
    max_iter : int
        Gauss-Newton iterations.
    checks : bool
        Run the global checks (determinability, multi-start, split halves; see ``fit``).

    """

    max_iter: int = 60
    name: str = "ml"
    checks: bool = True

    def initial_state(self, p: EstimationProblem) -> State:
        """Closed-form start: ellipsoid (when D is wanted and the data cover 3D), then Wahba."""
        y = p.mag_nT
        C = p.C_enu_body
        D = np.eye(3)
        o = np.zeros(3)
        if EstimateTerm.SOFT_IRON in p.terms or EstimateTerm.OFFSET in p.terms:
            try:
                o_e, D_e = fit_ellipsoid(y)
                if EstimateTerm.OFFSET in p.terms:
                    o = o_e
                if EstimateTerm.SOFT_IRON in p.terms:
                    D = D_e * 3.0 / np.trace(D_e)
            except EstimationError:
                pass  # single-axis data: start from o = 0, D = I; GN finds what is observable
        yc = cast(F64, np.linalg.solve(D, (y - o).T).T)
        B_ref = p.reference_field_enu_nT
        cands = None
        if p.R_nominal_body_mag is not None:

            cands = np.concatenate([cube_rotations(), p.R_nominal_body_mag[None]])
        R, B = init_rotation(yc, C, B_ref, cands)
        if B_ref is not None and EstimateTerm.SOFT_IRON in p.terms:
            # D was normalised to trace 3; a known |B| restores the scale (D ~ D_tilde R_hat)
            scale = np.median(np.linalg.norm(yc, axis=1)) / np.linalg.norm(B_ref)
            D = D * scale
        return State(R, np.asarray(B, float), o, D, float(p.time_offset0_s))

    def fit(self, p: EstimationProblem) -> Calibration:
        """Estimate; see :class:`Calibration` for the fields.

        With ``checks`` (the default) the fit is checked globally (module ``checks``): terms
        the motion confounds are not estimated, the fit is repeated from several starts,
        the covariance is the block sandwich, and the rotation of two halves of equal
        information is compared; what the checks find goes to ``Calibration.checks``
        (``refusals`` and ``doubts`` for the verdict) and ``not_estimated``.
        """
        if EstimateTerm.TIME_OFFSET in p.terms:
            p = _inside_attitude_span(p)
        not_estimated: list[dict] = []
        refusals: list[str] = []
        doubts: list[str] = []
        if self.checks:
            p, not_estimated, base_note, nested = self._determinable(p)
            if base_note:
                doubts.append(base_note)
        model = Model(p, estimate_B=p.reference_field_enu_nT is None)
        gn, pc = self._solve(p, model, self.initial_state)
        cal = self.finish(p, model, gn)
        if not self.checks:
            return cal
        info: dict = {}
        if not_estimated:
            doubts.append("not estimated (the motion cannot determine them): "
                          + ", ".join(d["term"] for d in not_estimated))
        gn, cal, start_note, start_info = self._multistart(p, pc, model, gn, cal, nested)
        info["starts"] = start_info
        info["nested"] = [{k: v for k, v in nf.items() if k != "state"} for nf in nested]
        if start_note is not None:
            refusals.append(start_note)
        split = self._split(p, model, gn, cal)
        if split is not None:
            info["split"] = split.to_dict()
            info["sigma_rotvec_sandwich_deg"] = [float(x) for x in cal.sigma_rotvec_deg]
            cal = apply_split(cal.replace(checks={**cal.checks, "doubts": doubts}), split)
            doubts = list(cal.checks.get("doubts", ()))
        info["refusals"] = refusals
        info["doubts"] = doubts
        return cal.replace(checks={**cal.checks, **info}, not_estimated=tuple(not_estimated))

    def _solve(self, p: EstimationProblem, model: Model, start
               ) -> tuple[GNResult, EstimationProblem]:
        """Run coarse-to-fine Gauss-Newton from ``start(problem)``.

        Returns the result and the coarse problem.
        """
        # Coarse to fine: on a long recording, start and converge on an evenly decimated
        # subset; the full-data Gauss-Newton then needs one or two iterations to the same
        # optimum (the start only has to lie in its basin).
        pc = _decimated(p, COARSE_SAMPLES) if p.n > 2 * COARSE_SAMPLES else p
        s0 = start(pc)
        if model.with_tau:
            # Fit without tau first: the rotation must be close before tau's Jacobian is useful.
            m0 = Model(
                EstimationProblem(**{**pc.__dict__,
                                     "terms": pc.terms - {EstimateTerm.TIME_OFFSET}}),
                estimate_B=model.estimate_B,
            )
            s0 = gauss_newton(m0, s0, self.max_iter).s
        if pc is not p:
            s0 = gauss_newton(Model(pc, estimate_B=model.estimate_B), s0, self.max_iter).s
        return gauss_newton(model, s0, self.max_iter), pc

    # ------------------------------------------------------------------ global checks
    def _determinable(self, p: EstimationProblem
                      ) -> tuple[EstimationProblem, list[dict], str | None, list[dict]]:
        """Leave out the requested terms that the motion confounds (``checks.confounded``).

        The information of the full requested model is taken at the fit of the rotation and
        field alone (offset 0, D = I, the initial tau): the motion decides what can be
        determined, not a start that may already have wandered. Terms are removed one at a
        time, each time the one whose removal leaves the best-determined model, until no
        block is confounded. Also returns the nested fits (rotation and field; with the
        offset when asked for) on the check samples: their solutions are starts of the
        multi-start and their rotations are reported beside the result.
        """
        extra = [t for t in (EstimateTerm.SOFT_IRON, EstimateTerm.OFFSET,
                             EstimateTerm.TIME_OFFSET) if t in p.terms]
        pb = EstimationProblem(**{**p.__dict__, "terms": frozenset()})
        pcb = _decimated(pb, CHECK_SAMPLES) if pb.n > 2 * CHECK_SAMPLES else pb
        mb = Model(pcb, estimate_B=pb.reference_field_enu_nT is None)
        gb = gauss_newton(mb, self.initial_state(pcb), self.max_iter)
        sb = gb.s
        nested = [{"terms": [], "rotvec_deg": _log(sb.R) * 180.0 / np.pi,
                   "residual_rms_nT": float(np.sqrt(np.mean(gb.r**2))), "state": sb}]
        if EstimateTerm.OFFSET in p.terms:
            # the next nested model, rotation, field and offset: a start of its own
            po = EstimationProblem(**{**pcb.__dict__, "terms": frozenset({EstimateTerm.OFFSET})})
            go = gauss_newton(Model(po, estimate_B=mb.estimate_B), sb, self.max_iter)
            nested.append({"terms": ["offset"], "rotvec_deg": _log(go.s.R) * 180.0 / np.pi,
                           "residual_rms_nT": float(np.sqrt(np.mean(go.r**2))),
                           "state": go.s})
        pcf = EstimationProblem(**{**pcb.__dict__, "terms": p.terms})
        sb = State(sb.R, sb.B, np.zeros(3), np.eye(3), float(p.time_offset0_s))
        if EstimateTerm.SOFT_IRON in p.terms and pb.reference_field_enu_nT is not None:
            # a known |B| carries the scale of D: start it at the measured ratio
            yn = np.median(np.linalg.norm(pcb.mag_nT, axis=1))
            sb = State(sb.R, sb.B, sb.o, np.eye(3) * yn / np.linalg.norm(sb.B), sb.tau)

        def ratios(terms: frozenset) -> tuple[dict, dict]:
            m = Model(EstimationProblem(**{**pcf.__dict__, "terms": terms}),
                      estimate_B=pb.reference_field_enu_nT is None)
            J = m.jacobian(sb)
            H, _ = _normal(J, m.weights(sb), np.zeros((pcf.n, 3)), np.ones(pcf.n))
            return analyse(H, m.blocks).block_ratio, m.blocks

        words = {
            EstimateTerm.OFFSET: "the offset trades against the field and the rotation: the field "
            "direction in the sensor frame did not cover enough of the sphere (rotate the "
            "sensor through very different attitudes, about at least two axes)",
            EstimateTerm.SOFT_IRON: "the soft-iron matrix trades against the rotation: the motion "
            "did not turn the sensor through enough directions (tumble it about all three axes)",
            EstimateTerm.TIME_OFFSET: "the time offset trades against the rotation: the rotation "
            "rate hardly changed (vary the rotation rate, turn back and forth)",
        }
        terms = frozenset(extra)
        dropped: list[dict] = []
        while True:
            rat, blocks = ratios(terms)
            bad = confounded(rat, list(blocks))
            if not bad or not terms:
                break
            # remove the term whose absence leaves the best-determined model
            best, best_score = None, -1.0
            for t in extra:
                if t not in terms:
                    continue
                r2, b2 = ratios(terms - {t})
                score = min(
                    (float(np.min(v[v >= RELATIVE_INFO_THRESHOLD])) if np.any(
                        v >= RELATIVE_INFO_THRESHOLD) else 1.0) for v in r2.values()
                )
                if score > best_score:
                    best, best_score = t, score
            assert best is not None
            worst = min(bad.values())
            dropped.append({
                "term": best.value,
                "reason": f"{words[best]} (only {worst:.1e} of the information of its weakest "
                "combination is left once the other parameters are free)",
            })
            terms = terms - {best}
        note = None
        rat, blocks = ratios(terms)
        bad = confounded(rat, ["rot"])
        if bad:
            note = (
                "the motion barely determines the rotation about one axis (only "
                f"{bad['rot']:.1e} of its information survives the field being unknown): "
                "rotate about a second, very different axis"
            )
        return EstimationProblem(**{**p.__dict__, "terms": terms}), dropped, note, nested

    def _multistart(self, p: EstimationProblem, pc: EstimationProblem, model: Model, gn: GNResult,
                    cal: Calibration, nested: list[dict] | None = None,
                    ) -> tuple[GNResult, Calibration, str | None, list]:
        """Repeat the fit from other starts; refuse when distinct minima fit about as well.

        Starts (on the coarse problem): the closed-form start, a neutral one (no offset,
        D = I, Wahba on the raw readings) and the closed-form rotation turned by 90 deg about
        each body axis. A minimum that fits better replaces the result; one that fits about
        as well (within 25 effective chi-square units, i.e. 5 sigma) but with a rotation
        that differs by more than 1 deg and 5 sigma makes the result start-dependent.
        """
        if pc.n > 2 * CHECK_SAMPLES:
            pc = _decimated(pc, CHECK_SAMPLES)
        mc = Model(pc, estimate_B=model.estimate_B)
        s_main = gn.s
        starts = [self.initial_state(pc), self._neutral_state(pc)]
        for nf in nested or ():
            # the nested fits' solutions (no D, no tau: those start neutral)
            sn = nf["state"]
            o = sn.o if "offset" in model.blocks else np.zeros(3)
            starts.append(State(sn.R, sn.B, o, starts[1].D, float(p.time_offset0_s)))
        for k in range(3):
            e = np.zeros(3)
            e[k] = np.pi / 2
            s = starts[0]
            R = so3_exp(e) @ s.R
            starts.append(State(R, s.B, s.o, s.D, s.tau))
        # the main solution's cost on the coarse problem
        results = [(s_main, _cost(pc.mag_nT - mc.predict(s_main), mc.weights(s_main),
                                  np.ones(pc.n))[0])]
        for s in starts:
            try:
                g = gauss_newton(mc, s, self.max_iter)
            except (np.linalg.LinAlgError, FloatingPointError):
                continue
            c, _ = _cost(g.r, g.W, np.ones(pc.n))
            if np.isfinite(c):
                results.append((g.s, c))
        c_main = results[0][1]
        dof = max(3 * pc.n - mc.n_params, 1)
        frac = max(float(cal.checks.get("n_eff_fraction", 1.0)), 1e-3)
        s2_eff = (c_main / dof) / frac if p.noise is None else 1.0 / frac
        sig = np.radians(np.where(np.isfinite(cal.sigma_rotvec_deg), cal.sigma_rotvec_deg, 0.0))
        info = []
        note = None
        best_s, best_c = results[0]
        for s, c in results[1:]:
            ang = float(np.degrees(np.linalg.norm(_log(s.R @ s_main.R.T))))
            dchi = (c - c_main) / s2_eff
            info.append({"rotation_from_result_deg": ang, "delta_chi2": float(dchi)})
            if c < best_c and dchi < -25.0:
                best_s, best_c = s, c
        if best_s is not s_main:
            # a clearly better minimum: the result moves there
            gn = gauss_newton(model, best_s, self.max_iter)
            cal = self.finish(p, model, gn)
            s_main, c_main = best_s, best_c
            sig = np.radians(np.where(np.isfinite(cal.sigma_rotvec_deg),
                                      cal.sigma_rotvec_deg, 0.0))
        for s, c in results[1:]:
            dv = _log(s.R @ s_main.R.T)
            ang = float(np.degrees(np.linalg.norm(dv)))
            z = np.abs(dv) / np.maximum(sig, 1e-12)
            dchi = (c - c_main) / s2_eff
            if ang > 1.0 and np.max(z) > 5.0 and abs(dchi) < 25.0:
                rv = np.degrees(_log(s.R))
                note = (
                    "the fit depends on its start: a rotation of "
                    + ", ".join(f"{v:+.1f}" for v in rv)
                    + f" deg fits these data about as well ({ang:.1f} deg away): the motion "
                    "does not determine the misalignment with the requested terms; rotate "
                    "about more axes or estimate fewer terms"
                )
                break
        return gn, cal, note, info

    def _neutral_state(self, p: EstimationProblem) -> State:
        """No offset, D = I (trace-scaled when a reference fixes |B|), Wahba on raw readings."""
        R, B = init_rotation(p.mag_nT, p.C_enu_body, p.reference_field_enu_nT)
        D = np.eye(3)
        if p.reference_field_enu_nT is not None and EstimateTerm.SOFT_IRON in p.terms:
            D = D * np.median(np.linalg.norm(p.mag_nT, axis=1)) / np.linalg.norm(
                p.reference_field_enu_nT)
        return State(R, np.asarray(B, float), np.zeros(3), D, float(p.time_offset0_s))

    def _split(self, p: EstimationProblem, model: Model, gn: GNResult,
               cal: Calibration) -> SplitCheck | None:
        """Fit two contiguous halves of equal rotation information and compare them."""
        if p.n < 200:
            return None
        J = model.jacobian(gn.s)
        info = per_sample_rot_info(J, gn.W, model.blocks["rot"])
        first = info_halves(info)
        sub = MLEstimator(max_iter=self.max_iter, name=self.name, checks=False)
        out = []
        for m in (first, ~first):
            ph = _subset(p, m)
            if ph.n < 50:
                return None
            mh = Model(ph, estimate_B=model.estimate_B)
            try:
                g = gauss_newton(mh, gn.s, self.max_iter)
                c, cov = sub.finish_with_cov(ph, mh, g)
            except (EstimationError, np.linalg.LinAlgError):
                return None
            if c.unobservable_axes_body and not cal.unobservable_axes_body:
                return None
            out.append((c, cov))
        t_split = float((p.t_ns[np.flatnonzero(~first)[0]] - p.t_ns[0]) * 1e-9)
        (a, cov_a), (b, cov_b) = out
        return SplitCheck.compare(a, b, t_split, cov_a, cov_b,
                                  undetermined_directions(cal))


    def finish(self, p: EstimationProblem, model: Model, gn: GNResult) -> Calibration:
        """Covariance, observability and the Calibration value."""
        return self.finish_with_cov(p, model, gn)[0]

    def finish_with_cov(self, p: EstimationProblem, model: Model, gn: GNResult
                        ) -> tuple[Calibration, F64]:
        """:meth:`finish`, and the rotation's covariance (rad^2, 3x3, block sandwich).

        The covariance is finite everywhere: about an axis the motion does not determine it
        is about zero (the truncated inverse), where the calibration's sigma is infinite.
        """
        s, w, W, r, H = gn.s, gn.w, gn.W, gn.r, gn.H
        dof = max(3 * p.n - model.n_params, 1)
        chi2, _ = _cost(r, W, w)
        # Unknown noise: scale by the residual variance. Known noise: the model's own.
        s2 = chi2 / dof if p.noise is None else 1.0
        an = analyse(H, model.blocks)
        cov_white = an.cov * s2
        # Block sandwich (module ``checks``): correlated residuals, never below white.
        cov, n_eff_frac = sandwich_cov(model.jacobian(s), W, w, r, p.t_ns, an.cov, cov_white)
        blocks = model.blocks
        warnings: list[str] = []

        def block_cov(name: str) -> F64:
            sl = blocks[name]
            return cov[sl, sl]

        rot_null = an.block_null.get("rot", np.zeros((3, 0)))
        sig_rot = sigma_with_null(block_cov("rot"), rot_null)
        sig_rot_white = sigma_with_null(cov_white[blocks["rot"], blocks["rot"]], rot_null)
        axes = [canonical_axis(v) for v in rot_null.T]
        if axes:
            warnings.append(rotation_words(axes, p.reference_field_enu_nT is not None))
        sig_B = None
        if "B" in blocks:
            sig_B = sigma_with_null(block_cov("B"), an.block_null.get("B", np.zeros((3, 0))))
        o = sig_o = None
        if "offset" in blocks:
            o = s.o
            nul = an.block_null.get("offset", np.zeros((3, 0)))
            sig_o = sigma_with_null(block_cov("offset"), nul)
            for v in nul.T:
                a = canonical_axis(v)
                warnings.append(
                    "the offset along mag axis ["
                    + ", ".join(f"{c:+.3f}" for c in a)
                    + "] is not observable (kept at its initial value): rotate about a "
                    "second axis so that this direction sees the field change"
                )
        D = sig_D = None
        if "D" in blocks:
            D = s.D
            sl = blocks["D"]
            cd = cov[sl, sl]
            basis = model.basis
            # Var(D_ij) = e_ij^T cov e_ij with e_ij the basis coefficients of element ij.
            coef = basis.reshape(len(basis), 9).T  # (9, k)
            var = np.einsum("ek,kl,el->e", coef, cd, coef)
            sig_D = np.sqrt(np.maximum(var, 0.0)).reshape(3, 3)
            nul = an.block_null.get("D", np.zeros((len(basis), 0)))
            if nul.size:
                touched = np.abs(coef @ nul) > 1e-3
                sig_D = np.where(touched.any(axis=1).reshape(3, 3), np.inf, sig_D)
                warnings.append(
                    "part of the soft-iron matrix D is not observable from this motion (kept at "
                    "its initial value): rotate about two or three different axes"
                )
            if model.estimate_B:
                warnings.append(
                    "without a reference field the overall scale of D cannot be told from |B|: "
                    "D is normalised to trace 3"
                )
        tau = sig_tau = None
        if "tau" in blocks:
            tau = s.tau
            sig_tau = float(np.sqrt(max(block_cov("tau")[0, 0], 0.0)))
            if an.block_null.get("tau", np.zeros((1, 0))).size:
                sig_tau = float("inf")
                warnings.append(
                    "the time offset is not observable (kept at its initial value): it trades "
                    "against the rotation about the turning axis when the rate is constant; "
                    "vary the rotation rate or rotate about a second axis"
                )
        res = r
        rms = float(np.sqrt(np.mean(res**2)))
        if p.robust is not RobustLoss.NONE:
            n_down = int(np.sum(w < 0.5))
            if n_down:
                warnings.append(
                    f"{n_down} samples were down-weighted as outliers by the robust loss"
                )
        cal = Calibration(
            R_body_mag=s.R,
            sigma_rotvec_deg=np.degrees(sig_rot),
            B_enu_nT=s.B,
            estimator=self.name,
            residual_rms_nT=rms,
            n_samples=p.n,
            unobservable_axes_body=tuple(axes),
            D=D,
            offset_nT=o,
            time_offset_s=tau,
            sigma_D=sig_D,
            sigma_offset_nT=sig_o,
            sigma_time_offset_s=sig_tau,
            sigma_B_enu_nT=sig_B,
            R_nominal_body_mag=p.R_nominal_body_mag,
            warnings=tuple(warnings),
            n_eff=float(p.n * n_eff_frac),
            checks={"n_eff_fraction": n_eff_frac,
                    "sigma_rotvec_white_deg": np.degrees(sig_rot_white).tolist()},
        )
        return cal, block_cov("rot")


#: With a time offset, samples closer than this to either end of the attitude series are left
#: out: there the attitude at ``t - tau`` would be extrapolated (clamped), which both biases the
#: fit and breaks the exact tau / rotation degeneracy the observability analysis must see.
TAU_EDGE_MARGIN_S = 0.25


#: Samples of the coarse stage of a long recording (see :meth:`MLEstimator.fit`).
COARSE_SAMPLES = 20_000
#: Samples (evenly spread) on which determinability and the other starts are checked: the
#: information ratios are scale-free and a start's basin does not depend on the sample count.
CHECK_SAMPLES = 4_000


def _decimated(p: EstimationProblem, n_max: int) -> EstimationProblem:
    """Every k-th sample of ``p`` (at most ``n_max``), keeping the full attitude series.

    The time-offset term re-interpolates the attitude at ``t - tau``; that needs the whole
    series, so when the aligned samples are the only attitude they are kept as the series.
    """
    k = int(np.ceil(p.n / n_max))
    att = p.attitude
    if att is None:
        att = AttitudeSeries(p.t_ns - np.int64(round(p.time_offset0_s * 1e9)), p.q_enu_body)
    return EstimationProblem(
        **{
            **p.__dict__,
            "t_ns": p.t_ns[::k],
            "mag_nT": p.mag_nT[::k],
            "q_enu_body": p.q_enu_body[::k],
            "attitude": att,
        }
    )


def _subset(p: EstimationProblem, mask: np.ndarray) -> EstimationProblem:
    """Return the samples of ``p`` where ``mask`` is true, with the whole attitude series."""
    att = p.attitude
    if att is None:
        att = AttitudeSeries(p.t_ns - np.int64(round(p.time_offset0_s * 1e9)), p.q_enu_body)
    return EstimationProblem(**{**p.__dict__, "t_ns": p.t_ns[mask], "mag_nT": p.mag_nT[mask],
                      "q_enu_body": p.q_enu_body[mask], "attitude": att})


def _log(R: F64) -> F64:
    """Return the rotation vector (rad) of a rotation matrix."""
    return quat_to_rotvec(matrix_to_quat(R))


def _inside_attitude_span(p: EstimationProblem) -> EstimationProblem:
    att = p.attitude
    if att is None:
        t_att = p.t_ns - np.int64(round(p.time_offset0_s * 1e9))
    else:
        t_att = att.t_ns
    margin = np.int64((TAU_EDGE_MARGIN_S + abs(p.time_offset0_s)) * 1e9)
    keep = (p.t_ns >= t_att[0] + margin) & (p.t_ns <= t_att[-1] - margin)
    if att is None:
        # The aligned samples are the attitude series itself: keep it whole for interpolation.

        att = AttitudeSeries(t_att, p.q_enu_body)
    return EstimationProblem(
        **{
            **p.__dict__,
            "t_ns": p.t_ns[keep],
            "mag_nT": p.mag_nT[keep],
            "q_enu_body": p.q_enu_body[keep],
            "attitude": att,
        }
    )


def fisher_information(
    p: EstimationProblem,
    R: F64,
    B: F64,
    *,
    D: F64 | None = None,
    offset_nT: F64 | None = None,
    time_offset_s: float = 0.0,
) -> tuple[F64, dict[str, slice]]:
    """Fisher information of all the model's parameters at the truth, and its blocks.

    ``p`` must hold the true attitude (``q_enu_body`` noise-free) and the generator's noise
    model (``p.noise``). The data model is Gaussian with the per-sample covariance
    ``sigma_m^2 I + D R.T [b]x Sigma_att [b]x.T R D.T`` (attitude noise linearised, as the
    generator adds it: :meth:`NoiseModel.attitude_cov_body`), so the information is
    ``sum_i J_i.T Sigma_i^-1 J_i`` with the Jacobian of :class:`Model`. (The covariance also
    depends on ``R``; that dependence carries no information in the exact model, where the
    attitude error moves the reading along the sphere ``|y| = |B|``, and is left out.)

    Returns
    -------
    H : ndarray (P, P)
        In the parameter order of ``blocks`` (rotation in rad, body frame, first).
    blocks : dict of str -> slice

    """
    if p.noise is None:
        raise EstimationError("the Fisher information needs a noise model")
    model = Model(p, estimate_B=p.reference_field_enu_nT is None)
    s = State(
        np.asarray(R, float),
        np.asarray(B, float),
        np.zeros(3) if offset_nT is None else np.asarray(offset_nT, float),
        np.eye(3) if D is None else np.asarray(D, float),
        float(time_offset_s),
    )
    J = model.jacobian(s)
    W = model.weights(s)
    H, _ = _normal(J, W, np.zeros((p.n, 3)), np.ones(p.n))
    return H, model.blocks


def fisher_rotation_crb_deg(p: EstimationProblem, R: F64, B: F64, **truth: object) -> F64:
    """Cramer-Rao bound (1-sigma, deg) of the rotation about body x, y, z at the truth.

    The rotation block of the inverse Fisher information (:func:`fisher_information`), i.e.
    the information marginalised over every nuisance parameter of the problem (``B`` unless
    ``p`` has a reference field, and the offset, ``D`` and ``tau`` when ``p.terms`` asks for
    them; their true values as keywords ``D``, ``offset_nT``, ``time_offset_s``):
    ``M = H_rr - H_ro H_oo^-1 H_or``, bound ``sqrt(diag(M^-1))``. ``inf`` about an axis the
    data cannot determine.
    """
    H, blocks = fisher_information(p, R, B, **truth)  # type: ignore[arg-type]
    # Jacobi scaling: rad^-2 and nT^-2 entries differ by ~1e9.
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    r = blocks["rot"]
    o = np.r_[r.stop : H.shape[0]]
    M = Hs[r, r]
    if o.size:
        M = M - Hs[r][:, o] @ np.linalg.solve(Hs[np.ix_(o, o)], Hs[o][:, r])
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    keep = w > RELATIVE_INFO_THRESHOLD * max(w[-1], 1e-300)
    cov = (V[:, keep] / w[keep]) @ V[:, keep].T
    crb = np.sqrt(np.maximum(np.diag(cov), 0.0)) / d[r]
    touched = np.any(np.abs(V[:, ~keep]) > 1e-3, axis=1)
    return np.degrees(np.where(touched, np.inf, crb))
