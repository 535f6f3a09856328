"""The data types of a block adjustment: frames, the problem, the options and the result.

A :class:`Problem` holds frames (a :class:`~geocoder.adjust.sensor.SensorModel` and its
approximate parameters each), ground points with their pseudo-observations and the image
observations; :func:`geocoder.adjust.solver.adjust` takes it with :class:`AdjustOptions` and
returns an :class:`AdjustResult`.  Plain dataclasses; no computation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .dem import DEM
from .layout import DEFAULT_BLOCK_SIZE
from .sensor import SensorModel

__all__ = ["AdjustOptions", "AdjustResult", "Frame", "Problem"]


@dataclass
class Frame:
    """One image frame: its sensor model and approximate parameters.

    Attributes
    ----------
    model : SensorModel
    params : ndarray, shape (n,)
        Approximate values.
    prior_weight : ndarray, shape (n, n), optional
        Weight of the pseudo-observation ``params = prior_value``.  With a ``free`` mask only the
        free x free block is used.
    prior_value : ndarray, shape (n,), optional
        Defaults to the initial ``params``.
    free : ndarray of bool, shape (n,), optional
        Parameters that are estimated; the others are held at their values.  Default all.
    """

    model: SensorModel
    params: np.ndarray
    prior_weight: np.ndarray | None = None
    prior_value: np.ndarray | None = None
    free: np.ndarray | None = None


@dataclass
class Problem:
    """A block of frames, ground points and image observations.

    Attributes
    ----------
    frames : list of Frame
    ground : ndarray, shape (P, 3)
        Approximate ground coordinates.
    ground_prior : ndarray, shape (P, 3)
        A-priori ground coordinates (surveyed values for control points).
    ground_weight : ndarray, shape (P, 3, 3)
        Weight of the ground pseudo-observations (zeros for tie points; may be rank deficient,
        e.g. only the height).
    obs_frame, obs_point : ndarray of int, shape (M,)
        Frame and point index of every image observation.
    obs_xy : ndarray, shape (M, 2)
        Observed image coordinates ``(x=col, y=row)``.
    obs_weight : ndarray, shape (M, 2, 2)
        Full weight matrices; may be rank deficient (edge points) and are never inverted.
    dem : DEM, optional
        A terrain model (:class:`geocoder.adjust.dem.DEM`): the heights of ``dem_points`` are
        held to its bilinear height with its ``sigma`` (seed 000 sec. 2.5).  The constraint
        ``h(P) - H(lat, lon) = 0`` is re-linearised at every iteration, slope included, and
        replaces those points' ``ground_prior`` / ``ground_weight`` (a point outside the DEM
        keeps them).
    dem_points : ndarray, optional
        Indices (or a boolean mask) of the points held to ``dem``; default all points without
        a prior weight (the tie points).
    """

    frames: list[Frame]
    ground: np.ndarray
    ground_prior: np.ndarray
    ground_weight: np.ndarray
    obs_frame: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_weight: np.ndarray
    dem: DEM | None = None
    dem_points: np.ndarray | None = None


@dataclass
class AdjustOptions:
    """Options of :func:`adjust`.

    Attributes
    ----------
    max_iter : int
        Gauss-Newton iterations per adjustment (each robust or snooping round re-adjusts).
    tol : float
        Convergence when every correction is below ``tol`` times the parameter's conditional
        standard deviation (``|dx_i| sqrt(N_ii) < tol``; an absolute test in units of the
        precision).
    rtol : float
        Relative convergence (MINPACK's ``ftol`` test, scale-free and model-independent):
        converged when both the actual and the predicted relative reduction of the weighted
        square sum ``Omega`` by an accepted step are at most ``rtol``::

            |Omega - Omega_new| <= rtol Omega   and   Omega - Omega_lin <= rtol Omega

        with ``Omega_lin`` the square sum of the linearised residuals ``v - A dx``.  The
        predicted reduction keeps a short step from passing for convergence; a
        Levenberg-Marquardt step damped by ``lambda`` is held to ``rtol / (1 + lambda)``.  Set well above the rounding noise of ``Omega`` (~1e-13
        relative for a million observations) and below the change a useful step makes;
        0 disables it.
    damping : float
        Initial Levenberg-Marquardt ``lambda``: ``S + lambda diag(S)`` is solved, ``lambda`` is
        multiplied by 10 when the cost increases (the step is rejected) and divided by 10
        otherwise.  0 = plain Gauss-Newton.
    robust : bool
        Re-weight with eq 20b (``robust_l1_iterations`` rounds) then eq 22b
        (``robust_exp_iterations`` rounds), rejecting weight factors below ``robust_min_weight``.
    robust_l1_iterations, robust_exp_iterations : int
    robust_min_weight : float
    snooping : bool
        Baarda data snooping after the (robust) adjustment.
    snooping_threshold : float
        Critical value of the normalised residual (3.29 = 99.9 % of the normal distribution).
    max_snoop_rounds : int
        At most this many observations are rejected by snooping (one per round).
    covariance : bool
        Compute ``param_cov``, ``ground_cov``, redundancy numbers and normalised residuals.
    max_dense_unknowns : int
        Covariances, redundancy numbers and snooping need the dense inverse of ``S``; above
        this many reduced unknowns they are skipped (``None`` in the result).
    block_size : int or None
        Observations per chunk of the streamed assembly (whole frames, at least one per chunk):
        the Jacobians and the per-observation products of one chunk at a time are in memory.
        With more than one chunk the parameter Jacobians are kept only within
        ``keep_jacobians``, else evaluated a second time for the back-substitution (and the
        statistics).  None: one chunk,
        everything kept (fastest, memory proportional to the observations).  The results do
        not depend on it beyond rounding.
    keep_jacobians : int
        Bytes of parameter Jacobians (``8 x 2 x parameters`` per observation) that may be kept
        from the assembly for the back-substitution and the statistics; when they need more,
        they are evaluated again chunk by chunk and the memory stays bounded by
        ``block_size`` and this budget.  0 = always evaluate again.
    """

    max_iter: int = 20
    tol: float = 1e-6
    rtol: float = 1e-10
    damping: float = 0.0
    robust: bool = False
    robust_l1_iterations: int = 3
    robust_exp_iterations: int = 3
    robust_min_weight: float = 0.1
    snooping: bool = False
    snooping_threshold: float = 3.29
    max_snoop_rounds: int = 10
    covariance: bool = True
    max_dense_unknowns: int = 5000
    block_size: int | None = DEFAULT_BLOCK_SIZE
    keep_jacobians: int = 1 << 30


@dataclass
class AdjustResult:
    """Result of :func:`adjust` (observation arrays in the problem's order).

    Attributes
    ----------
    params : list of ndarray
        Adjusted parameters per frame (fixed ones unchanged).
    ground : ndarray, shape (P, 3)
        Adjusted ground coordinates (unchanged for points that could not be determined).
    residuals : ndarray, shape (M, 2)
        Observed minus projected image coordinates, for all observations.
    sigma0 : float
        ``sqrt(Omega / total_redundancy)``, ``Omega`` the weighted square sum of the residuals of
        the active observations and pseudo-observations; NaN when the redundancy is 0.
    iterations : int
        Gauss-Newton steps of the final adjustment.
    converged : bool
    convergence : str
        Which test ended the iterations: ``"step"`` (``tol``), ``"relative"`` (``rtol``) or
        ``""`` when ``max_iter`` was reached first.
    obs_active : ndarray of bool, shape (M,)
        False for observations rejected by robust weighting or snooping.
    obs_robust_weight : ndarray, shape (M,)
        Last robust weight factor (1 without robust estimation, 0 when rejected).  The final
        adjustment uses the original weights of the active observations.
    redundancy : ndarray, shape (M,) or None
        Redundancy number ``rank(W_i) - tr(W_i A_i Q A_i^T)`` (sum over the two components, in
        ``[0, rank(W_i)]``); NaN for unused observations.
    normalized_residuals : ndarray, shape (M,) or None
        ``sqrt(v^T W v) / (sigma0 sqrt(r_i))``; NaN for unused observations or ``r_i ~ 0``.
    param_cov : list of ndarray or None
        ``sigma0^2`` times the frame's block of ``S^-1`` (full ``n x n``, zeros for fixed params).
    ground_cov : ndarray, shape (P, 3, 3) or None
        ``sigma0^2 (N_gg^-1 + N_gg^-1 N_gf Q_ff N_fg N_gg^-1)``; NaN for undetermined points.
    time_per_iteration : list of float
        Wall time in seconds of every Gauss-Newton step (all rounds).
    solver : str
        ``"cholmod"``, ``"banded-cholesky"`` or ``"splu"``.
    point_valid : ndarray of bool, shape (P,)
        False for points whose 3x3 normal block is singular (e.g. a tie point seen once, no
        prior); they are left out of the adjustment together with their observations.
    total_redundancy : float
        Number of (rank-counted) observations and pseudo-observations minus unknowns.
    pseudo_redundancy : float or None
        Sum of the redundancy numbers of the pseudo-observations (priors), so that
        ``nansum(redundancy) + pseudo_redundancy == total_redundancy``.
    n_snooped : int
        Observations rejected by data snooping.
    """

    params: list[np.ndarray]
    ground: np.ndarray
    residuals: np.ndarray
    sigma0: float
    iterations: int
    converged: bool
    obs_active: np.ndarray
    obs_robust_weight: np.ndarray
    redundancy: np.ndarray | None
    normalized_residuals: np.ndarray | None
    param_cov: list[np.ndarray] | None
    ground_cov: np.ndarray | None
    time_per_iteration: list[float] = field(default_factory=list)
    solver: str = "splu"
    point_valid: np.ndarray | None = None
    total_redundancy: float = 0.0
    pseudo_redundancy: float | None = None
    n_snooped: int = 0
    convergence: str = ""
