"""Tile-parallel interest points: the Foerstner operator over a dask array.

One pass over the tiles: every task computes ``w, q`` on its tile plus a halo of
``window // 2 + 1 + radius`` (enough for the non-maximum suppression to see every neighbour
of a core pixel), returns the sum of ``w`` over its core and the core's candidate points
(non-maximum suppression and the per-cell cap need no size threshold, see
:func:`_tile_candidates`). The gathered sums fix ``w_min = f * mean(w)``, applied to the
candidates on the client. So points on tile borders are neither duplicated nor lost, and the
result does not depend on the tile size (see the tests). (Until 0.1 this took two passes,
reading and filtering every tile twice.)
"""

from __future__ import annotations

from dataclasses import dataclass

import dask
import dask.array as da
import numpy as np

from ..kernels.interest import (
    DEFAULT_CAP,
    DEFAULT_CELL,
    DEFAULT_F,
    DEFAULT_Q_MIN,
    DEFAULT_RADIUS,
    DEFAULT_WINDOW,
    InterestPoints,
    foerstner,
    select_points,
)
from ..scene import WindowReader
from ..tiles import TileGrid
from .job import Job, run_tiles


@dataclass(frozen=True)
class InterestOptions:
    """Options of the interest operator (seed 000 sec. 4.4.1)."""

    window: int = DEFAULT_WINDOW
    q_min: float = DEFAULT_Q_MIN
    f: float = DEFAULT_F
    radius: int = DEFAULT_RADIUS
    cell: int = DEFAULT_CELL
    cap: int = DEFAULT_CAP

    @property
    def halo(self) -> int:
        return self.window // 2 + 1 + self.radius


def _clipped(grid: TileGrid, iy: int, ix: int, depth: int) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """Global window of tile (iy, ix) grown by ``depth`` inside the image (as ``boundary='none'``), and its core in it."""
    r0, c0, core = grid.overlapped_origin(iy, ix, depth)
    rows = sum(grid.rows[: iy + 1]) + (depth if iy < len(grid.rows) - 1 else 0)
    cols = sum(grid.cols[: ix + 1]) + (depth if ix < len(grid.cols) - 1 else 0)
    return (r0, int(rows), c0, int(cols)), core


def _tile_candidates(block: np.ndarray, origin, core, width, opts: InterestOptions) -> tuple[float, int, InterestPoints]:
    """One pass over a tile (core plus ``opts.halo``): its share of the global mean of ``w``
    and its candidate points, thinned before the size threshold is known.

    The candidates are the points :func:`select_points` keeps with ``w_min = 0``. For any
    ``w_min >= 0`` the points it keeps are exactly the candidates with ``w > w_min``: a
    candidate above the threshold is suppressed only by neighbours at least as strong,
    which pass the threshold too, and the strongest ``cap`` of a cell above a threshold
    are the strongest ``cap`` of the cell cut at that threshold (cells never straddle tiles).
    """
    w, q = foerstner(block, window=opts.window)
    r0, r1, c0, c1 = core
    wc = w[r0:r1, c0:c1]
    good = wc > 0
    total, count = float(wc[good].astype(np.float64).sum()), int(good.sum())
    cands = select_points(
        w, q, w_min=0.0, q_min=opts.q_min, radius=opts.radius,
        cell=opts.cell, cap=opts.cap, core=core, origin=origin, width=width,
    )
    return total, count, cands


def _window_candidates(reader: WindowReader, band: int, window, core, width, opts: InterestOptions):
    return _tile_candidates(reader.read(*window)[band], (window[0], window[2]), core, width, opts)


def _above(points: InterestPoints, w_min: float) -> InterestPoints:
    """Points with ``w > w_min``, compared in float32 as the float32 ``w`` map is."""
    keep = points.w.astype(np.float32) > np.float32(w_min)
    return InterestPoints(points.x[keep], points.y[keep], points.w[keep], points.q[keep])


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
    # one pass: every tile gives its sum of w (the seed's threshold f * mean(w) is global)
    # and its thinned candidates; the threshold is applied here, on the gathered candidates
    depth = opts.halo
    keys = [(iy, ix) for iy in range(len(grid.rows)) for ix in range(len(grid.cols))]
    if reader is None:
        blocks = da.overlap.overlap(image, depth={0: depth, 1: depth}, boundary="none").to_delayed()
    tasks = {}
    for iy, ix in keys:
        window, core = _clipped(grid, iy, ix, depth)
        if reader is not None:
            tasks[f"{iy}-{ix}"] = dask.delayed(_window_candidates, pure=True)(reader, band, window, core, w, opts)
        else:
            tasks[f"{iy}-{ix}"] = dask.delayed(_tile_candidates, pure=True)(blocks[iy, ix], (window[0], window[2]), core, w, opts)
    parts = run_tiles(job, f"interest-candidates-{name}", tasks, phase=f"interest points ({name})")
    total = sum(p[0] for p in parts.values())
    count = sum(p[1] for p in parts.values())
    if count == 0:
        return InterestPoints.concatenate([])
    w_min = opts.f * total / count
    return InterestPoints.concatenate([_above(p[2], w_min) for p in parts.values()])
