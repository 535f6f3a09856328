"""Reduced normal equations of the block adjustment, assembled block by block (seed 000 eq 5).

The observations are sorted by frame and cut into *chunks* of whole frames of about
``block_size`` observations, the frames taken in a reverse Cuthill-McKee order of the frame
graph (frames that share points are neighbours).  The Jacobians are evaluated one chunk at a
time, one model call per frame.  A point's 3x3 block ``N_gg`` and its Schur complement need all
of its observations, so rows of a point that is still observed in a later chunk wait in a
buffer until that chunk; every *group* handed to the assembly therefore holds all the
observations of its points.  The buffer holds the points that straddle the chunk boundary, a
band of the frame graph, so the working memory of an iteration is bounded by the block size
and the band, not by the number of observations.  Only arrays of a few numbers per
observation (residuals, weights, ground Jacobians) and the reduced system itself persist.

Per group everything is batched numpy: with ``N_gg^-1 = L L^T`` and ``G_i = L^T C_i``
(``C_i = J_g,i^T W_i J_p,i``) the Schur complement is

    S_ff = N_ff - sum_{i in f} G_i^T G_i - sum_{a != b in f, same point} G_a^T G_b
    S_fg =      - sum_{a in f, b in g, same point} G_a^T G_b

the first sum one GEMM per frame (rows contiguous), the pair sums one batched GEMM per group
of frame pairs of similar size.  The blocks land in a (frames + frame pairs, n, n) array whose
scatter into the compressed sparse columns of ``S`` is computed once per layout
(:mod:`geocoder.adjust.layout`, whose names are re-exported here).

References
----------
Paderes, Mikhail & Foerstner (1984), Rectification of single and multiple frames of satellite
scanner imagery using points and edges as control, eqs 3-5.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from .layout import DEFAULT_BLOCK_SIZE, Layout, layout, ranks, same_point_pairs, sum_by

__all__ = [
    "DEFAULT_BLOCK_SIZE",
    "Layout",
    "Normals",
    "assemble",
    "back_substitute",
    "cost",
    "hold_to_dem",
    "jacobian_chunks",
    "layout",
    "point_groups",
    "ranks",
    "residuals",
    "same_point_pairs",
    "sum_by",
]

_POINT_RTOL = 1e-10  # a 3x3 point block whose eigenvalue ratio is below this is singular
_GEMM_BUDGET = 1 << 16  # observation pairs gathered at once by the pair products


def _pair_products(g: np.ndarray, a: np.ndarray, b: np.ndarray, seg: np.ndarray, nseg: int) -> np.ndarray:
    """``U[s] = sum_{q: seg_q = s} g[a_q]^T g[b_q]`` for ``g`` of shape (m, 3, n), ``seg`` sorted.

    Segments are bucketed by length (powers of two); a bucket is zero-padded and multiplied
    with one batched GEMM of inner dimension ``3 x length``, so the work runs in BLAS.
    """
    n = g.shape[2]
    out = np.zeros((nseg, n, n))
    counts = np.bincount(seg, minlength=nseg)
    starts = np.cumsum(counts) - counts
    nz = np.flatnonzero(counts)
    if nz.size == 0:
        return out
    bucket = np.ceil(np.log2(counts[nz])).astype(np.int64)
    for bk in np.unique(bucket):  # a few buckets; each a handful of batched GEMMs
        segs = nz[bucket == bk]
        length = int(counts[segs].max())
        step = max(1, _GEMM_BUDGET // length)
        ar = np.arange(length)
        for j in range(0, segs.size, step):
            ss = segs[j : j + step]
            mask = ar[None, :] < counts[ss][:, None]
            pos = np.where(mask, starts[ss][:, None] + ar[None, :], -1)
            k = ss.size
            ga = g[a[pos]]
            ga[~mask] = 0.0  # padding
            gb = g[b[pos]]
            out[ss] = np.matmul(ga.reshape(k, 3 * length, n).transpose(0, 2, 1), gb.reshape(k, 3 * length, n))
    return out


def hold_to_dem(lay: Layout, ground: np.ndarray) -> None:
    """Re-linearise the DEM height constraint of ``lay.dem_idx`` at ``ground`` (in place).

    ``c(P) + g . dP = 0`` with weight ``1 / sigma^2`` is written as the ground pseudo-observation
    ``(prior - P)^T W (prior - P)`` with ``W = g g^T / sigma^2`` and ``prior = P - g c / |g|^2``:
    the same normal-equation terms, and ``c^2 / sigma^2`` in the cost.

    Parameters
    ----------
    lay : Layout
    ground : ndarray, shape (P, 3)
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
    lay.ground_rank[k] = np.where(ok, 1, ranks(lay.dem_weight0))


