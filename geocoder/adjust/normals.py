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
scatter into the compressed sparse columns of ``S`` is computed once per layout.

References
----------
Paderes, Mikhail & Foerstner (1984), Rectification of single and multiple frames of satellite
scanner imagery using points and edges as control, eqs 3-5.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .dem import DEM

if TYPE_CHECKING:  # pragma: no cover - typing only
    from .solver import Problem

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

DEFAULT_BLOCK_SIZE = 1 << 17  # observations per chunk (~0.4 GB of work arrays at 32 parameters)
_RANK_RTOL = 1e-9  # eigenvalues below this fraction of the largest count as zero (weight ranks)
_POINT_RTOL = 1e-10  # a 3x3 point block whose eigenvalue ratio is below this is singular
_GEMM_BUDGET = 1 << 16  # observation pairs gathered at once by the pair products


# --------------------------------------------------------------------------------------------
# small vectorised helpers
# --------------------------------------------------------------------------------------------


def sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum the rows of ``values`` into ``n`` bins.

    Parameters
    ----------
    index : ndarray of int, shape (m,)
        Bin of every row.
    values : ndarray, shape (m, ...)
    n : int
        Number of bins.

    Returns
    -------
    ndarray, shape (n, ...)
    """
    m = index.shape[0]
    flat = values.reshape(m, -1)
    agg = sp.csr_matrix((np.ones(m), (index, np.arange(m))), shape=(n, m))
    return np.asarray(agg @ flat).reshape((n,) + values.shape[1:])


def ranks(w: np.ndarray) -> np.ndarray:
    """Numerical ranks of a stack of symmetric positive semi-definite matrices.

    Parameters
    ----------
    w : ndarray, shape (k, d, d)

    Returns
    -------
    ndarray of int, shape (k,)
    """
    if w.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    ev = np.linalg.eigvalsh(w)
    top = ev[:, -1:]
    return np.sum(ev > _RANK_RTOL * np.maximum(top, 0.0), axis=1) * (top[:, 0] > 0)


def same_point_pairs(obs: np.ndarray, point: np.ndarray, *, ordered: bool) -> tuple[np.ndarray, np.ndarray]:
    """All pairs ``(a, b)`` of the observations ``obs`` that share a point, ``a == b`` included.

    Parameters
    ----------
    obs : ndarray of int
        Observation indices (into ``point``).
    point : ndarray of int
        Point of every observation.
    ordered : bool
        List both ``(a, b)`` and ``(b, a)``, grouped by ``a``; otherwise each unordered pair once.

    Returns
    -------
    a, b : ndarray of int
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


# --------------------------------------------------------------------------------------------
# layout
# --------------------------------------------------------------------------------------------


@dataclass
class Layout:
    """Index structure of a problem, fixed for the whole adjustment (internal order of rows).

    Observations are sorted by the processing position of their frame; ``order[i]`` is the
    problem's index of internal observation ``i``.  Chunk ``c`` holds observations
    ``chunk_lo[c]:chunk_lo[c + 1]`` (whole frames ``chunk_frames[c]``); ``obs_done[i]`` is the
    chunk after which the point of observation ``i`` has been seen completely.  ``pair_key``
    lists the frame pairs ``fa * n_frames + fb`` (``fa < fb``) sharing a point, sorted; block
    ``n_frames + k`` of the block array is pair ``k``.  ``s_src``, ``s_indices`` and
    ``s_indptr`` scatter the flattened block array into ``S`` in CSC form.
    """

    n_frames: int
    n_points: int
    order: np.ndarray
    frame_lo: np.ndarray
    frame_hi: np.ndarray
    obs_frame: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_weight: np.ndarray
    obs_rank: np.ndarray
    free: list[np.ndarray]
    nmax: int
    idx: np.ndarray  # (F, nmax) unknown index of each free parameter, -1 = padding
    n_unknowns: int
    prior_w: list[np.ndarray | None]
    prior_val: list[np.ndarray]
    ground_prior: np.ndarray
    ground_weight: np.ndarray
    ground_rank: np.ndarray
    prior_rank: int
    chunk_lo: np.ndarray
    chunk_frames: list[np.ndarray]
    obs_done: np.ndarray
    pair_key: np.ndarray
    s_src: np.ndarray
    s_indices: np.ndarray
    s_indptr: np.ndarray
    dem: DEM | None = None
    dem_idx: np.ndarray | None = None
    dem_prior0: np.ndarray | None = None
    dem_weight0: np.ndarray | None = None

    @property
    def n_chunks(self) -> int:
        """Number of chunks."""
        return len(self.chunk_frames)


