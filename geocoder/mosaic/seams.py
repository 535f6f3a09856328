"""Seamlines of a mosaic: a coarse "which scene" label map, cut along least-cost paths through the overlaps.

Pure numpy/scipy: no dask, no I/O. The mosaic decides its seams once, on a coarse grid of the
output (cells of ``factor x factor`` output pixels, the scale of its overview levels), and
every output tile then reads the window of that label map it needs:

1. :func:`centre_labels`: every coarse cell goes to the covering scene that sees it nearest
   its centre (normalised Chebyshev distance, :func:`geocoder.mosaic.compose.centre_score`):
   the seams of the ``"centre"`` rule, as a start.
2. :func:`cut_pair`, for every pair of overlapping scenes whose regions touch: a corridor of
   ``width`` cells either side of their common boundary, inside the cells both scenes cover
   entirely, is cut again by a minimum s-t cut (the dual of a least-cost path between the
   two ends of the seam) on the 4-neighbour grid of the corridor. The cells outside the
   corridor that belong to the first scene are the source, those of the second the sink;
   where the corridor meets a third scene or the edge of the overlap there is no terminal,
   so the cut ends there freely. Crossing between two cells costs the sum of their costs,
   ``1 + gain * min(|v_i - v_j| / s, cap) + pull * d / width``: the absolute grey difference
   of the two (balanced) scenes in a cell over its robust scale ``s`` in the corridor, plus
   one so that, among equally good cuts, the shortest wins, plus a pull towards the centre
   rule's seam (``d`` cells away), which keeps each pixel in the scene that sees it least
   distorted where the grey values do not say otherwise. The seam thus runs where the scenes agree
   (around a car, a cloud, a building that leans differently in each) and through smooth
   areas, where a residual misregistration is not seen.
3. :func:`label_weights` in each output tile: the label map upsampled (nearest) to the
   tile plus a halo, and every scene weighted by its signed distance from its region's
   boundary, linearly over ``feather`` output pixels. The distances are exact up to the
   halo, so the result does not depend on the tiling.

The cut uses :func:`scipy.sparse.csgraph.maximum_flow` (Dinic's algorithm, integer capacities)
and the residual graph's reachable set; a corridor is a few cells wide, so a pair's graph is
small (its length times ``2 width + 1`` cells) and the pass over all pairs is cheap next to the
resampling. Memory on the node that cuts grows with the coarse mosaic (``1 / factor**2`` of it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

from .compose import NO_SOURCE

__all__ = ["CoarseScene", "centre_labels", "cut_pair", "grid_min_cut", "label_weights", "least_cost_labels",
           "seam_pairs"]


@dataclass
class CoarseScene:
    """One scene on the coarse grid of the mosaic, over its bounding box of cells.

    Attributes
    ----------
    row0, col0 : int
        The box's first cell (coarse row and column of the mosaic).
    value : ndarray, shape (h, w), float32
        The balanced scene's mean grey value (all bands) over each cell's samples; NaN where
        any sample has no data.
    score : ndarray, shape (h, w)
        :func:`~geocoder.mosaic.compose.centre_score` of each cell's centre (NaN: not covered).
    full : ndarray of bool, shape (h, w)
        Every sample of the cell lies in the scene and has data.
    """

    row0: int
    col0: int
    value: np.ndarray
    score: np.ndarray
    full: np.ndarray

    @property
    def box(self) -> tuple[int, int, int, int]:
        """``row0, row1, col0, col1`` of the scene's cells."""
        h, w = self.value.shape
        return self.row0, self.row0 + h, self.col0, self.col0 + w


