"""The index structure of a block adjustment, fixed for all its iterations (seed 000 sec. 2.4).

:func:`layout` sorts the observations by the processing position of their frame (a reverse
Cuthill-McKee order of the frame graph: frames that share points are neighbours), cuts them
into chunks of whole frames of about ``block_size`` observations, lists the frame pairs that
share a point and precomputes the scatter of the reduced normal matrix's blocks into
compressed sparse columns.  Also the small vectorised helpers the assembly
(:mod:`geocoder.adjust.normals`) and the statistics share: :func:`sum_by`, :func:`ranks`,
:func:`same_point_pairs`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .dem import DEM

if TYPE_CHECKING:  # pragma: no cover - typing only
    from .problem import Problem

__all__ = ["DEFAULT_BLOCK_SIZE", "Layout", "layout", "ranks", "same_point_pairs", "sum_by"]

DEFAULT_BLOCK_SIZE = 1 << 17  # observations per chunk (~0.4 GB of work arrays at 32 parameters)
_RANK_RTOL = 1e-9  # eigenvalues below this fraction of the largest count as zero (weight ranks)


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
