"""Robust weight functions and iteratively re-weighted least squares (seed 000 sec. 4.3.2).

Observations are 2-vectors (a coordinate difference per point pair) that share one
design row ``B_i`` (a basis of monomials in the point's position) for both coordinates, so a
fit is ``obs ~ B @ coef`` with ``coef`` of shape (m, 2) and one weight per point.

References
----------
Paderes, Mikhail & Foerstner (1984), eqs 14-22 and sec. 4.4.3.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np


class StopReason(StrEnum):
    """Why :func:`robust_fit` stopped (a ``str``, so it compares equal to and prints as its value)."""

    PRECISION = "precision"
    MAX_ITERATIONS = "max_iterations"
    TOO_FEW = "too_few"


def weight_l1(v: np.ndarray) -> np.ndarray:
    """Eq 20b: ``w(v) = 4 (sqrt(1 + v^2/2) - 1) / v^2``, the smoothed L1 norm (w(0) = 1)."""
    v2 = np.asarray(v, dtype=np.float64) ** 2
    # 4 (sqrt(1 + v2/2) - 1) / v2, rewritten to stay exact near 0
    return 2.0 / (np.sqrt(1.0 + 0.5 * v2) + 1.0)


def weight_exp(v: np.ndarray) -> np.ndarray:
    """Eq 22b: ``w(v) = exp(-v^2 / 2)``, the redescending weight of Krarup et al."""
    return np.exp(-0.5 * np.asarray(v, dtype=np.float64) ** 2)


@dataclass(frozen=True)
class RobustFit:
    """Result of :func:`robust_fit`.

    Attributes
    ----------
    coef : ndarray, shape (m, 2)
        Coefficients for the x and y components.
    weights : ndarray, shape (n,)
        Final weights; 0 marks a rejected observation.
    residuals : ndarray, shape (n, 2)
        ``obs - basis @ coef`` for every observation (rejected ones included).
    sigma0 : float
        Posterior standard deviation of unit weight (per coordinate) of the survivors.
    iterations : int
        Re-weighting iterations used.
    converged : bool
        Whether the parameter change fell below the required precision.
    reason : StopReason
        Why the iteration stopped: ``PRECISION``, ``MAX_ITERATIONS`` or ``TOO_FEW`` (too few
        observations kept for the fit).
    """

    coef: np.ndarray
    weights: np.ndarray
    residuals: np.ndarray
    sigma0: float
    iterations: int
    converged: bool
    reason: StopReason

    @property
    def inliers(self) -> np.ndarray:
        """Boolean mask of the observations that survived."""
        return self.weights > 0


def _solve(basis: np.ndarray, obs: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    sw = np.sqrt(weights)[:, None]
    coef, _, rank, _ = np.linalg.lstsq(basis * sw, obs * sw, rcond=None)
    return coef if rank == basis.shape[1] else None


def _normalised(residuals: np.ndarray, w0: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """Residual size per point in units of its robust standard deviation."""
    r = np.sqrt(0.5 * (residuals**2).sum(axis=1) * w0)
    scale = 1.4826 * np.median(r[alive]) if alive.any() else 0.0
    scale = max(scale, 1e-12)
    return r / scale


def robust_fit(
    basis: np.ndarray,
    obs: np.ndarray,
    w0: np.ndarray | None = None,
    *,
    l1_iterations: int = 4,
    max_iterations: int = 25,
    precision: float = 1e-3,
    precision_rows: slice = slice(0, 1),
    drop_fraction: float = 0.1,
    min_points: int | None = None,
    test: float = 3.0,
    final_equal_weights: bool = True,
    start: np.ndarray | None = None,
) -> RobustFit:
    """Robust least squares by re-weighting (seed 000 sec. 4.3.2 and 4.4.3).

    The first ``l1_iterations`` iterations use eq 20b, the rest eq 22b, applied to residuals
    normalised by their robust scale (1.4826 x median, so the weights do not depend on the
    units). Weights below ``drop_fraction`` of the mean weight are set to zero. The loop
    stops when the change of the coefficients in ``precision_rows`` (the shift terms) is
    below ``precision``, when fewer than ``min_points`` observations are left, or after
    ``max_iterations``. Survivors whose normalised residual passes ``test`` then get one
    final equal-weight pass.

    Parameters
    ----------
    basis : ndarray, shape (n, m)
        Design rows shared by the x and y component of each observation.
    obs : ndarray, shape (n, 2)
        Observed 2-vectors.
    w0 : ndarray, shape (n,), optional
        Initial (a priori) weights, e.g. eq 29; default all ones.
    start : ndarray, shape (m, 2), optional
        Approximate coefficients (e.g. from a simpler model fitted first): the first
        weights then already reflect the residuals from it (seed 000 sec. 4.4.3).

    Returns
    -------
    RobustFit
    """
    basis = np.asarray(basis, dtype=np.float64)
    obs = np.asarray(obs, dtype=np.float64)
    n, m = basis.shape
    min_points = max(m + 1, min_points or 0)
    w0 = np.ones(n) if w0 is None else np.asarray(w0, dtype=np.float64)
    w0 = np.where(np.isfinite(w0) & (w0 > 0), w0, 0.0)
    if w0.any():
        w0 = w0 / w0[w0 > 0].mean()
    weights = w0.copy()
    coef = np.zeros((m, 2))
    if start is not None:
        coef = np.asarray(start, dtype=np.float64).copy()
        weights = w0 * weight_l1(_normalised(obs - basis @ coef, w0, w0 > 0))
    reason, converged, it = StopReason.MAX_ITERATIONS, False, 0
    if np.count_nonzero(weights) < min_points:
        return RobustFit(coef, np.zeros(n), obs.copy(), np.inf, 0, False, StopReason.TOO_FEW)
    for it in range(1, max_iterations + 1):
        new = _solve(basis, obs, weights)
        if new is None:
            reason = StopReason.TOO_FEW
            break
        change = np.abs(new[precision_rows] - coef[precision_rows]).max()
        coef = new
        residuals = obs - basis @ coef
        alive = weights > 0
        v = _normalised(residuals, w0, alive)
        fn = weight_l1 if it <= l1_iterations else weight_exp
        weights = w0 * fn(v)
        weights[~alive] = 0.0
        if weights.any():
            weights[weights < drop_fraction * weights[weights > 0].mean()] = 0.0
        if np.count_nonzero(weights) < min_points:
            reason = StopReason.TOO_FEW
            break
        if it > l1_iterations and change < precision:
            reason, converged = StopReason.PRECISION, True
            break
    residuals = obs - basis @ coef
    alive = weights > 0
    if reason == StopReason.TOO_FEW:
        return RobustFit(coef, np.zeros(n), residuals, np.inf, it, False, reason)
    survivors = alive & (_normalised(residuals, w0, alive) < test)
    if np.count_nonzero(survivors) < min_points:
        return RobustFit(coef, np.zeros(n), residuals, np.inf, it, False, StopReason.TOO_FEW)
    final_w = np.where(survivors, 1.0 if final_equal_weights else w0, 0.0)
    new = _solve(basis, obs, final_w)
    if new is not None:
        coef = new
    residuals = obs - basis @ coef
    dof = 2 * np.count_nonzero(survivors) - 2 * m
    sigma0 = float(np.sqrt((final_w[:, None] * residuals**2).sum() / dof)) if dof > 0 else np.inf
    return RobustFit(coef, final_w, residuals, sigma0, it, converged, reason)