def centre_labels(shape: tuple[int, int], scenes: list[CoarseScene]) -> np.ndarray:
    """Coarse label map of the centre rule: each cell from the scene that sees it nearest its centre.

    Cells that a scene covers entirely are preferred to cells it covers in part (so that a
    label seldom points at pixels without data).

    Parameters
    ----------
    shape : (rows, cols)
        The coarse grid.
    scenes : list of CoarseScene

    Returns
    -------
    ndarray, shape ``shape``, uint16
        Scene index per cell, :data:`~geocoder.mosaic.compose.NO_SOURCE` where none covers.
    """
    label = np.full(shape, NO_SOURCE, dtype=np.uint16)
    best = np.full(shape, np.inf)
    for k, s in enumerate(scenes):
        r0, r1, c0, c1 = s.box
        a0, a1, b0, b1 = max(r0, 0), min(r1, shape[0]), max(c0, 0), min(c1, shape[1])
        if a0 >= a1 or b0 >= b1:
            continue
        sl = (slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0))
        covered = np.isfinite(s.score[sl]) & np.isfinite(s.value[sl])
        # a partly covered cell ranks behind every entirely covered one
        rank = np.where(covered, s.score[sl] + np.where(s.full[sl], 0.0, 1e3), np.inf)
        win = rank < best[a0:a1, b0:b1]
        best[a0:a1, b0:b1] = np.where(win, rank, best[a0:a1, b0:b1])
        label[a0:a1, b0:b1] = np.where(win, np.uint16(k), label[a0:a1, b0:b1])
    return label


def grid_min_cut(cost: np.ndarray, active: np.ndarray, source: np.ndarray, sink: np.ndarray) -> np.ndarray:
    """Minimum s-t cut of a 4-neighbour grid whose edges cost the sum of their cells' costs.

    Parameters
    ----------
    cost : ndarray, shape (h, w), int
        Cost of every cell (>= 1 where active).
    active : ndarray of bool, shape (h, w)
        The cells free to go either way.
    source, sink : ndarray of bool, shape (h, w)
        Cells tied to the source and to the sink (disjoint, not active). Edges between two
        terminal cells are left out: the cut runs through the active cells only.

    Returns
    -------
    ndarray of bool, shape (h, w)
        True for the active cells on the source's side of the cut.
    """
    h, w = cost.shape
    nodes = active | source | sink
    ids = np.full((h, w), -1, dtype=np.int64)
    n = int(nodes.sum())
    ids[nodes] = np.arange(n)
    s_node, t_node = n, n + 1
    rows, cols, caps = [], [], []
    for da, db in ((0, 1), (1, 0)):
        a = (slice(0, h - da), slice(0, w - db))
        b = (slice(da, h), slice(db, w))
        edge = nodes[a] & nodes[b] & (active[a] | active[b])
        ua, ub = ids[a][edge], ids[b][edge]
        c = (cost[a][edge] + cost[b][edge]).astype(np.int64)
        rows += [ua, ub]
        cols += [ub, ua]
        caps += [c, c]
    finite = int(sum(int(c.sum()) for c in caps)) + 1
    big = min(finite, 2**30)
    rows += [np.full(int(source.sum()), s_node), ids[sink]]
    cols += [ids[source], np.full(int(sink.sum()), t_node)]
    caps += [np.full(int(source.sum()), big), np.full(int(sink.sum()), big)]
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(caps)
    graph = sp.csr_array((v.astype(np.int32), (r, c)), shape=(n + 2, n + 2))
    graph.sum_duplicates()
    flow = maximum_flow(graph, s_node, t_node, method="dinic").flow
    residual = (graph - flow).tocsr()
    residual.data = np.where(residual.data > 0, 1, 0).astype(np.int32)
    residual.eliminate_zeros()
    reached = breadth_first_order(residual, s_node, directed=True, return_predecessors=False)
    side = np.zeros(n + 2, dtype=bool)
    side[reached] = True
    out = np.zeros((h, w), dtype=bool)
    out[nodes] = side[:n][ids[nodes]]
    return out & active


def _four_neighbours(mask: np.ndarray) -> np.ndarray:
    """Cells 4-adjacent to ``mask`` (not in it)."""
    grown = ndimage.binary_dilation(mask, structure=ndimage.generate_binary_structure(2, 1))
    return grown & ~mask


