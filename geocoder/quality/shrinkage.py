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


def random_effects(values: np.ndarray, var: np.ndarray, design: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The trend ``design @ beta`` of ``values`` and their spread about it beyond their noise.

    Parameters
    ----------
    values, var : ndarray (n,)
        The estimates and their variances (> 0).
    design : ndarray (n, q)
        The trend's regressors (a column of ones: a common mean).

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
    tau2 = max((np.sum(w * resid * resid) - (n - q)) / max(scale, 1e-300), 0.0)
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
