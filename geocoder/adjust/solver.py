"""Least-squares block adjustment of scanner frames with points eliminated first (seed 000 sec. 2.4).

The linearised observation equations (seed eq 3) of every image observation ``i`` of ground
point ``p`` in frame ``f`` are ``J_p,i dp_f + J_g,i dg_p = f_i - v_i`` with ``f_i`` the observed
minus the projected image coordinates.  Frames and points can carry pseudo-observations (prior
weights).  The normal equations (eq 4)

    [ N_ff  N_fg ] [dp]   [t_p]
    [ N_gf  N_gg ] [dg] = [t_g]

are reduced by eliminating the ground points first (eq 5): ``N_gg`` is block diagonal with one
3x3 block per point, so ``S = N_ff - N_fg N_gg^-1 N_gf`` is a sparse matrix with one ``n x n``
block for every pair of frames that share a point.  ``S dp = t_p - N_fg N_gg^-1 t_g`` is solved with
a sparse factorisation and the ground corrections are back-substituted per point.

The assembly of ``S`` (:mod:`geocoder.adjust.normals`) streams the observations in chunks of
whole frames, so the working memory is bounded by ``AdjustOptions.block_size``; the precision
figures live in :mod:`geocoder.adjust.statistics`.  Everything is vectorised over observations
and points; the only Python loops are over frames (one model call and one GEMM each), chunks,
buckets of frame pairs of similar size, and iterations.

References
----------
Paderes, Mikhail & Foerstner (1984), Rectification of single and multiple frames of satellite
scanner imagery using points and edges as control, eqs 3-5 (block adjustment), eqs 20b and 22b
(robust weight functions).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ..kernels.robust import weight_exp, weight_l1
from .dem import DEM
from .normals import (
    DEFAULT_BLOCK_SIZE,
    Layout,
    Normals,
    assemble,
    back_substitute,
    hold_to_dem,
    layout,
    residuals,
)
from .normals import cost as _cost
from .statistics import robust_scale, statistics

try:  # optional, faster and symmetric
    from sksparse.cholmod import cholesky as _cholmod_cholesky  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the environment
    _cholmod_cholesky = None

__all__ = [
    "AdjustOptions",
    "AdjustResult",
    "Frame",
    "Problem",
    "SensorModel",
    "adjust",
    "numeric_jacobians",
]

_BANDED_MAX_ENTRIES = (
    1 << 26
)  # banded Cholesky when (bandwidth + 1) * unknowns is below this (512 MB)


class SensorModel(Protocol):
    """What the solver needs from a sensor model (one instance per frame, or shared).

    Attributes
    ----------
    n_params : int
        Number of parameters of one frame.
    """

    n_params: int

    def project(self, params: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Image coordinates of ground points.

        Parameters
        ----------
        params : numpy.ndarray
            The frame's parameters, shape ``(n_params,)``.
        ground : numpy.ndarray
            Ground points, shape ``(m, 3)``.

        Returns
        -------
        numpy.ndarray
            Image coordinates ``(m, 2)`` as ``(x=col, y=row)``.
        """
        ...

    def jacobians(
        self, params: np.ndarray, ground: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of :meth:`project` with respect to the parameters and the ground points.

        Parameters
        ----------
        params : numpy.ndarray
            The frame's parameters, shape ``(n_params,)``.
        ground : numpy.ndarray
            Ground points, shape ``(m, 3)``.

        Returns
        -------
        d_params : numpy.ndarray
            Shape ``(m, 2, n_params)``.
        d_ground : numpy.ndarray
            Shape ``(m, 2, 3)``.
        """
        ...


def numeric_jacobians(
    model: SensorModel,
    params: np.ndarray,
    ground: np.ndarray,
    *,
    step_params: np.ndarray | float | None = None,
    step_ground: np.ndarray | float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference Jacobians of ``model.project``, vectorised over the points.

    Parameters
    ----------
    model : SensorModel
        Only ``project`` is used, so a model may implement ``jacobians`` with this function.
    params : ndarray, shape (n,)
        Parameters at which to differentiate.
    ground : ndarray, shape (m, 3)
        Ground points.
    step_params : float or ndarray, shape (n,), optional
        Half-steps for the parameters; default ``1e-6 * max(1, |params|)``.
    step_ground : float or ndarray, shape (3,), optional
        Half-steps for the ground coordinates (ground units), default 1.0.

    Returns
    -------
    jp : ndarray, shape (m, 2, n)
        Derivatives with respect to the parameters.
    jg : ndarray, shape (m, 2, 3)
        Derivatives with respect to the ground coordinates.
    """
    params = np.asarray(params, dtype=np.float64)
    ground = np.asarray(ground, dtype=np.float64)
    n, m = params.size, ground.shape[0]
    if step_params is None:
        hp = 1e-6 * np.maximum(1.0, np.abs(params))
    else:
        hp = np.broadcast_to(np.asarray(step_params, dtype=np.float64), (n,))
    hg = np.broadcast_to(np.asarray(step_ground, dtype=np.float64), (3,))
    jp = np.empty((m, 2, n))
    for k in range(
        n
    ):  # loop over parameters only; each call is vectorised over the points
        p1, p2 = params.copy(), params.copy()
        p1[k] += hp[k]
        p2[k] -= hp[k]
        jp[:, :, k] = (model.project(p1, ground) - model.project(p2, ground)) / (
            2.0 * hp[k]
        )
    jg = np.empty((m, 2, 3))
    for k in range(3):
        g1, g2 = ground.copy(), ground.copy()
        g1[:, k] += hg[k]
        g2[:, k] -= hg[k]
        jg[:, :, k] = (model.project(params, g1) - model.project(params, g2)) / (
            2.0 * hg[k]
        )
    return jp, jg


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


# --------------------------------------------------------------------------------------------
# the reduced system: ordering, solve, Gauss-Newton
# --------------------------------------------------------------------------------------------


def _frame_order(lay: Layout, pairs: np.ndarray) -> tuple[np.ndarray, int]:
    """Unknown permutation from a reverse Cuthill-McKee ordering of the frame graph, and its bandwidth."""
    nf = lay.n_frames
    adj = sp.coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(nf, nf)
    ).tocsr()
    order = reverse_cuthill_mckee((adj + adj.T).tocsr(), symmetric_mode=True)
    perm = lay.idx[order].ravel()
    perm = perm[perm >= 0]
    pos = np.empty(lay.n_frames, dtype=np.int64)
    pos[order] = np.arange(nf)
    # bandwidth in unknowns: frames coupled at distance d in the order -> < (d + 1) * nmax
    nfree = (lay.idx >= 0).sum(axis=1)
    first = np.zeros(nf + 1, dtype=np.int64)
    first[1:] = np.cumsum(nfree[order])
    pa, pb = pos[pairs[:, 0]], pos[pairs[:, 1]]
    lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
    bw = int(
        np.max(first[hi + 1] - 1 - first[lo], initial=int(nfree.max(initial=1)) - 1)
    )
    return perm, bw