def cut_pair(label: np.ndarray, i: int, j: int, si: CoarseScene, sj: CoarseScene, *, width: float,
             gain: float = 4.0, cap: float = 20.0, pull: float = 2.0) -> int:
    """Move the seam between scenes ``i`` and ``j`` onto the least-cost cut of their corridor, in place.

    Parameters
    ----------
    label : ndarray, shape (H, W), uint16
        The coarse label map (changed in place).
    i, j : int
        The two scenes' indices in ``label``.
    si, sj : CoarseScene
        The two scenes on the coarse grid.
    width : float
        Half-width of the corridor around the current seam, in cells.
    gain, cap, pull : float
        Cost of a cell: ``1 + gain * min(|v_i - v_j| / scale, cap) + pull * d / width``, ``d``
        its distance from the current seam: where the scenes agree equally well, the seam
        stays near the centre rule's (the scenes' least distorted parts).

    Returns
    -------
    int
        Number of cells whose label changed.
    """
    H, W = label.shape
    r0, r1 = max(max(si.row0, sj.row0) - 1, 0), min(min(si.box[1], sj.box[1]) + 1, H)
    c0, c1 = max(max(si.col0, sj.col0) - 1, 0), min(min(si.box[3], sj.box[3]) + 1, W)
    if r0 >= r1 or c0 >= c1:
        return 0

    def window(s: CoarseScene, a: np.ndarray, fill) -> np.ndarray:
        out = np.full((r1 - r0, c1 - c0), fill, dtype=a.dtype)
        a0, a1, b0, b1 = max(r0, s.row0), min(r1, s.box[1]), max(c0, s.col0), min(c1, s.box[3])
        if a0 < a1 and b0 < b1:
            out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = a[a0 - s.row0 : a1 - s.row0, b0 - s.col0 : b1 - s.col0]
        return out

    lab = label[r0:r1, c0:c1]
    is_i, is_j = lab == i, lab == j
    boundary = (is_i & _four_neighbours(is_j)) | (is_j & _four_neighbours(is_i))
    if not boundary.any():
        return 0
    vi, vj = window(si, si.value, np.float32(np.nan)), window(sj, sj.value, np.float32(np.nan))
    both = window(si, si.full, False) & window(sj, sj.full, False) & np.isfinite(vi) & np.isfinite(vj)
    dist = ndimage.distance_transform_edt(~boundary)
    near = dist <= width
    corridor = near & both & (is_i | is_j)
    if not corridor.any():
        return 0
    ring = _four_neighbours(corridor)
    source, sink = ring & is_i, ring & is_j
    if not source.any() or not sink.any():
        return 0
    # a cell costs the largest difference around it: the cut keeps a cell away from an object
    # (whose feathered edge would otherwise reach across the seam)
    diff = ndimage.maximum_filter(np.nan_to_num(np.abs(vi - vj), nan=0.0), size=3)
    scale = 1.4826 * float(np.median(diff[corridor]))
    if not scale > 0:
        scale = float(np.mean(diff[corridor])) or 1.0
    cost = 1 + np.rint(gain * np.minimum(np.nan_to_num(diff / scale, nan=cap), cap)
                       + pull * np.minimum(dist, width) / max(width, 1e-9)).astype(np.int64)
    side = grid_min_cut(cost, corridor, source, sink)
    new = np.where(corridor, np.where(side, np.uint16(i), np.uint16(j)), lab)
    changed = int(np.count_nonzero(new != lab))
    label[r0:r1, c0:c1] = new
    return changed


def least_cost_labels(shape: tuple[int, int], scenes: list[CoarseScene], pairs: list[tuple[int, int]], *,
                      width: float, gain: float = 4.0, passes: int = 3) -> np.ndarray:
    """Coarse label map with least-cost seams: :func:`centre_labels`, then :func:`cut_pair` for every pair.

    Cutting one pair moves its seam, and so where the seams of its scenes with their other
    neighbours run (where three scenes meet, a seam that was ``i | k`` may now be ``i | j``).
    The pairs are therefore cut again, up to ``passes`` times, while a pass still changes
    cells (a cut of a seam that is already least-cost changes nothing).

    Parameters
    ----------
    shape : (rows, cols)
        The coarse grid.
    scenes : list of CoarseScene
    pairs : list of (i, j)
        The overlapping pairs (any order; each is cut once, in the order given).
    width : float
        Half-width of each pair's corridor, in cells.
    gain : float
        Weight of the grey difference in a cell's cost (:func:`cut_pair`).
    passes : int
        Most passes over the pairs.

    Returns
    -------
    ndarray, shape ``shape``, uint16
    """
    label = centre_labels(shape, scenes)
    for _ in range(passes):
        changed = sum(cut_pair(label, i, j, scenes[i], scenes[j], width=width, gain=gain) for i, j in pairs)
        if not changed:
            break
    return label