def _frame_pair_keys(obs_frame: np.ndarray, obs_point: np.ndarray, n_frames: int) -> np.ndarray:
    """Sorted unique ``fa * n_frames + fb`` (``fa < fb``) of the frame pairs sharing a point."""
    a, b = same_point_pairs(np.arange(obs_frame.size), obs_point, ordered=False)
    fa, fb = obs_frame[a], obs_frame[b]
    keep = fa != fb
    fa, fb = fa[keep], fb[keep]
    return np.unique(np.minimum(fa, fb) * n_frames + np.maximum(fa, fb))


def _csc_scatter(idx: np.ndarray, pair_key: np.ndarray, n_unknowns: int) -> tuple[np.ndarray, ...]:
    """Positions in the flattened block array of the CSC entries of ``S``, and its structure."""
    nf, n = idx.shape
    fa, fb = pair_key // max(nf, 1), pair_key % max(nf, 1)
    k = pair_key.size
    rows = np.concatenate([
        np.broadcast_to(idx[:, :, None], (nf, n, n)).ravel(),
        np.broadcast_to(idx[fa][:, :, None], (k, n, n)).ravel(),
        np.broadcast_to(idx[fb][:, :, None], (k, n, n)).ravel(),
    ])
    cols = np.concatenate([
        np.broadcast_to(idx[:, None, :], (nf, n, n)).ravel(),
        np.broadcast_to(idx[fb][:, None, :], (k, n, n)).ravel(),
        np.broadcast_to(idx[fa][:, None, :], (k, n, n)).ravel(),
    ])
    off = nf * n * n
    src = np.concatenate([
        np.arange(off + k * n * n),
        (off + np.arange(k * n * n).reshape(k, n, n).transpose(0, 2, 1)).ravel(),  # transposed blocks
    ])
    keep = (rows >= 0) & (cols >= 0)
    # each (row, col) occurs once, so the CSC conversion only permutes: carry the source position
    pattern = sp.coo_matrix(
        (src[keep] + 1.0, (rows[keep], cols[keep])), shape=(n_unknowns, n_unknowns)
    ).tocsc()  # + 1: no stored value is zero, so none can be dropped
    return pattern.data.astype(np.int64) - 1, pattern.indices, pattern.indptr


