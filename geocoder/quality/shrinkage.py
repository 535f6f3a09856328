"""Empirical Bayes shrinkage of many noisy estimates toward a trend they share (issue 14).

Per-line estimates (a scan line's shift, its slope along the line) are each known to their own
precision, and the lines differ in truth by some spread about a smooth trend across the
scene. :func:`random_effects` fits the trend by weighted least squares and estimates that
spread, ``tau2``, by DerSimonian and Laird's method of moments; :func:`shrink` moves each
estimate ``tau2 / (tau2 + var)`` of the way from the trend to its own value. Estimates that do
not differ beyond their noise come back on the trend, known to the precision of all of them
together; estimates that do (turbulence, relief) keep their own.
"""

from __future__ import annotations

import numpy as np


def random_effects(values: np.ndarray, var: np.ndarray, design: np.ndarray, *, shared: int = 1,
                   z: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """The trend ``design @ beta`` of ``values`` and their spread about it beyond their noise.

    Parameters
    ----------
    values, var : ndarray (n,)
        The estimates and their variances (> 0).
    design : ndarray (n, q)
        The trend's regressors (a column of ones: a common mean).
    shared : int
        Each estimate shares its error with its ``shared - 1`` nearest neighbours on either
        side, linearly less with distance (scan lines matched with a template ``shared``
        rows high): the weighted residuals' sum of squares ``Q`` scatters more than for
        independent estimates.
    z : float
        Only the excess of ``Q`` over its expectation beyond ``z`` of its standard deviations
        (for the estimates' noise alone) counts as spread: a spread that the noise would
        give by chance now and then is taken as none.

    Returns
    -------
    trend, trend_var : ndarray (n,)
        The trend, fitted with weights ``1 / (var + tau2)``, and its variance at each estimate
        (``shared`` times that of independent estimates: ``1 + 2 sum(rho_k)``).
    tau2 : float
        DerSimonian and Laird's moment estimate of the variance of the estimates' true values
        about the trend (at least 0).
    """
    x = np.asarray(design, np.float64)
    y = np.asarray(values, np.float64)
    v = np.maximum(np.asarray(var, np.float64), 1e-300)
    n, q = x.shape
    w = 1.0 / v
    inv = np.linalg.inv(x.T @ (w[:, None] * x))
    resid = y - x @ (inv @ (x.T @ (w * y)))
    scale = np.sum(w) - np.trace(inv @ (x.T @ ((w * w)[:, None] * x)))
    lag = np.arange(1, max(shared, 1))
    # var(Q) = 2 sum_ij rho_ij^2 for correlated standard normal residuals
    inflation = 1.0 + 2.0 * np.sum((1.0 - lag / shared) ** 2)
    chance = z * np.sqrt(2.0 * max(n - q, 1) * inflation)
    tau2 = max((np.sum(w * resid * resid) - (n - q) - chance) / max(scale, 1e-300), 0.0)
    w = 1.0 / (v + tau2)
    inv = np.linalg.inv(x.T @ (w[:, None] * x))
    trend = x @ (inv @ (x.T @ (w * y)))
    # a mean of values sharing their errors over ``shared`` neighbours: 1 + 2 sum(rho_k) = shared
    return trend, max(shared, 1) * np.einsum("li,ij,lj->l", x, inv, x), tau2


def shrink(values: np.ndarray, var: np.ndarray, design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``values`` shrunk toward their trend (:func:`random_effects`) and their posterior variance.

    ``k = tau2 / (tau2 + var)``; the posterior is ``trend + k (values - trend)`` with variance
    ``k var + (1 - k)^2 trend_var``.
    """
    trend, trend_var, tau2 = random_effects(values, var, design)
    v = np.maximum(np.asarray(var, np.float64), 1e-300)
    keep = tau2 / (tau2 + v)
    return trend + keep * (np.asarray(values, np.float64) - trend), keep * v + (1.0 - keep) ** 2 * trend_var


def _inverse_trigamma(y: float) -> float:
    """``x`` with ``trigamma(x) = y`` (> 0), by Newton's method on ``1 / trigamma`` (Smyth 2004)."""
    from scipy.special import polygamma

    x = 0.5 + 1.0 / y
    for _ in range(50):
        tri = float(polygamma(1, x))
        step = tri * (1.0 - tri / y) / float(polygamma(2, x))
        x += step
        if -step / x < 1e-8:
            break
    return x


def moderated_variance(s2: np.ndarray, dof: np.ndarray) -> tuple[np.ndarray, float]:
    """Sample variances shrunk toward their common value by how little they differ beyond chance.

    Each ``s2`` is taken as a scaled chi-square variate with ``dof`` degrees of freedom about
    its own true variance, the true variances as drawn from a scaled inverse chi-square prior
    with ``d0`` degrees of freedom about ``s0^2``. ``d0`` and ``s0^2`` come from the moments of
    ``log s2`` (Smyth 2004, the empirical Bayes step of limma): where the ``s2`` scatter no
    more than their degrees of freedom explain, ``d0`` is infinite and every variance is
    ``s0^2``; where they scatter much more, each keeps nearly its own.

    Parameters
    ----------
    s2 : ndarray (n,)
        Sample variances (> 0).
    dof : ndarray (n,)
        Their degrees of freedom (> 0).

    Returns
    -------
    ndarray (n,)
        The posterior means ``(d0 s0^2 + dof s2) / (d0 + dof)``.
    float
        ``d0`` (``inf``: the variances do not differ beyond chance).
    """
    from scipy.special import digamma, polygamma

    s2 = np.asarray(s2, np.float64)
    d = np.maximum(np.asarray(dof, np.float64), 1e-3)
    if s2.size < 3:
        return s2, 0.0
    s2 = np.maximum(s2, 1e-6 * max(float(np.median(s2)), 1e-300))  # a zero is no log
    e = np.log(s2) - digamma(d / 2) + np.log(d / 2)
    mean = float(np.mean(e))
    excess = float(np.var(e, ddof=1) - np.mean(polygamma(1, d / 2)))
    if excess <= 0:
        return np.full_like(s2, np.exp(mean)), np.inf
    d0 = 2.0 * _inverse_trigamma(excess)
    s0 = np.exp(mean + digamma(d0 / 2) - np.log(d0 / 2))
    return (d0 * s0 + d * s2) / (d0 + d), d0