def upsample_labels(coarse: np.ndarray, row0: int, col0: int, window: tuple[int, int, int, int], factor: int,
                    shape: tuple[int, int]) -> np.ndarray:
    """Label of every output pixel of ``window`` (``r0, r1, c0, c1``, may reach outside the mosaic).

    Parameters
    ----------
    coarse : ndarray, shape (h, w), uint16
        Cells ``row0 ...``, ``col0 ...`` of the coarse label map (covering the window).
    row0, col0 : int
        The first coarse cell of ``coarse``.
    window : (r0, r1, c0, c1)
        Output pixels.
    factor : int
        Output pixels per coarse cell.
    shape : (rows, cols)
        The mosaic's size in output pixels; outside it the label is ``NO_SOURCE``.

    Returns
    -------
    ndarray, shape (r1 - r0, c1 - c0), uint16
    """
    r0, r1, c0, c1 = window
    rows, cols = np.arange(r0, r1), np.arange(c0, c1)
    ir = np.clip(rows // factor - row0, 0, coarse.shape[0] - 1)
    ic = np.clip(cols // factor - col0, 0, coarse.shape[1] - 1)
    out = coarse[ir[:, None], ic[None, :]]
    inside = ((rows >= 0) & (rows < shape[0]))[:, None] & ((cols >= 0) & (cols < shape[1]))[None, :]
    return np.where(inside, out, NO_SOURCE).astype(np.uint16)


def label_weights(label: np.ndarray, scenes: np.ndarray, *, feather: float) -> np.ndarray:
    """Blending weight of every scene from a label map, feathered across the label boundaries.

    A scene's signed distance ``t`` from the boundary of its region (``+1/2`` on its side of
    the boundary's first pixel, ``-1/2`` on the other, growing by one per pixel; distances to
    pixels without a label do not count) gives the weight ``clip(1/2 + t / feather, 0, 1)``.
    Two regions that meet along a straight boundary get weights that sum to one, rising
    linearly from 0 to 1 across ``feather`` pixels.

    Parameters
    ----------
    label : ndarray, shape (h, w), uint16
        Scene index per pixel (:data:`NO_SOURCE`: none), over a window that reaches at least
        ``feather / 2 + 1`` pixels beyond the pixels whose weights are used.
    scenes : ndarray of int, shape (K,)
        The scenes to weight.
    feather : float
        Width of the blend, in pixels; 0: no blend.

    Returns
    -------
    ndarray, shape (K, h, w), float32
        Unnormalised weights (0 where no label says the scene).
    """
    labelled = label != NO_SOURCE
    out = np.zeros((len(scenes), *label.shape), dtype=np.float32)
    for n, k in enumerate(scenes):
        mine = label == k
        if not mine.any():
            continue
        other = labelled & ~mine
        if feather <= 0 or not other.any():
            out[n] = mine
            continue
        inside = ndimage.distance_transform_edt(~other) - 0.5  # to the nearest pixel of another scene
        outside = ndimage.distance_transform_edt(~mine) - 0.5  # to the nearest pixel of this scene
        t = np.where(mine, inside, -outside)
        out[n] = np.where(labelled, np.clip(0.5 + t / feather, 0.0, 1.0), 0.0)
    return out


def seam_pairs(source: np.ndarray, *, rows: int | None = None, cols: int | None = None) -> tuple[np.ndarray, ...]:
    """The pixels where the source changes to the right or below: ``(row, col, a, b)``.

    Parameters
    ----------
    source : ndarray, shape (h, w), uint16
        Scene index per pixel (:data:`NO_SOURCE`: none).
    rows, cols : int, optional
        Only pixels ``[:rows, :cols]`` count (their right and lower neighbours may lie beyond,
        as in an output tile read with one more row and column).

    Returns
    -------
    tuple of ndarray
        ``row, col`` of the pixel, ``a`` its scene and ``b`` its neighbour's, for every pixel
        with a neighbour (right or below) from another scene; a pixel with two such
        neighbours appears twice.
    """
    h, w = source.shape
    rows = h if rows is None else rows
    cols = w if cols is None else cols
    out = []
    for dr, dc in ((0, 1), (1, 0)):
        a = source[: h - dr, : w - dc]
        b = source[dr:, dc:]
        hit = (a != b) & (a != NO_SOURCE) & (b != NO_SOURCE)
        hit[rows:, :] = False
        hit[:, cols:] = False
        r, c = np.nonzero(hit)
        out.append((r, c, a[r, c], b[r, c]))
    return tuple(np.concatenate([o[q] for o in out]) for q in range(4))
