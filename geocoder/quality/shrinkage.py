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


def random_effects(values: np.ndarray, var: np.ndarray, design: np.ndarray, *, significance: float = 0.0,
                   correlation: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """The trend ``design @ beta`` of ``values`` and their spread about it beyond their noise.

    Parameters
    ----------
    values, var : ndarray (n,)
        The estimates and their variances (> 0).
    design : ndarray (n, q)
        The trend's regressors (a column of ones: a common mean).
    significance : float
        ``z``: a spread is only taken when the weighted squares of the residuals, ``Q``, exceed
        their expectation without one, ``n - q``, by more than ``z`` times their standard
        deviation, ``sqrt(2 (n - q) correlation)``; 0: whenever they exceed it. Floored at 0,
        the moment estimate is positive by chance on about half of the sets that have no
        spread, and every estimate then keeps a share of its noise that its variance counts
        as signal.
    correlation : float
        How many neighbouring estimates share one's error (their residuals' squares scatter
        that many times more than independent ones').

    Returns
    -------
    trend, trend_var : ndarray (n,)
        The trend, fitted with weights ``1 / (var + tau2)``, and its variance at each estimate.
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
    excess = np.sum(w * resid * resid) - (n - q)
    significant = excess > significance * np.sqrt(2.0 * max(n - q, 0) * correlation)
    tau2 = max(excess / max(scale, 1e-300), 0.0) if significant else 0.0
    w = 1.0 / (v + tau2)
    inv = np.linalg.inv(x.T @ (w[:, None] * x))
    trend = x @ (inv @ (x.T @ (w * y)))
    return trend, np.einsum("li,ij,lj->l", x, inv, x), tau2


def shrink(values: np.ndarray, var: np.ndarray, design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``values`` shrunk toward their trend (:func:`random_effects`) and their posterior variance.

    ``k = tau2 / (tau2 + var)``; the posterior is ``trend + k (values - trend)`` with variance
    ``k var + (1 - k)^2 trend_var``.
    """
    trend, trend_var, tau2 = random_effects(values, var, design)
    v = np.maximum(np.asarray(var, np.float64), 1e-300)
    keep = tau2 / (tau2 + v)
    return trend + keep * (np.asarray(values, np.float64) - trend), keep * v + (1.0 - keep) ** 2 * trend_var
