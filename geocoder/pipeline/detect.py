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
from .job import Job, run_tiles


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


def _w_sum(block: np.ndarray) -> tuple[float, int]:
    good = block > 0
    return float(block[good].astype(np.float64).sum()), int(good.sum())


def interest_points(image: da.Array, opts: InterestOptions = InterestOptions(), *, job: Job | None = None, name: str = "image") -> InterestPoints:
    """Interest points of a 2-D dask array (one band), gathered as one small table.

    Parameters
    ----------
    image : dask.array.Array, shape (H, W)
        Grey values, NaN = nodata. Its chunks are the tiles; chunk sizes must be multiples
        of ``opts.cell`` (except the last) for tiling-independent thinning.
    opts : InterestOptions
    job : Job, optional
        Where finished tiles are kept (a rerun skips them).
    name : str
        Name of the image in the job's stages and the progress phases.

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
    # pass 1: the mean interest value over the whole image (the seed's threshold is global)
    depth1 = opts.window // 2 + 1
    wmap = image.map_overlap(_w_only, depth=depth1, boundary="none", dtype=np.float32, window=opts.window).to_delayed()
    keys = [f"{iy}-{ix}" for iy in range(wmap.shape[0]) for ix in range(wmap.shape[1])]
    sums = run_tiles(job, f"interest-mean-{name}",
                     {k: dask.delayed(_w_sum)(wmap[int(k.split("-")[0]), int(k.split("-")[1])]) for k in keys},
                     phase=f"interest points ({name}, 1/2)")
    total = sum(s for s, _ in sums.values())
    count = sum(c for _, c in sums.values())
    if count == 0:
        return InterestPoints.concatenate([])
    w_min = opts.f * total / count
    # pass 2: points per tile, thinned on the global cell grid
    depth = opts.halo
    blocks = da.overlap.overlap(image, depth={0: depth, 1: depth}, boundary="none").to_delayed()
    tasks = {}
    for iy in range(blocks.shape[0]):
        for ix in range(blocks.shape[1]):
            r0, c0, core = grid.overlapped_origin(iy, ix, depth)
            tasks[f"{iy}-{ix}"] = dask.delayed(_points_block, pure=True)(blocks[iy, ix], (r0, c0), core, w, w_min, opts)
    parts = run_tiles(job, f"interest-{name}", tasks, phase=f"interest points ({name}, 2/2)")
    return InterestPoints.concatenate(list(parts.values()))