# --------------------------------------------------------------------------------------------
# model evaluation, streamed
# --------------------------------------------------------------------------------------------


def residuals(lay: Layout, models: Sequence[Any], params: Sequence[np.ndarray], ground: np.ndarray) -> np.ndarray:
    """Observed minus projected image coordinates, one model call per frame.

    Parameters
    ----------
    lay : Layout
    models : sequence of SensorModel
    params : sequence of ndarray
        Parameters of every frame.
    ground : ndarray, shape (P, 3)

    Returns
    -------
    ndarray, shape (M, 2)
        In the layout's observation order.
    """
    res = np.zeros((lay.obs_frame.size, 2))
    for f in range(lay.n_frames):
        s0, s1 = lay.frame_lo[f], lay.frame_hi[f]
        if s1 > s0:
            res[s0:s1] = lay.obs_xy[s0:s1] - models[f].project(params[f], ground[lay.obs_point[s0:s1]])
    return res


def jacobian_chunks(
    lay: Layout, models: Sequence[Any], params: Sequence[np.ndarray], ground: np.ndarray
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """Jacobians chunk by chunk, one model call per frame.

    Parameters
    ----------
    lay : Layout
    models : sequence of SensorModel
    params : sequence of ndarray
    ground : ndarray, shape (P, 3)

    Yields
    ------
    lo, hi : int
        The chunk's observations ``lo:hi``.
    jp : ndarray, shape (hi - lo, 2, nmax)
        Derivatives by the free parameters (zero padded).
    jg : ndarray, shape (hi - lo, 2, 3)
        Derivatives by the ground coordinates.
    """
    for c in range(lay.n_chunks):
        lo, hi = int(lay.chunk_lo[c]), int(lay.chunk_lo[c + 1])
        jp = np.zeros((hi - lo, 2, lay.nmax))
        jg = np.empty((hi - lo, 2, 3))
        for f in lay.chunk_frames[c]:
            s0, s1 = lay.frame_lo[f], lay.frame_hi[f]
            if s1 == s0:
                continue
            a, b = models[f].jacobians(params[f], ground[lay.obs_point[s0:s1]])
            fi = lay.free[f]
            jp[s0 - lo : s1 - lo, :, : fi.size] = np.asarray(a)[:, :, fi]
            jg[s0 - lo : s1 - lo] = b
        yield lo, hi, jp, jg


def point_groups(
    lay: Layout, chunks: Iterator[tuple[int, int, np.ndarray, np.ndarray]]
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Regroup chunk rows so that every group holds all the observations of its points.

    Rows of points still observed in a later chunk wait in a buffer until that chunk.

    Parameters
    ----------
    lay : Layout
    chunks : iterator
        As yielded by :func:`jacobian_chunks`, in chunk order.

    Yields
    ------
    obs : ndarray of int
        The group's observations, ascending (so each frame's rows are contiguous).
    jp, jg : ndarray
        Their Jacobians.
    """
    pending: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for c, (lo, hi, jp, jg) in enumerate(chunks):
        done = lay.obs_done[lo:hi]
        later = done > c
        waiting = pending.pop(c, [])
        if not later.any() and not waiting:
            yield np.arange(lo, hi), jp, jg  # no copy
            continue
        rows = np.flatnonzero(later)
        target = done[rows]
        for t in np.unique(target):  # at most one entry per later chunk
            r = rows[target == t]
            pending.setdefault(int(t), []).append((lo + r, jp[r], jg[r]))
        now = np.flatnonzero(~later)
        parts = [*waiting, (lo + now, jp[now], jg[now])]
        del jp, jg
        yield tuple(np.concatenate([p[k] for p in parts]) for k in range(3))  # type: ignore[misc]


# --------------------------------------------------------------------------------------------
# normal equations
# --------------------------------------------------------------------------------------------


@dataclass
class Normals:
    """Reduced normal equations ``S dp = r`` and what the back-substitution needs.

    Attributes
    ----------
    w : ndarray, shape (M, 2, 2)
        Effective weights (0 for unused observations).
    used : ndarray of bool, shape (M,)
    valid : ndarray of bool, shape (P,)
        Points with a regular 3x3 block.
    ninv : ndarray, shape (P, 3, 3)
        ``N_gg^-1`` (zeros for invalid points).
    tg : ndarray, shape (P, 3)
        Right-hand side of the points.
    jg : ndarray, shape (M, 2, 3)
        Ground Jacobians.
    s : scipy.sparse.csc_matrix
    r : ndarray, shape (n_unknowns,)
    ngg_diag : ndarray, shape (P, 3)
    frame_pairs : ndarray, shape (K, 2)
        Frame pairs coupled through used observations.
    jp_chunks : list of (int, int, ndarray) or None
        ``(lo, hi, jp)`` of every chunk: the parameter Jacobians, kept when they fit in the
        ``keep_jacobians`` budget of :func:`assemble`; None when they must be re-evaluated.
    """

    w: np.ndarray
    used: np.ndarray
    valid: np.ndarray
    ninv: np.ndarray
    tg: np.ndarray
    jg: np.ndarray
    s: sp.csc_matrix
    r: np.ndarray
    ngg_diag: np.ndarray
    frame_pairs: np.ndarray
    jp_chunks: list[tuple[int, int, np.ndarray]] | None = None

    def jacobian_source(
        self, lay: Layout, models: Sequence[Any], params: Sequence[np.ndarray], ground: np.ndarray
    ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        """The Jacobians at the point of linearisation, chunk by chunk (kept or re-evaluated).

        Parameters
        ----------
        lay : Layout
        models : sequence of SensorModel
        params : sequence of ndarray
        ground : ndarray, shape (P, 3)
            The point of linearisation.

        Returns
        -------
        iterator
            As :func:`jacobian_chunks`.
        """
        if self.jp_chunks is None:
            return jacobian_chunks(lay, models, params, ground)
        return iter([(lo, hi, jp, self.jg[lo:hi]) for lo, hi, jp in self.jp_chunks])


def _frame_runs(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame, start and end of each run of equal values in ``frame``."""
    if frame.size == 0:
        e = np.zeros(0, np.int64)
        return e, e, e
    start = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    end = np.r_[start[1:], frame.size]
    return frame[start], start, end


def assemble(
    lay: Layout,
    models: Sequence[Any],
    params: Sequence[np.ndarray],
    ground: np.ndarray,
    res: np.ndarray,
    factor: np.ndarray,
    *,
    keep_jacobians: int = 0,
) -> Normals:
    """Reduced normal equations over the frame parameters, points eliminated (seed eq 5).

    Streams the observations chunk by chunk (:func:`jacobian_chunks`, :func:`point_groups`);
    see the module docstring for the algebra.

    Parameters
    ----------
    lay : Layout
    models : sequence of SensorModel
    params : sequence of ndarray
    ground : ndarray, shape (P, 3)
    res : ndarray, shape (M, 2)
        Residuals at ``params``, ``ground`` (:func:`residuals`).
    factor : ndarray, shape (M,)
        Weight factors of the observations (robust weights; 0 = unused).
    keep_jacobians : int
        Keep the parameter Jacobians for the back-substitution when they take at most this
        many bytes (always with a single chunk: they are in memory anyway); otherwise they are
        evaluated again.

    Returns
    -------
    Normals
    """
    nf, npt, n = lay.n_frames, lay.n_points, lay.nmax
    m = lay.obs_frame.size
    k_pairs = lay.pair_key.size
    # blocks: frames, frame pairs, then the pairs of distinct observations within one frame
    blocks = np.zeros((2 * nf + k_pairs, n, n))
    touched = np.zeros(k_pairs, bool)
    tp = np.zeros((nf, n))
    w_all = np.zeros((m, 2, 2))
    jg_all = np.zeros((m, 2, 3))
    used_all = np.zeros(m, bool)
    valid = np.zeros(npt, bool)
    ninv = np.zeros((npt, 3, 3))
    tg = np.zeros((npt, 3))
    ngg_diag = np.zeros((npt, 3))
    keep = lay.n_chunks == 1 or m * 2 * n * 8 <= keep_jacobians
    kept: list[tuple[int, int, np.ndarray]] = []

    def chunks() -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        for lo, hi, jp, jg in jacobian_chunks(lay, models, params, ground):
            if keep:
                kept.append((lo, hi, jp))
            yield lo, hi, jp, jg

    for obs, jp, jg in point_groups(lay, chunks()):
        pt, fr = lay.obs_point[obs], lay.obs_frame[obs]
        upt, loc = np.unique(pt, return_inverse=True)
        loc = loc.ravel()
        w = lay.obs_weight[obs] * factor[obs, None, None]
        wjg = np.matmul(w, jg)
        ngg = sum_by(loc, np.matmul(jg.transpose(0, 2, 1), wjg), upt.size) + lay.ground_weight[upt]
        ev = np.linalg.eigvalsh(ngg)
        ok = (ev[:, -1] > 0) & (ev[:, 0] > _POINT_RTOL * ev[:, -1])
        used = (factor[obs] > 0) & ok[loc] & (lay.obs_rank[obs] > 0)
        if not used.all():
            w = w * used[:, None, None]
            wjg = wjg * used[:, None, None]
        ni = np.zeros((upt.size, 3, 3))
        ni[ok] = np.linalg.inv(ngg[ok])
        t = sum_by(loc, np.einsum("mij,mi->mj", wjg, res[obs]), upt.size)
        t += np.einsum("pij,pj->pi", lay.ground_weight[upt], lay.ground_prior[upt] - ground[upt])
        t[~ok] = 0.0
        # only the used rows enter the products (unused ones may hold NaN Jacobians, and an
        # extra zero row would change the rounding of the frame GEMMs)
        u_rows = slice(None) if used.all() else np.flatnonzero(used)
        jpu, wu, locu, fru = jp[u_rows], w[u_rows], loc[u_rows], fr[u_rows]
        # G_i = L^T C_i with N_gg^-1 = L L^T; h = L^T t_g
        lt = np.zeros((upt.size, 3, 3))
        lt[ok] = np.linalg.cholesky(ni[ok]).transpose(0, 2, 1)
        g = np.matmul(np.matmul(lt[locu], wjg[u_rows].transpose(0, 2, 1)), jpu)  # (m, 3, n)
        h = np.einsum("pij,pj->pi", lt, t)[locu]  # (m, 3)
        wjp = np.matmul(wu, jpu)
        wres = np.einsum("mij,mj->mi", wu, res[obs[u_rows]])
        for f, s0, s1 in zip(*_frame_runs(fru)):  # one GEMM per frame (its rows are contiguous)
            jf, gf = jpu[s0:s1].reshape(-1, n), g[s0:s1].reshape(-1, n)
            blocks[f] += jf.T @ wjp[s0:s1].reshape(-1, n) - gf.T @ gf
            tp[f] += jf.T @ wres[s0:s1].ravel() - gf.T @ h[s0:s1].ravel()
        del wjp, wres, jpu
        # pairs of distinct observations of one point
        a, b = same_point_pairs(np.arange(locu.size), locu, ordered=False)
        a, b = a[a != b], b[a != b]
        fa, fb = fru[a], fru[b]
        swap = fa > fb
        a, b = np.where(swap, b, a), np.where(swap, a, b)
        fa, fb = np.minimum(fa, fb), np.maximum(fa, fb)
        k = np.searchsorted(lay.pair_key, fa * nf + fb)
        blk = np.where(fa == fb, nf + k_pairs + fa, nf + k)
        o = np.argsort(blk, kind="stable")
        ublk, seg = np.unique(blk[o], return_inverse=True)
        blocks[ublk] -= _pair_products(g, a[o], b[o], seg.ravel(), ublk.size)
        touched[ublk[ublk < nf + k_pairs] - nf] = True
        del g
        # keep what the back-substitution and the statistics need
        w_all[obs], jg_all[obs], used_all[obs] = w, jg, used
        valid[upt], ninv[upt], tg[upt] = ok, ni, t
        ngg_diag[upt] = np.diagonal(ngg, axis1=1, axis2=2)
    same = blocks[nf + k_pairs :]  # holds -U of the pairs within a frame: S_ff gets -(U + U^T)
    blocks[:nf] += same + same.transpose(0, 2, 1)
    for f in range(nf):  # priors, O(frames)
        if lay.prior_w[f] is not None:
            kf = lay.free[f].size
            blocks[f, :kf, :kf] += lay.prior_w[f]
            tp[f, :kf] += lay.prior_w[f] @ (lay.prior_val[f] - params[f])[lay.free[f]]
    flat = blocks[: nf + k_pairs].reshape(-1)
    s = sp.csc_matrix((flat[lay.s_src], lay.s_indices, lay.s_indptr), shape=(lay.n_unknowns,) * 2)
    r = np.zeros(lay.n_unknowns)
    sel = lay.idx >= 0
    r[lay.idx[sel]] = tp[sel]
    key = lay.pair_key[touched]
    pairs = np.c_[key // max(nf, 1), key % max(nf, 1)]
    return Normals(w_all, used_all, valid, ninv, tg, jg_all, s, r, ngg_diag, pairs, kept if keep else None)


def back_substitute(
    lay: Layout,
    models: Sequence[Any],
    params: Sequence[np.ndarray],
    ground: np.ndarray,
    nrm: Normals,
    dpad: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground corrections ``dg = N_gg^-1 (t_g - N_gf dp)`` for frame corrections ``dp``.

    The parameter Jacobians are re-evaluated chunk by chunk unless ``nrm`` kept them
    (:meth:`Normals.jacobian_source`).

    Parameters
    ----------
    lay : Layout
    models : sequence of SensorModel
    params : sequence of ndarray
    ground : ndarray, shape (P, 3)
        The point of linearisation of ``nrm``.
    nrm : Normals
    dpad : ndarray, shape (F, nmax)
        Frame corrections (free parameters, zero padded).

    Returns
    -------
    u : ndarray, shape (M, 2)
        ``J_p dp`` of every observation.
    dg : ndarray, shape (P, 3)
    """
    u = np.empty((lay.obs_frame.size, 2))
    for lo, hi, jp, _ in nrm.jacobian_source(lay, models, params, ground):
        u[lo:hi] = np.einsum("min,mn->mi", jp, dpad[lay.obs_frame[lo:hi]])
    u[~nrm.used] = 0.0  # unused rows may hold NaN Jacobians
    wjg = np.matmul(nrm.w, nrm.jg)
    back = sum_by(lay.obs_point, np.einsum("mij,mi->mj", wjg, u), lay.n_points)
    return u, np.einsum("pij,pj->pi", nrm.ninv, nrm.tg - back)


def cost(
    lay: Layout,
    res: np.ndarray,
    w: np.ndarray,
    params: Sequence[np.ndarray],
    ground: np.ndarray,
    valid: np.ndarray,
) -> float:
    """Weighted square sum of the observation and pseudo-observation residuals.

    Parameters
    ----------
    lay : Layout
    res : ndarray, shape (M, 2)
    w : ndarray, shape (M, 2, 2)
    params : sequence of ndarray
    ground : ndarray, shape (P, 3)
    valid : ndarray of bool, shape (P,)
        Points whose prior enters.

    Returns
    -------
    float
    """
    c = float(np.einsum("mi,mij,mj->", res, w, res))
    for f in range(lay.n_frames):
        if lay.prior_w[f] is not None:
            d = (lay.prior_val[f] - params[f])[lay.free[f]]
            c += float(d @ lay.prior_w[f] @ d)
    d = lay.ground_prior - ground
    c += float(np.einsum("pi,pij,pj->", d[valid], lay.ground_weight[valid], d[valid]))
    return c
