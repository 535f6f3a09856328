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
    (points,) = interest_points_many([image], opts, job=job, names=[name], readers=None if reader is None else [reader],
                                     bands=[band], stage=f"interest-candidates-{name}")
    return points


def interest_points_many(images: list[da.Array], opts: InterestOptions = InterestOptions(), *, job: Job | None = None,
                         names: list[str], readers: list[WindowReader] | None = None, bands: list[int] | None = None,
                         stage: str = "interest-candidates", phase: str | None = None) -> list[InterestPoints]:
    """Interest points of several images, all tiles of all of them in one tile-parallel stage.

    As :func:`interest_points` for each image (its own threshold ``f * mean(w)`` over its own
    tiles), with one round trip for all: the tasks of one image do not wait for another's.

    Parameters
    ----------
    images : list of dask.array.Array
        One band each, (H, W); their chunks are the tiles.
    opts : InterestOptions
    job : Job, optional
        Keeps every tile's candidates under ``stage`` (a rerun skips them).
    names : list of str
        A name per image, unique (the tasks' keys).
    readers, bands : list, optional
        The images in their Zarr stores and the 0-based band of each (see :func:`interest_points`).
    stage, phase : str
        The job's stage and the progress phase (default ``interest points (NAMES)``).

    Returns
    -------
    list of InterestPoints
        Per image, global pixel coordinates sorted by (row, column).
    """
    depth = opts.halo
    tasks, owner = {}, {}
    for n, (name, image) in enumerate(zip(names, images)):
        grid = interest_grid(image, opts)
        if readers is None:
            blocks = da.overlap.overlap(image.rechunk(grid.chunks), depth={0: depth, 1: depth}, boundary="none").to_delayed()
        for tile in grid:
            window, core = _clipped(grid, tile.iy, tile.ix, depth)
            key = f"{name}-{tile.key}"
            if readers is not None:
                band = 0 if bands is None else bands[n]
                tasks[key] = dask.delayed(_window_candidates, pure=True)(readers[n], band, window, core, grid.width, opts)
            else:
                tasks[key] = dask.delayed(_tile_candidates, pure=True)(blocks[tile.iy, tile.ix], (window[0], window[2]), core,
                                                                        grid.width, opts)
            owner[key] = n
    # one pass: every tile gives its sum of w (the seed's threshold f * mean(w) is global)
    # and its thinned candidates; the threshold is applied here, on the gathered candidates
    parts = run_tiles(job, stage, tasks, phase=phase or f"interest points ({', '.join(names)})")
    out = []
    for n in range(len(images)):
        mine = [p for key, p in parts.items() if owner[key] == n]
        total, count = sum(p[0] for p in mine), sum(p[1] for p in mine)
        if count == 0:
            out.append(InterestPoints.concatenate([]))
            continue
        w_min = opts.f * total / count
        out.append(InterestPoints.concatenate([_above(p[2], w_min) for p in mine]))
    return out


def interest_grid(image: da.Array, opts: InterestOptions) -> TileGrid:
    """The interest operator's tiles of one band: its chunks, a last tile narrower than the
    halo merged into the one before; every tile but the last a multiple of ``opts.cell``."""
    h, w = image.shape
    rows = TileGrid.regular(h, w, image.chunksize[0], min_last=opts.halo + 1).rows
    cols = TileGrid.regular(h, w, image.chunksize[1], min_last=opts.halo + 1).cols
    for size in (*rows[:-1], *cols[:-1]):
        if size % opts.cell:
            raise ValueError(f"tile size {size} is not a multiple of the interest cell {opts.cell}")
    return TileGrid(h, w, rows, cols)
