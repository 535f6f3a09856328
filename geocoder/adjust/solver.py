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

Everything is vectorised over observations and points; the only Python loops are over frames
(one model call and one small GEMM each), over groups of frame pairs of similar size in the
assembly of ``S``, and over the iterations.

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

_RANK_RTOL = (
    1e-9  # eigenvalues below this fraction of the largest count as zero (weight ranks)
)
_POINT_RTOL = (
    1e-10  # a 3x3 point block whose eigenvalue ratio is below this is singular
)
_GEMM_BUDGET = 1 << 16  # observation pairs gathered at once in the assembly of S
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
# small vectorised helpers
# --------------------------------------------------------------------------------------------


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of ``values`` (m, ...) into ``n`` bins given by ``index`` (m,)."""
    m = index.shape[0]
    flat = values.reshape(m, -1)
    agg = sp.csr_matrix((np.ones(m), (index, np.arange(m))), shape=(n, m))
    return np.asarray(agg @ flat).reshape((n,) + values.shape[1:])


def _ranks(w: np.ndarray) -> np.ndarray:
    """Numerical ranks of a stack of symmetric PSD matrices (k, d, d)."""
    if w.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    ev = np.linalg.eigvalsh(w)
    top = ev[:, -1:]
    return np.sum(ev > _RANK_RTOL * np.maximum(top, 0.0), axis=1) * (top[:, 0] > 0)


def _same_point_pairs(
    obs: np.ndarray, point: np.ndarray, *, ordered: bool
) -> tuple[np.ndarray, np.ndarray]:
    """All pairs ``(a, b)`` of observations ``obs`` sharing a point (``a`` before ``b`` unless ordered).

    Includes ``a == b``.  With ``ordered`` every ``(a, b)`` and ``(b, a)`` is listed, grouped
    by ``a``.
    """
    order = np.argsort(point[obs], kind="stable")
    s_obs = obs[order]
    s_pt = point[s_obs]
    n = s_obs.size
    if n == 0:
        return s_obs, s_obs
    is_start = np.r_[True, s_pt[1:] != s_pt[:-1]]
    gstart_of_group = np.flatnonzero(is_start)
    counts = np.diff(np.r_[gstart_of_group, n])
    gid = np.cumsum(is_start) - 1
    gstart = gstart_of_group[gid]
    gend = gstart + counts[gid]
    first = gstart if ordered else np.arange(n)
    lens = gend - first
    total = int(lens.sum())
    a_pos = np.repeat(np.arange(n), lens)
    offs = np.arange(total) - np.repeat(np.cumsum(lens) - lens, lens)
    b_pos = np.repeat(first, lens) + offs
    return s_obs[a_pos], s_obs[b_pos]


def _segmented_gemm(
    x: np.ndarray,
    y: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    seg: np.ndarray,
    nseg: int,
    scale: np.ndarray,
) -> np.ndarray:
    """``U[s] = sum_{q: seg_q = s} scale_q x[a_q]^T y[b_q]`` for ``x, y`` of shape (m, 3, n).

    ``seg`` must be sorted.  Segments are grouped by length (powers of two) and each group is
    zero-padded and computed with one batched matrix product, so the work runs in BLAS.
    """
    n = x.shape[2]
    out = np.zeros((nseg, n, n))
    counts = np.bincount(seg, minlength=nseg)
    starts = np.cumsum(counts) - counts
    nz = np.flatnonzero(counts)
    if nz.size == 0:
        return out
    bucket = np.ceil(np.log2(counts[nz])).astype(np.int64)
    for bk in np.unique(bucket):
        segs = nz[bucket == bk]
        length = int(counts[segs].max())
        step = max(1, _GEMM_BUDGET // length)
        ar = np.arange(length)
        for j in range(0, segs.size, step):
            ss = segs[j : j + step]
            mask = ar[None, :] < counts[ss][:, None]
            pos = np.where(mask, starts[ss][:, None] + ar[None, :], starts[ss][:, None])
            wq = np.where(mask, scale[pos], 0.0)
            xg = x[a[pos]] * wq[:, :, None, None]  # (s, L, 3, n)
            yg = y[b[pos]]
            k = ss.size
            out[ss] = np.matmul(
                xg.reshape(k, 3 * length, n).transpose(0, 2, 1),
                yg.reshape(k, 3 * length, n),
            )
    return out


# --------------------------------------------------------------------------------------------
# problem layout and linearisation
# --------------------------------------------------------------------------------------------


@dataclass
class _Layout:
    n_frames: int
    n_points: int
    order: (
        np.ndarray
    )  # internal observation i is problem observation order[i] (sorted by frame)
    frame_start: np.ndarray  # (F + 1,)
    obs_frame: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_weight: np.ndarray
    obs_rank: np.ndarray
    free: list[np.ndarray]  # indices of free parameters per frame
    nmax: int
    idx: np.ndarray  # (F, nmax) global unknown index, -1 = padding
    n_unknowns: int
    prior_w: list[np.ndarray | None]  # free x free
    prior_val: list[np.ndarray]
    ground_prior: np.ndarray
    ground_weight: np.ndarray
    ground_rank: np.ndarray
    prior_rank: int
    dem: DEM | None = None
    dem_idx: np.ndarray | None = None  # points held to the DEM
    dem_prior0: np.ndarray | None = None  # their own prior, kept where the DEM has no height
    dem_weight0: np.ndarray | None = None


def _hold_to_dem(lay: _Layout, ground: np.ndarray) -> None:
    """Re-linearise the DEM height constraint of ``lay.dem_idx`` at ``ground`` (in place).

    ``c(P) + g . dP = 0`` with weight ``1 / sigma^2`` is written as the ground pseudo-observation
    ``(prior - P)^T W (prior - P)`` with ``W = g g^T / sigma^2`` and ``prior = P - g c / |g|^2``:
    the same normal-equation terms, and ``c^2 / sigma^2`` in the cost.
    """
    if lay.dem is None or lay.dem_idx is None or lay.dem_idx.size == 0:
        return
    k = lay.dem_idx
    c, g = lay.dem.constraint(ground[k])
    ok = np.isfinite(c) & np.all(np.isfinite(g), axis=1)
    c, g = np.where(ok, c, 0.0), np.where(ok[:, None], g, 0.0)
    gg = np.maximum(np.einsum("pi,pi->p", g, g), np.finfo(float).tiny)
    w = g[:, :, None] * g[:, None, :] / lay.dem.sigma**2
    prior = ground[k] - g * (c / gg)[:, None]
    lay.ground_weight[k] = np.where(ok[:, None, None], w, lay.dem_weight0)
    lay.ground_prior[k] = np.where(ok[:, None], prior, lay.dem_prior0)
    lay.ground_rank[k] = np.where(ok, 1, _ranks(lay.dem_weight0))


def _layout(problem: Problem) -> _Layout:
    frames = problem.frames
    nf = len(frames)
    npt = int(np.asarray(problem.ground).shape[0])
    obs_frame = np.asarray(problem.obs_frame, dtype=np.int64)
    order = np.argsort(obs_frame, kind="stable")
    of = obs_frame[order]
    frame_start = np.searchsorted(of, np.arange(nf + 1))
    free, prior_w, prior_val = [], [], []
    prior_rank = 0
    for fr in frames:
        p = np.asarray(fr.params, dtype=np.float64)
        fmask = np.ones(p.size, bool) if fr.free is None else np.asarray(fr.free, bool)
        fi = np.flatnonzero(fmask)
        free.append(fi)
        prior_val.append(
            p.copy()
            if fr.prior_value is None
            else np.asarray(fr.prior_value, np.float64)
        )
        if fr.prior_weight is None:
            prior_w.append(None)
        else:
            wf = np.asarray(fr.prior_weight, np.float64)[np.ix_(fi, fi)]
            prior_w.append(wf)
            prior_rank += int(_ranks(wf[None])[0]) if fi.size else 0
    nfree = np.array([f.size for f in free], dtype=np.int64)
    nmax = int(nfree.max()) if nf else 0
    offs = np.cumsum(nfree) - nfree
    ar = np.arange(nmax)
    idx = np.where(ar[None, :] < nfree[:, None], offs[:, None] + ar[None, :], -1)
    ow = np.asarray(problem.obs_weight, np.float64)[order]
    gw = np.array(problem.ground_weight, np.float64)  # copies: the DEM constraint updates rows
    gp = np.array(problem.ground_prior, np.float64)
    dem_idx = None
    if problem.dem is not None:
        sel = problem.dem_points
        if sel is None:
            dem_idx = np.flatnonzero(~np.any(gw != 0, axis=(1, 2)))
        else:
            sel = np.asarray(sel)
            dem_idx = np.flatnonzero(sel) if sel.dtype == bool else np.unique(sel.astype(np.int64))
    return _Layout(
        n_frames=nf,
        n_points=npt,
        order=order,
        frame_start=frame_start,
        obs_frame=of,
        obs_point=np.asarray(problem.obs_point, dtype=np.int64)[order],
        obs_xy=np.asarray(problem.obs_xy, np.float64)[order],
        obs_weight=ow,
        obs_rank=_ranks(ow),
        free=free,
        nmax=nmax,
        idx=idx,
        n_unknowns=int(nfree.sum()),
        prior_w=prior_w,
        prior_val=prior_val,
        ground_prior=gp,
        ground_weight=gw,
        ground_rank=_ranks(gw),
        prior_rank=prior_rank,
        dem=problem.dem,
        dem_idx=dem_idx,
        dem_prior0=None if dem_idx is None else gp[dem_idx].copy(),
        dem_weight0=None if dem_idx is None else gw[dem_idx].copy(),
    )


@dataclass
class _Lin:
    res: np.ndarray  # (M, 2) observed - projected
    jp: np.ndarray  # (M, 2, nmax), free columns first
    jg: np.ndarray  # (M, 2, 3)


def _residuals(
    lay: _Layout,
    models: list[SensorModel],
    params: list[np.ndarray],
    ground: np.ndarray,
) -> np.ndarray:
    """Observed minus projected image coordinates (M, 2), one model call per frame."""
    res = np.zeros((lay.obs_frame.size, 2))
    for f in range(lay.n_frames):
        s0, s1 = lay.frame_start[f], lay.frame_start[f + 1]
        if s1 > s0:
            res[s0:s1] = lay.obs_xy[s0:s1] - models[f].project(
                params[f], ground[lay.obs_point[s0:s1]]
            )
    return res


def _linearise(
    lay: _Layout,
    models: list[SensorModel],
    params: list[np.ndarray],
    ground: np.ndarray,
    res: np.ndarray | None = None,
) -> _Lin:
    m = lay.obs_frame.size
    if res is None:
        res = _residuals(lay, models, params, ground)
    jp = np.zeros((m, 2, lay.nmax))
    jg = np.empty((m, 2, 3))
    for f in range(
        lay.n_frames
    ):  # one model call per frame, vectorised over its observations
        s0, s1 = lay.frame_start[f], lay.frame_start[f + 1]
        if s1 == s0:
            continue
        g = ground[lay.obs_point[s0:s1]]
        a, b = models[f].jacobians(params[f], g)
        fi = lay.free[f]
        jp[s0:s1, :, : fi.size] = np.asarray(a)[:, :, fi]
        jg[s0:s1] = b
    return _Lin(res, jp, jg)


def _cost(
    lay: _Layout,
    res: np.ndarray,
    w: np.ndarray,
    params: list[np.ndarray],
    ground: np.ndarray,
    valid: np.ndarray,
) -> float:
    """Weighted square sum of observation and pseudo-observation residuals."""
    c = float(np.einsum("mi,mij,mj->", res, w, res))
    for f in range(lay.n_frames):
        if lay.prior_w[f] is not None:
            d = (lay.prior_val[f] - params[f])[lay.free[f]]
            c += float(d @ lay.prior_w[f] @ d)
    d = lay.ground_prior - ground
    c += float(np.einsum("pi,pij,pj->", d[valid], lay.ground_weight[valid], d[valid]))
    return c


@dataclass
class _Normals:
    w: np.ndarray  # (M, 2, 2) effective weights (0 for unused observations)
    used: np.ndarray  # (M,) bool
    valid: np.ndarray  # (P,) bool
    ninv: np.ndarray  # (P, 3, 3)
    ct: np.ndarray  # (M, 3, n) = Jg^T W Jp
    et: np.ndarray  # (M, 3, n) = Ngg^-1 Jg^T W Jp
    tg: np.ndarray  # (P, 3)
    s: sp.csc_matrix
    r: np.ndarray
    ngg_diag: np.ndarray  # (P, 3)
    frame_pairs: np.ndarray  # (K, 2) frames coupled through points


def _normals(
    lay: _Layout,
    lin: _Lin,
    factor: np.ndarray,
    params: list[np.ndarray],
    ground: np.ndarray,
) -> _Normals:
    nf, npt, nmax = lay.n_frames, lay.n_points, lay.nmax
    w = lay.obs_weight * factor[:, None, None]
    pt = lay.obs_point
    wjg = np.matmul(w, lin.jg)  # (M, 2, 3)
    ngg = (
        _sum_by(pt, np.matmul(lin.jg.transpose(0, 2, 1), wjg), npt) + lay.ground_weight
    )
    ev = np.linalg.eigvalsh(ngg)
    valid = (ev[:, -1] > 0) & (ev[:, 0] > _POINT_RTOL * ev[:, -1])
    used = (factor > 0) & valid[pt] & (lay.obs_rank > 0)
    if not used.all():
        w = w * used[:, None, None]
        wjg = wjg * used[:, None, None]
    ninv = np.zeros((npt, 3, 3))
    ninv[valid] = np.linalg.inv(ngg[valid])
    tg = _sum_by(pt, np.einsum("mij,mi->mj", wjg, lin.res), npt)
    tg += np.einsum("pij,pj->pi", lay.ground_weight, lay.ground_prior - ground)
    tg[~valid] = 0.0
    ct = np.matmul(wjg.transpose(0, 2, 1), lin.jp)  # (M, 3, n)
    et = np.matmul(ninv[pt], ct)
    # frame blocks and reduced right-hand side
    nff = np.zeros((nf, nmax, nmax))
    tp = np.zeros((nf, nmax))
    wres = np.einsum("mij,mj->mi", w, lin.res)
    for f in range(nf):  # small GEMMs, O(frames)
        s0, s1 = lay.frame_start[f], lay.frame_start[f + 1]
        if s1 > s0:
            jpf = lin.jp[s0:s1].reshape(-1, nmax)  # (2K, n), contiguous
            nff[f] = jpf.T @ np.matmul(w[s0:s1], lin.jp[s0:s1]).reshape(-1, nmax)
            tp[f] = jpf.T @ wres[s0:s1].ravel()
        if lay.prior_w[f] is not None:
            k = lay.free[f].size
            nff[f, :k, :k] += lay.prior_w[f]
            tp[f, :k] += lay.prior_w[f] @ (lay.prior_val[f] - params[f])[lay.free[f]]
    tp -= _sum_by(lay.obs_frame, np.einsum("min,mi->mn", et, tg[pt]), nf)
    # coupling through the points: pairs of used observations sharing a point
    a, b = _same_point_pairs(np.flatnonzero(used), pt, ordered=False)
    fa, fb = lay.obs_frame[a], lay.obs_frame[b]
    swap = fa > fb
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    fa, fb = np.minimum(fa, fb), np.maximum(fa, fb)
    key = fa * nf + fb
    o = np.argsort(key, kind="stable")
    a, b, key = a[o], b[o], key[o]
    ukey, seg = np.unique(key, return_inverse=True)
    scale = np.where(a == b, 0.5, 1.0)  # U + U^T on the diagonal counts a == b once
    u = _segmented_gemm(et, ct, a, b, seg.ravel(), ukey.size, scale)
    ka, kb = ukey // nf, ukey % nf
    rows = np.concatenate(
        [
            np.broadcast_to(lay.idx[:, :, None], nff.shape).ravel(),
            np.broadcast_to(lay.idx[ka][:, :, None], u.shape).ravel(),
            np.broadcast_to(lay.idx[kb][:, :, None], u.shape).ravel(),
        ]
    )
    cols = np.concatenate(
        [
            np.broadcast_to(lay.idx[:, None, :], nff.shape).ravel(),
            np.broadcast_to(lay.idx[kb][:, None, :], u.shape).ravel(),
            np.broadcast_to(lay.idx[ka][:, None, :], u.shape).ravel(),
        ]
    )
    vals = np.concatenate([nff.ravel(), -u.ravel(), -u.transpose(0, 2, 1).ravel()])
    keep = (rows >= 0) & (cols >= 0)
    nu = lay.n_unknowns
    rows, cols, vals = (
        rows[keep].astype(np.int32),
        cols[keep].astype(np.int32),
        vals[keep],
    )
    s = sp.coo_matrix((vals, (rows, cols)), shape=(nu, nu)).tocsc()
    del rows, cols, vals
    s.sum_duplicates()
    r = np.zeros(nu)
    sel = lay.idx >= 0
    r[lay.idx[sel]] = tp[sel]
    pairs = np.c_[ka, kb]
    return _Normals(
        w,
        used,
        valid,
        ninv,
        ct,
        et,
        tg,
        s,
        r,
        np.diagonal(ngg, axis1=1, axis2=2).copy(),
        pairs,
    )


def _frame_order(lay: _Layout, pairs: np.ndarray) -> tuple[np.ndarray, int]:
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
            up = sp_.row <= sp_.col
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
    lin: _Lin
    normals: _Normals
    iterations: int = 0
    converged: bool = False
    solver: str = "splu"
    convergence: str = ""


def _relative_converged(
    lay: _Layout,
    lin: _Lin,
    nrm: _Normals,
    dpad: np.ndarray,
    dg: np.ndarray,
    new_params: list[np.ndarray],
    new_ground: np.ndarray,
    cost: float,
    new_cost: float,
    rtol: float,
) -> bool:
    """MINPACK-style test: actual and predicted relative reductions of the cost both <= rtol."""
    if not abs(cost - new_cost) <= rtol * cost:
        return False
    step_img = np.einsum("min,mn->mi", lin.jp, dpad[lay.obs_frame])
    step_img += np.einsum("mij,mj->mi", lin.jg, dg[lay.obs_point])
    lin_res = np.where(nrm.used[:, None], lin.res - step_img, 0.0)  # unused rows may hold NaN
    lin_cost = _cost(lay, lin_res, nrm.w, new_params, new_ground, nrm.valid)
    return cost - lin_cost <= rtol * cost


def _gauss_newton(
    lay: _Layout,
    models: list[SensorModel],
    params: list[np.ndarray],
    ground: np.ndarray,
    factor: np.ndarray,
    opt: AdjustOptions,
    times: list[float],
) -> _State:
    _hold_to_dem(lay, ground)
    lin = _linearise(lay, models, params, ground)
    nrm = _normals(lay, lin, factor, params, ground)
    cost = _cost(lay, lin.res, nrm.w, params, ground, nrm.valid)
    lam = float(opt.damping)
    state = _State(params, ground, lin, nrm)
    for it in range(opt.max_iter):
        t0 = time.perf_counter()
        s = nrm.s
        if lam > 0:
            s = (s + sp.diags(lam * s.diagonal())).tocsc()
        dp, state.solver = _solve(s, nrm.r, _frame_order(lay, nrm.frame_pairs))
        dpad = np.zeros((lay.n_frames, lay.nmax))
        sel = lay.idx >= 0
        dpad[sel] = dp[lay.idx[sel]]
        back = _sum_by(
            lay.obs_point,
            np.einsum("min,mn->mi", nrm.ct, dpad[lay.obs_frame]),
            lay.n_points,
        )
        dg = np.einsum("pij,pj->pi", nrm.ninv, nrm.tg - back)
        new_params = []
        for f in range(lay.n_frames):
            p = params[f].copy()
            p[lay.free[f]] += dpad[f, : lay.free[f].size]
            new_params.append(p)
        new_ground = ground + dg
        new_res = _residuals(lay, models, new_params, new_ground)
        _hold_to_dem(lay, new_ground)  # the DEM misclosure at the new points enters the cost
        new_cost = _cost(lay, new_res, nrm.w, new_params, new_ground, nrm.valid)
        state.iterations = it + 1
        if lam > 0 and not new_cost <= cost:  # NaN (a point lost by a wild step) counts as worse
            # a rejected step that is already negligible: the cost is at its minimum (to rounding)
            at_minimum = (
                opt.rtol > 0
                and np.isfinite(new_cost)
                and _relative_converged(lay, lin, nrm, dpad, dg, new_params, new_ground, cost, new_cost, opt.rtol)
            )
            _hold_to_dem(lay, ground)
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
            lay, lin, nrm, dpad, dg, new_params, new_ground, cost, new_cost, opt.rtol / (1.0 + lam_used)
        )
        solver = state.solver
        del nrm, lin, state  # keep one set of normal equations in memory
        params, ground = new_params, new_ground
        lin = _linearise(lay, models, params, ground, new_res)
        nrm = _normals(lay, lin, factor, params, ground)
        cost = _cost(lay, lin.res, nrm.w, params, ground, nrm.valid)
        state = _State(params, ground, lin, nrm, it + 1, False, solver)
        times.append(time.perf_counter() - t0)
        if step < opt.tol or relative:
            state.converged = True
            state.convergence = "step" if step < opt.tol else "relative"
            break
    return state


# --------------------------------------------------------------------------------------------
# statistics: sigma0, covariances, redundancy numbers
# --------------------------------------------------------------------------------------------


def _redundancy_total(lay: _Layout, nrm: _Normals) -> float:
    n_obs = float(lay.obs_rank[nrm.used].sum())
    n_pseudo = float(lay.prior_rank + lay.ground_rank[nrm.valid].sum())
    return n_obs + n_pseudo - lay.n_unknowns - 3.0 * float(nrm.valid.sum())


@dataclass
class _Stats:
    sigma0: float
    dof: float
    redundancy: np.ndarray | None = None
    wtest: np.ndarray | None = None
    param_cov: list[np.ndarray] | None = None
    ground_cov: np.ndarray | None = None
    pseudo_redundancy: float | None = None


def _statistics(lay: _Layout, st: _State, *, dense: bool) -> _Stats:
    nrm, lin = st.normals, st.lin
    omega = _cost(lay, lin.res, nrm.w, st.params, st.ground, nrm.valid)
    dof = _redundancy_total(lay, nrm)
    sigma0 = float(np.sqrt(omega / dof)) if dof > 0 else float("nan")
    out = _Stats(sigma0, dof)
    if not dense:
        return out
    s2 = sigma0**2 if np.isfinite(sigma0) else 1.0
    nu, nf, nmax = lay.n_unknowns, lay.n_frames, lay.nmax
    sdense = nrm.s.toarray()
    if nu:
        try:
            q = scipy.linalg.cho_solve(scipy.linalg.cho_factor(sdense), np.eye(nu))
        except np.linalg.LinAlgError:
            q = np.linalg.inv(sdense)
    else:
        q = np.zeros((0, 0))
    qpad = np.zeros((nu + 1, nu + 1))
    qpad[:nu, :nu] = q
    idx = np.where(lay.idx >= 0, lay.idx, nu)
    qdiag = qpad[idx[:, :, None], idx[:, None, :]]  # (F, n, n)
    pt, frm = lay.obs_point, lay.obs_frame
    # Yt_i = (Q[f_i, :] N_fg[:, p_i])^T = sum_b C_b^T Q[f_b, f_i]   (3, n)
    a, b = _same_point_pairs(np.flatnonzero(nrm.used), pt, ordered=True)
    yt = np.zeros((pt.size, 3, nmax))
    step = max(1, _GEMM_BUDGET // max(nmax, 1))
    for j in range(0, a.size, step):  # chunks of pairs, bounded memory
        aa, bb = a[j : j + step], b[j : j + step]
        qb = qpad[idx[frm[bb]][:, :, None], idx[frm[aa]][:, None, :]]
        np.add.at(yt, aa, np.matmul(nrm.ct[bb], qb))
    # V_p = N_gp Q N_fg[:, p] = sum_b C_b^T Y_b
    v = _sum_by(pt, np.einsum("min,mjn->mij", nrm.ct, yt), lay.n_points)
    ninv = nrm.ninv
    qgg = ninv + np.matmul(np.matmul(ninv, v), ninv)
    # covariance of the predicted observations: B = G Q G^T + Jg Ngg^-1 Jg^T with G = Jp - K N_gp
    k = np.matmul(lin.jg, ninv[pt])  # (M, 2, 3)
    jq = np.zeros_like(lin.jp)
    for f in range(nf):  # one small GEMM per frame
        s0, s1 = lay.frame_start[f], lay.frame_start[f + 1]
        jq[s0:s1] = lin.jp[s0:s1] @ qdiag[f]
    jy = np.matmul(lin.jp, yt.transpose(0, 2, 1))  # Jp Y  (M, 2, 3)
    bmat = np.matmul(jq, lin.jp.transpose(0, 2, 1)) - np.matmul(
        jy, k.transpose(0, 2, 1)
    )
    bmat -= np.matmul(k, jy.transpose(0, 2, 1))
    bmat += np.matmul(np.matmul(k, v[pt]), k.transpose(0, 2, 1))
    bmat += np.matmul(k, lin.jg.transpose(0, 2, 1))
    wb = np.einsum("mij,mji->m", nrm.w, bmat)
    red = np.where(nrm.used, lay.obs_rank - wb, np.nan)
    vwv = np.einsum("mi,mij,mj->m", lin.res, nrm.w, lin.res)
    with np.errstate(invalid="ignore", divide="ignore"):
        wt = np.where(
            nrm.used & (red > 1e-10),
            np.sqrt(vwv / red) / (sigma0 if np.isfinite(sigma0) else 1.0),
            np.nan,
        )
    # pseudo-observations
    pseudo = 0.0
    for f in range(nf):
        if lay.prior_w[f] is not None:
            kf = lay.free[f].size
            pw = lay.prior_w[f]
            pseudo += float(_ranks(pw[None])[0]) - float(
                np.sum(pw * qdiag[f, :kf, :kf])
            )
    vg = nrm.valid
    pseudo += float(
        lay.ground_rank[vg].sum()
        - np.einsum("pij,pji->", lay.ground_weight[vg], qgg[vg])
    )
    param_cov = []
    for f in range(nf):
        n_all = st.params[f].size
        c = np.zeros((n_all, n_all))
        fi = lay.free[f]
        c[np.ix_(fi, fi)] = s2 * qdiag[f, : fi.size, : fi.size]
        param_cov.append(c)
    gcov = s2 * qgg
    gcov[~vg] = np.nan
    out.redundancy, out.wtest, out.param_cov, out.ground_cov, out.pseudo_redundancy = (
        red,
        wt,
        param_cov,
        gcov,
        pseudo,
    )
    return out


def _robust_scale(
    lay: _Layout, st: _State, *, trimmed: bool
) -> tuple[np.ndarray, float]:
    """Per-observation ``sqrt(r^T W r / rank)`` (nominal weights) and a robust sigma0 estimate.

    ``trimmed``: sigma0 of the observations kept in the last round (those with a positive
    weight factor), with their nominal weights, ``sqrt(Omega / redundancy)``.  Otherwise
    (resistant to any fraction of gross errors below one half, somewhat low): the median of the
    residuals standardised with an approximate redundancy fraction per point,
    ``1 - 3 / (components observed at the point + rank of its prior)``, divided by the median
    of ``sqrt(chi2_k / k)`` (k = rank of the weight).
    """
    rk = np.maximum(lay.obs_rank, 1)
    vwv = np.einsum("mi,mij,mj->m", st.lin.res, lay.obs_weight, st.lin.res)
    raw = np.sqrt(vwv / rk)
    if trimmed:
        nrm = st.normals
        omega = _cost(
            lay,
            st.lin.res,
            lay.obs_weight * nrm.used[:, None, None],
            st.params,
            st.ground,
            nrm.valid,
        )
        dof = _redundancy_total(lay, nrm)
        if dof > 0 and omega > 0:
            return raw, float(np.sqrt(omega / dof))
    pt = lay.obs_point
    use = st.normals.valid[pt] & (lay.obs_rank > 0)
    ncomp = (
        np.bincount(pt[use], weights=lay.obs_rank[use], minlength=lay.n_points)
        + lay.ground_rank
    )
    frac = 1.0 - 3.0 / np.maximum(ncomp, 1.0)
    use &= frac[pt] > 0.05
    if not use.any():
        return raw, 1.0
    # medians of sqrt(chi2_k / k): k = 1 -> 0.6745, k = 2 -> sqrt(ln 2) = 0.8326
    med = np.where(lay.obs_rank[use] >= 2, np.sqrt(np.log(2.0)), 0.6745)
    sig = float(np.median(raw[use] / np.sqrt(frac[pt[use]]) / med))
    return raw, max(sig, np.finfo(float).tiny)


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
    lay = _layout(problem)
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
            raw, sig = _robust_scale(lay, st, trimmed=wfun is weight_exp and rnd > 0)
            rweight = wfun(raw / sig)
            active = rweight >= opt.robust_min_weight
            rweight[~active] = 0.0
            st = _gauss_newton(lay, models, st.params, st.ground, rweight, opt, times)
        st = _gauss_newton(
            lay, models, st.params, st.ground, active.astype(float), opt, times
        )
    dense = lay.n_unknowns <= opt.max_dense_unknowns
    n_snooped = 0
    stats = _statistics(lay, st, dense=dense and (opt.snooping or opt.covariance))
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
            stats = _statistics(lay, st, dense=True)
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
        residuals=back(st.lin.res),
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