def layout(problem: Problem, block_size: int | None = DEFAULT_BLOCK_SIZE) -> Layout:
    """Index structure of a problem: observation order, chunks, frame pairs, structure of ``S``.

    Parameters
    ----------
    problem : Problem
        The adjustment problem (:class:`geocoder.adjust.solver.Problem`).
    block_size : int or None
        Observations per chunk (whole frames; a frame with more is a chunk of its own).  None
        puts all observations in one chunk.

    Returns
    -------
    Layout
    """
    frames = problem.frames
    nf = len(frames)
    npt = int(np.asarray(problem.ground).shape[0])
    obs_frame = np.asarray(problem.obs_frame, dtype=np.int64)
    obs_point = np.asarray(problem.obs_point, dtype=np.int64)
    pair_key = _frame_pair_keys(obs_frame, obs_point, nf)
    # processing order of the frames: reverse Cuthill-McKee keeps the points that straddle a
    # chunk boundary, and so the buffer, in a band of the frame graph
    adj = sp.coo_matrix((np.ones(pair_key.size), (pair_key // max(nf, 1), pair_key % max(nf, 1))), shape=(nf, nf))
    seq = reverse_cuthill_mckee((adj + adj.T).tocsr(), symmetric_mode=True) if nf else np.zeros(0, np.int64)
    pos = np.empty(nf, dtype=np.int64)
    pos[seq] = np.arange(nf)
    order = np.argsort(pos[obs_frame], kind="stable")
    of, op = obs_frame[order], obs_point[order]
    starts = np.searchsorted(pos[of], np.arange(nf + 1))  # by processing position
    frame_lo, frame_hi = np.empty(nf, np.int64), np.empty(nf, np.int64)
    frame_lo[seq], frame_hi[seq] = starts[:-1], starts[1:]
    # chunks of whole frames
    cap = max(1, int(of.size if block_size is None else block_size))
    counts = np.diff(starts)
    chunk_of_pos = np.zeros(nf, np.int64)
    if nf:
        chunk_of_pos = (np.cumsum(counts) - counts) // cap  # start of each frame decides its chunk
        chunk_of_pos = np.unique(chunk_of_pos, return_inverse=True)[1].ravel()
    n_chunks = int(chunk_of_pos.max()) + 1 if nf else 0
    chunk_frames = [seq[chunk_of_pos == c] for c in range(n_chunks)]
    chunk_lo = np.searchsorted(chunk_of_pos, np.arange(n_chunks + 1))
    chunk_lo = starts[chunk_lo]
    obs_chunk = chunk_of_pos[pos[of]]
    done_pt = np.zeros(npt, np.int64)
    np.maximum.at(done_pt, op, obs_chunk)
    # frame parameters
    free, prior_w, prior_val = [], [], []
    prior_rank = 0
    for fr in frames:  # O(frames)
        p = np.asarray(fr.params, dtype=np.float64)
        fmask = np.ones(p.size, bool) if fr.free is None else np.asarray(fr.free, bool)
        fi = np.flatnonzero(fmask)
        free.append(fi)
        prior_val.append(p.copy() if fr.prior_value is None else np.asarray(fr.prior_value, np.float64))
        if fr.prior_weight is None:
            prior_w.append(None)
        else:
            wf = np.asarray(fr.prior_weight, np.float64)[np.ix_(fi, fi)]
            prior_w.append(wf)
            prior_rank += int(ranks(wf[None])[0]) if fi.size else 0
    nfree = np.array([f.size for f in free], dtype=np.int64)
    nmax = int(nfree.max()) if nf else 0
    offs = np.cumsum(nfree) - nfree
    ar = np.arange(nmax)
    idx = np.where(ar[None, :] < nfree[:, None], offs[:, None] + ar[None, :], -1)
    n_unknowns = int(nfree.sum())
    s_src, s_indices, s_indptr = _csc_scatter(idx, pair_key, n_unknowns)
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
    return Layout(
        n_frames=nf, n_points=npt, order=order, frame_lo=frame_lo, frame_hi=frame_hi,
        obs_frame=of, obs_point=op, obs_xy=np.asarray(problem.obs_xy, np.float64)[order],
        obs_weight=ow, obs_rank=ranks(ow), free=free, nmax=nmax, idx=idx, n_unknowns=n_unknowns,
        prior_w=prior_w, prior_val=prior_val, ground_prior=gp, ground_weight=gw,
        ground_rank=ranks(gw), prior_rank=prior_rank, chunk_lo=chunk_lo, chunk_frames=chunk_frames,
        obs_done=done_pt[op], pair_key=pair_key, s_src=s_src, s_indices=s_indices, s_indptr=s_indptr,
        dem=problem.dem, dem_idx=dem_idx,
        dem_prior0=None if dem_idx is None else gp[dem_idx].copy(),
        dem_weight0=None if dem_idx is None else gw[dem_idx].copy(),
    )


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