def _solve(
    s: sp.csc_matrix, r: np.ndarray, order: tuple[np.ndarray, int] | None = None
) -> tuple[np.ndarray, str]:
    """Solve the reduced normal equations: CHOLMOD, banded Cholesky (RCM frame order) or SuperLU."""
    n = r.size
    if n == 0:
        return r.copy(), "none"
    if _cholmod_cholesky is not None:  # pragma: no cover - optional dependency
        try:
            return _cholmod_cholesky(s)(r), "cholmod"
        except Exception:  # noqa: BLE001, S110 - not positive definite: use the fallbacks below
            pass
    if order is not None:
        perm, bw = order
        if (bw + 1) * n <= _BANDED_MAX_ENTRIES and bw < n // 2:
            sp_ = s[perm][:, perm].tocoo()
            # frame pairs whose shared observations are all unused are stored zero blocks and
            # may lie outside the band of the coupled pairs
            up = (sp_.row <= sp_.col) & (sp_.col - sp_.row <= bw)
            ab = np.zeros((bw + 1, n))
            ab[bw + sp_.row[up] - sp_.col[up], sp_.col[up]] = sp_.data[up]
            try:
                x = scipy.linalg.solveh_banded(
                    ab, r[perm], overwrite_ab=True, check_finite=False
                )
            except np.linalg.LinAlgError:
                pass
            else:
                out = np.empty(n)
                out[perm] = x
                return out, "banded-cholesky"
    try:
        lu = spla.splu(s, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as exc:
        raise np.linalg.LinAlgError(
            "the reduced normal matrix is singular: add control, priors or fix parameters (datum defect)"
        ) from exc
    return lu.solve(r), "splu"



@dataclass
class _State:
    params: list[np.ndarray]
    ground: np.ndarray
    res: np.ndarray
    normals: Normals
    iterations: int = 0
    converged: bool = False
    solver: str = "splu"
    convergence: str = ""


def _relative_converged(
    lay: Layout,
    res: np.ndarray,
    nrm: Normals,
    u: np.ndarray,
    dg: np.ndarray,
    new_params: list[np.ndarray],
    new_ground: np.ndarray,
    cost: float,
    new_cost: float,
    rtol: float,
) -> bool:
    """MINPACK-style test: actual and predicted relative reductions of the cost both <= rtol.

    ``u`` is ``J_p dp`` per observation (:func:`geocoder.adjust.normals.back_substitute`).
    """
    if not abs(cost - new_cost) <= rtol * cost:
        return False
    step_img = u + np.einsum("mij,mj->mi", nrm.jg, dg[lay.obs_point])
    lin_res = np.where(nrm.used[:, None], res - step_img, 0.0)  # unused rows may hold NaN
    lin_cost = _cost(lay, lin_res, nrm.w, new_params, new_ground, nrm.valid)
    return cost - lin_cost <= rtol * cost


def _gauss_newton(
    lay: Layout,
    models: list[SensorModel],
    params: list[np.ndarray],
    ground: np.ndarray,
    factor: np.ndarray,
    opt: AdjustOptions,
    times: list[float],
) -> _State:
    hold_to_dem(lay, ground)
    res = residuals(lay, models, params, ground)
    nrm = assemble(lay, models, params, ground, res, factor, keep_jacobians=opt.keep_jacobians)
    cost = _cost(lay, res, nrm.w, params, ground, nrm.valid)
    lam = float(opt.damping)
    state = _State(params, ground, res, nrm)
    for it in range(opt.max_iter):
        t0 = time.perf_counter()
        s = nrm.s
        if lam > 0:
            s = (s + sp.diags(lam * s.diagonal())).tocsc()
        dp, state.solver = _solve(s, nrm.r, _frame_order(lay, nrm.frame_pairs))
        dpad = np.zeros((lay.n_frames, lay.nmax))
        sel = lay.idx >= 0
        dpad[sel] = dp[lay.idx[sel]]
        u, dg = back_substitute(lay, models, params, ground, nrm, dpad)
        new_params = []
        for f in range(lay.n_frames):
            p = params[f].copy()
            p[lay.free[f]] += dpad[f, : lay.free[f].size]
            new_params.append(p)
        new_ground = ground + dg
        new_res = residuals(lay, models, new_params, new_ground)
        hold_to_dem(lay, new_ground)  # the DEM misclosure at the new points enters the cost
        new_cost = _cost(lay, new_res, nrm.w, new_params, new_ground, nrm.valid)
        state.iterations = it + 1
        if lam > 0 and not new_cost <= cost:  # NaN (a point lost by a wild step) counts as worse
            # a rejected step that is already negligible: the cost is at its minimum (to rounding)
            at_minimum = (
                opt.rtol > 0
                and np.isfinite(new_cost)
                and _relative_converged(lay, res, nrm, u, dg, new_params, new_ground, cost, new_cost, opt.rtol)
            )
            hold_to_dem(lay, ground)
            times.append(time.perf_counter() - t0)
            if at_minimum:
                state.converged, state.convergence = True, "relative"
                break
            lam *= 10.0
            continue
        lam_used = lam
        if lam > 0:
            lam /= 10.0
        step = max(
            float(np.max(np.abs(dp) * np.sqrt(np.abs(nrm.s.diagonal())), initial=0.0)),
            float(np.max(np.abs(dg) * np.sqrt(np.abs(nrm.ngg_diag)), initial=0.0)),
        )
        relative = opt.rtol > 0 and _relative_converged(
            lay, res, nrm, u, dg, new_params, new_ground, cost, new_cost, opt.rtol / (1.0 + lam_used)
        )
        solver = state.solver
        del nrm, state, u  # keep one set of normal equations in memory
        params, ground, res = new_params, new_ground, new_res
        nrm = assemble(lay, models, params, ground, res, factor, keep_jacobians=opt.keep_jacobians)
        cost = _cost(lay, res, nrm.w, params, ground, nrm.valid)
        state = _State(params, ground, res, nrm, it + 1, False, solver)
        times.append(time.perf_counter() - t0)
        if step < opt.tol or relative:
            state.converged = True
            state.convergence = "step" if step < opt.tol else "relative"
            break
    return state


# --------------------------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------------------------



def adjust(problem: Problem, options: AdjustOptions | None = None) -> AdjustResult:
    """Least-squares block adjustment with the ground points eliminated first (seed eqs 3-5).

    Parameters
    ----------
    problem : Problem
        Frames, ground points and image observations.
    options : AdjustOptions, optional
        Iteration, robust estimation, data snooping and covariance options.

    Returns
    -------
    AdjustResult

    Notes
    -----
    * Gauss-Newton (optionally Levenberg-Marquardt damped) on the reduced normal equations
      ``S dp = r``; ``S`` is assembled as a sparse matrix from one ``n x n`` block per pair of
      frames sharing points and factorised with CHOLMOD if scikit-sparse is importable, else
      ordered by a reverse Cuthill-McKee numbering of the frames (seed sec. 2.4: proper
      numbering makes the reduced system banded) and solved by banded Cholesky
      (``scipy.linalg.solveh_banded``) when the band fits in memory, else by SuperLU
      (``scipy.sparse.linalg.splu``).
    * Points with a singular 3x3 normal block (a tie point seen once and without prior, all of
      its observations rejected...) are left out together with their observations
      (``point_valid``).
    * Robust estimation (``options.robust``) runs after a plain adjustment: each observation
      gets ``w(v)`` of its normalised residual ``v = sqrt(r^T W r / rank(W)) / sigma0``; eq 20b
      for ``robust_l1_iterations`` rounds with a median based (approximately redundancy
      corrected) ``sigma0``, then eq 22b for ``robust_exp_iterations`` rounds with the ``sigma0``
      of the observations kept in the previous round.  Weights are recomputed for every observation
      in every round; factors below ``robust_min_weight`` in the last round reject the
      observation.  The final adjustment uses the original weights of the kept observations.
    * Data snooping (``options.snooping``) rejects the observation with the largest test
      statistic ``sqrt(v^T W v) / (sigma0 sqrt(r_i))`` above ``snooping_threshold`` and
      re-adjusts, at most ``max_snoop_rounds`` times.
    * Redundancy numbers, normalised residuals, covariances and snooping need the dense inverse
      of ``S``; when there are more than ``options.max_dense_unknowns`` reduced unknowns they are
      skipped: ``redundancy``, ``normalized_residuals``, ``param_cov`` and ``ground_cov`` are
      None and no snooping takes place.
    * The frame parameters' fixed entries (``Frame.free``) are removed from the unknowns.
    """
    opt = AdjustOptions() if options is None else options
    lay = layout(problem, opt.block_size)
    models = [fr.model for fr in problem.frames]
    params = [np.asarray(fr.params, dtype=np.float64).copy() for fr in problem.frames]
    ground = np.asarray(problem.ground, dtype=np.float64).copy()
    m = lay.obs_frame.size
    times: list[float] = []
    active = np.ones(m, bool)
    rweight = np.ones(m)
    st = _gauss_newton(lay, models, params, ground, active.astype(float), opt, times)
    if opt.robust:
        kinds = [weight_l1] * opt.robust_l1_iterations + [
            weight_exp
        ] * opt.robust_exp_iterations
        for rnd, wfun in enumerate(
            kinds
        ):  # weights are recomputed for every observation in every round
            raw, sig = robust_scale(
                lay, st.params, st.ground, st.res, st.normals, trimmed=wfun is weight_exp and rnd > 0
            )
            rweight = wfun(raw / sig)
            active = rweight >= opt.robust_min_weight
            rweight[~active] = 0.0
            st = _gauss_newton(lay, models, st.params, st.ground, rweight, opt, times)
        st = _gauss_newton(
            lay, models, st.params, st.ground, active.astype(float), opt, times
        )
    dense = lay.n_unknowns <= opt.max_dense_unknowns
    n_snooped = 0
    stats = statistics(
        lay, models, st.params, st.ground, st.res, st.normals, dense=dense and (opt.snooping or opt.covariance)
    )
    if opt.snooping and dense:
        for _ in range(opt.max_snoop_rounds):
            wt = np.where(np.isfinite(stats.wtest), stats.wtest, -np.inf)
            worst = int(np.argmax(wt)) if m else 0
            if m == 0 or wt[worst] <= opt.snooping_threshold:
                break
            active[worst] = False
            rweight[worst] = 0.0
            n_snooped += 1
            st = _gauss_newton(
                lay, models, st.params, st.ground, active.astype(float), opt, times
            )
            stats = statistics(lay, models, st.params, st.ground, st.res, st.normals, dense=True)
    full = dense and (opt.covariance or opt.snooping)

    def back(x: np.ndarray | None) -> np.ndarray | None:
        if x is None:
            return None
        y = np.empty_like(x)
        y[lay.order] = x
        return y

    return AdjustResult(
        params=st.params,
        ground=st.ground,
        residuals=back(st.res),
        sigma0=stats.sigma0,
        iterations=st.iterations,
        converged=st.converged,
        convergence=st.convergence,
        obs_active=back(active),
        obs_robust_weight=back(rweight),
        redundancy=back(stats.redundancy) if full else None,
        normalized_residuals=back(stats.wtest) if full else None,
        param_cov=stats.param_cov if (full and opt.covariance) else None,
        ground_cov=stats.ground_cov if (full and opt.covariance) else None,
        time_per_iteration=times,
        solver=st.solver,
        point_valid=st.normals.valid.copy(),
        total_redundancy=float(stats.dof),
        pseudo_redundancy=stats.pseudo_redundancy if full else None,
        n_snooped=n_snooped,
    )
