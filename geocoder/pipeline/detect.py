"""Tile-parallel interest points: the Foerstner operator over a dask array.

Two passes over the tiles. The first computes ``w`` for every pixel (``map_overlap``, halo =
half the window) and reduces it to the global mean that fixes the size threshold
``w_min = f * mean(w)``; the second recomputes ``w, q`` on every tile plus a halo of
``window // 2 + 1 + radius`` (enough for the non-maximum suppression to see every neighbour
of a core pixel) and keeps the points of the core. So points on tile borders are neither
duplicated nor lost, and the result does not depend on the tile size (see the tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import dask
import dask.array as da
import numpy as np

from ..kernels.interest import InterestPoints, foerstner, select_points
from ..tiles import TileGrid


@dataclass(frozen=True)
class InterestOptions:
    """Options of the interest operator (seed 000 sec. 4.4.1)."""

    window: int = 7
    q_min: float = 0.25
    f: float = 1.5
    radius: int = 4
    cell: int = 64
    cap: int = 8

    @property
    def halo(self) -> int:
        return self.window // 2 + 1 + self.radius


def _w_only(block: np.ndarray, window: int) -> np.ndarray:
    return foerstner(block, window=window)[0]


def _points_block(block, origin, core, width, w_min, opts: InterestOptions) -> InterestPoints:
    w, q = foerstner(block, window=opts.window)
    return select_points(
        w, q, w_min=w_min, q_min=opts.q_min, radius=opts.radius,
        cell=opts.cell, cap=opts.cap, core=core, origin=origin, width=width,
    )


def interest_points(image: da.Array, opts: InterestOptions = InterestOptions()) -> InterestPoints:
    """Interest points of a 2-D dask array (one band), gathered as one small table.

    Parameters
    ----------
    image : dask.array.Array, shape (H, W)
        Grey values, NaN = nodata. Its chunks are the tiles; chunk sizes must be multiples
        of ``opts.cell`` (except the last) for tiling-independent thinning.
    opts : InterestOptions

    Returns
    -------
    InterestPoints
        Global pixel coordinates, sorted by (row, column).
    """
    h, w = image.shape
    grid = TileGrid.regular(h, w, image.chunksize[0], min_last=opts.halo + 1)
    grid = TileGrid(h, w, grid.rows, TileGrid.regular(h, w, image.chunksize[1], min_last=opts.halo + 1).cols)
    image = image.rechunk(grid.chunks)
    for size in (*grid.rows[:-1], *grid.cols[:-1]):
        if size % opts.cell:
            raise ValueError(f"tile size {size} is not a multiple of the interest cell {opts.cell}")
    depth1 = opts.window // 2 + 1
    wmap = image.map_overlap(_w_only, depth=depth1, boundary="none", dtype=np.float32, window=opts.window)
    total, count = dask.compute(da.where(wmap > 0, wmap, 0).astype(np.float64).sum(), (wmap > 0).sum())
    if count == 0:
        return InterestPoints.concatenate([])
    w_min = opts.f * float(total) / float(count)
    depth = opts.halo
    blocks = da.overlap.overlap(image, depth={0: depth, 1: depth}, boundary="none").to_delayed()
    tasks = []
    for iy in range(blocks.shape[0]):
        for ix in range(blocks.shape[1]):
            r0, c0, core = grid.overlapped_origin(iy, ix, depth)
            tasks.append(dask.delayed(_points_block, pure=True)(blocks[iy, ix], (r0, c0), core, w, w_min, opts))
    parts = dask.compute(*tasks)
    return InterestPoints.concatenate(list(parts))
