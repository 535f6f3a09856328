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
from ..scene import WindowReader
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


def _clipped(grid: TileGrid, iy: int, ix: int, depth: int) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """Global window of tile (iy, ix) grown by ``depth`` inside the image (as ``boundary='none'``), and its core in it."""
    r0, c0, core = grid.overlapped_origin(iy, ix, depth)
    rows = sum(grid.rows[: iy + 1]) + (depth if iy < len(grid.rows) - 1 else 0)
    cols = sum(grid.cols[: ix + 1]) + (depth if ix < len(grid.cols) - 1 else 0)
    return (r0, int(rows), c0, int(cols)), core


def _w_sum_window(reader: WindowReader, band: int, window, core, size: int) -> tuple[float, int]:
    w = foerstner(reader.read(*window)[band], window=size)[0]
    return _w_sum(w[core[0] : core[1], core[2] : core[3]])


def _points_window(reader: WindowReader, band: int, window, core, width, w_min, opts: InterestOptions) -> InterestPoints:
    return _points_block(reader.read(*window)[band], (window[0], window[2]), core, width, w_min, opts)


def interest_points(image: da.Array, opts: InterestOptions = InterestOptions(), *, job: Job | None = None, name: str = "image",
                    reader: WindowReader | None = None, band: int = 0) -> InterestPoints:
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
    reader, band : WindowReader, int, optional
        The same image in a Zarr store: each task then reads its tile and halo itself, so a
        worker holds one window at a time whatever the scene size (``image`` gives the tiling).

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
    keys = [(iy, ix) for iy in range(len(grid.rows)) for ix in range(len(grid.cols))]
    if reader is not None:
        tasks = {}
        for iy, ix in keys:
            window, core = _clipped(grid, iy, ix, depth1)
            tasks[f"{iy}-{ix}"] = dask.delayed(_w_sum_window, pure=True)(reader, band, window, core, opts.window)
    else:
        wmap = image.map_overlap(_w_only, depth=depth1, boundary="none", dtype=np.float32, window=opts.window).to_delayed()
        tasks = {f"{iy}-{ix}": dask.delayed(_w_sum)(wmap[iy, ix]) for iy, ix in keys}
    sums = run_tiles(job, f"interest-mean-{name}", tasks, phase=f"interest points ({name}, 1/2)")
    total = sum(s for s, _ in sums.values())
    count = sum(c for _, c in sums.values())
    if count == 0:
        return InterestPoints.concatenate([])
    w_min = opts.f * total / count
    # pass 2: points per tile, thinned on the global cell grid
    depth = opts.halo
    if reader is None:
        blocks = da.overlap.overlap(image, depth={0: depth, 1: depth}, boundary="none").to_delayed()
    tasks = {}
    for iy, ix in keys:
        window, core = _clipped(grid, iy, ix, depth)
        if reader is not None:
            tasks[f"{iy}-{ix}"] = dask.delayed(_points_window, pure=True)(reader, band, window, core, w, w_min, opts)
        else:
            tasks[f"{iy}-{ix}"] = dask.delayed(_points_block, pure=True)(blocks[iy, ix], (window[0], window[2]), core, w, w_min, opts)
    parts = run_tiles(job, f"interest-{name}", tasks, phase=f"interest points ({name}, 2/2)")
    return InterestPoints.concatenate(list(parts.values()))
