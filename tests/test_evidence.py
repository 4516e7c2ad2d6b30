"""The diagnosis' one criterion: the Laplace evidence (``stages/diagnose/statistics.py``).

Its Occam factor against the exact Gaussian marginal likelihood of a linear model, where
Laplace's method is exact; its BIC limit without a prior; and what it charges for the
directions of a prior the data do not see (a field map's fine modes).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from stages.diagnose.statistics import prior_occam


def _exact_minus2_log_evidence(J: np.ndarray, y: np.ndarray, var: np.ndarray, s2: float,
                               free: np.ndarray) -> float:
    """``-2 log p(y)`` of ``y = J x + e`` by the n x n covariance, no Laplace in it.

    ``x_j ~ N(0, var_j)`` where ``free_j`` is false; where it is true the prior is flat and
    the (improper) constant ``log det`` of its information on them is left out the same
    way the Occam factor leaves it out (it cancels between models that share them).
    """
    n = y.size
    Jq, Jo = J[:, ~free], J[:, free]
    C = s2 * np.eye(n) + Jq @ np.diag(var[~free]) @ Jq.T
    Ci = np.linalg.inv(C)
    if Jo.shape[1]:
        # the flat parameters integrated out: the restricted likelihood (REML)
        A = Jo.T @ Ci @ Jo
        Pi = Ci - Ci @ Jo @ np.linalg.solve(A, Jo.T @ Ci)
        return float(y @ Pi @ y + np.linalg.slogdet(C)[1] + np.linalg.slogdet(A)[1]
                     + (n - Jo.shape[1]) * np.log(2 * np.pi))
    return float(y @ Ci @ y + np.linalg.slogdet(C)[1] + n * np.log(2 * np.pi))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 6), n_free=st.integers(0, 3),
       scale=st.floats(0.01, 100.0))
def test_occam_is_the_exact_evidence_of_a_linear_model(seed: int, k: int, n_free: int,
                                                       scale: float) -> None:
    """Laplace's method is exact for a linear model with Gaussian prior and noise.

    ``rss / s2 + prior_occam + n log(2 pi s2) - n_flat log(2 pi)`` plus the ``log det`` of
    the flat parameters' own information must equal the exact ``-2 log`` marginal likelihood,
    to rounding, for priors from far narrower to far wider than the data's information.
    """
    rng = np.random.default_rng(seed)
    n, s2 = 40, 0.7
    P = k + n_free
    J = rng.normal(size=(n, P))
    free = np.zeros(P, dtype=bool)
    free[k:] = True
    var = np.where(free, 0.0, scale * rng.uniform(0.2, 5.0, P))
    x = np.where(free, rng.normal(size=P), rng.normal(size=P) * np.sqrt(np.maximum(var, 0)))
    y = J @ x + rng.normal(scale=np.sqrt(s2), size=n)
    prec = np.where(free, 0.0, s2 / np.where(free, 1.0, var))  # the fit's ridge, per nT^2
    H = J.T @ J + np.diag(prec)
    theta = np.linalg.solve(H, J.T @ y)
    rss = float(np.sum((y - J @ theta) ** 2))
    got = prior_occam(H, prec, np.full(P, s2), theta, np.ones(P, dtype=bool), 1.0, s2)
    # the flat parameters' own information: det(H / s2) = det(H_oo / s2) det(S_q|o / s2),
    # the second factor (with the prior's) is in the Occam factor
    flat = float(np.linalg.slogdet(H[np.ix_(free, free)] / s2)[1]) if n_free else 0.0
    laplace = rss / s2 + got + flat + n * np.log(2 * np.pi * s2) - n_free * np.log(2 * np.pi)
    exact = _exact_minus2_log_evidence(J, y, var, s2, free)
    assert abs(laplace - exact) < 1e-6 * max(1.0, abs(exact))


def test_unseen_directions_cost_nothing() -> None:
    """A prior direction the data carry no information on adds nothing to the Occam factor.

    Five weights, the data see two: the factor is that of the two alone, however many
    unseen weights the basis holds (the reason a map of many modes is not charged
    ``log n`` for each).
    """
    rng = np.random.default_rng(3)
    n, s2 = 200, 1.0
    J = np.zeros((n, 5))
    J[:, :2] = rng.normal(size=(n, 2))
    prec = np.full(5, 0.01)
    H = J.T @ J + np.diag(prec)
    theta = np.linalg.solve(H, J.T @ rng.normal(size=n))
    five = prior_occam(H, prec, np.full(5, s2), theta, np.ones(5, dtype=bool), 1.0, s2)
    two = prior_occam(H[:2, :2], prec[:2], np.full(2, s2), theta[:2], np.ones(2, dtype=bool),
                      1.0, s2)
    assert abs(five - two) < 1e-9
    # and a seen direction with a wide prior costs about log(n var / s2), the BIC's log n
    # plus the log of the prior's width in units of one sample's information
    one = prior_occam(np.array([[n + 1e-4]]), np.array([1e-4]), np.full(1, s2), np.zeros(1),
                      np.ones(1, dtype=bool), 1.0, s2)
    assert abs(one - np.log(1 + n / 1e-4)) < 1e-9


def test_inflation_divides_the_information() -> None:
    """Correlated residuals (inflation ``c``) hold ``1 / c`` of the white information."""
    H = np.array([[101.0]])
    prec = np.array([1.0])
    got = prior_occam(H, prec, np.ones(1), np.zeros(1), np.ones(1, dtype=bool), 4.0, 1.0)
    assert abs(got - np.log(1 + 100.0 / 4.0)) < 1e-12


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 6), ratio=st.floats(0.01, 100.0))
def test_the_prior_is_its_variance_whatever_noise_its_ridge_was_set_against(
        seed: int, k: int, ratio: float) -> None:
    """A ridge set against one noise, a residual of another: the evidence of the prior ``V``.

    A term's ridge is ``noise^2 / var``, with ``noise`` the residual's when the term was
    proposed; once the model fits, its residual variance ``s2`` is another (a field map
    that explains most of the residual leaves a fraction of it). The prior is still
    ``var``: the Occam factor with ``noise2`` must give the exact marginal likelihood of
    ``x ~ N(0, var)`` under noise ``s2``, at the fit of that model.
    """
    rng = np.random.default_rng(seed)
    n, s2 = 40, 0.7
    noise2 = ratio * s2  # the noise the ridge was set against
    J = rng.normal(size=(n, k))
    var = rng.uniform(0.2, 5.0, k)
    y = J @ (rng.normal(size=k) * np.sqrt(var)) + rng.normal(scale=np.sqrt(s2), size=n)
    prec = noise2 / var  # the fit's ridge, weighed against noise2
    H = J.T @ J + np.diag(prec)
    # the posterior mean of the model that is judged: prior var, noise s2
    theta = np.linalg.solve(J.T @ J + np.diag(s2 / var), J.T @ y)
    rss = float(np.sum((y - J @ theta) ** 2))
    got = prior_occam(H, prec, np.full(k, noise2), theta, np.ones(k, dtype=bool), 1.0, s2)
    laplace = rss / s2 + got + n * np.log(2 * np.pi * s2)
    exact = _exact_minus2_log_evidence(J, y, var, s2, np.zeros(k, dtype=bool))
    assert abs(laplace - exact) < 1e-6 * max(1.0, abs(exact))
