"""Tile-parallel correspondence: one task per base tile, reading its windows from Zarr.

Every task gets the base interest points of its tile and the distorted interest points of
the window the current prediction says it needs, reads the base tile (plus the patch
margin) and that distorted window straight from the Zarr stores, and returns refined tie
points. The tie points are then gathered (they are small) and a robust global polynomial
is fitted on one node (seed 003 sec. 7).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import dask
import numpy as np

from ..kernels.interest import InterestPoints
from ..kernels.polynomial import PolyMap, exponents, fit_polymap
from ..match.correspondence import CorrespondenceOptions, TileMatchStats, correspond, correspond_guided
from ..match.tiepoints import TiePoints
from ..scene import WindowReader
from ..tiles import PointsByRow, Tile, TileGrid, Window
from .job import Job, run_tiles


def _subset(points: InterestPoints, index: np.ndarray) -> InterestPoints:
    return InterestPoints(points.x[index], points.y[index], points.w[index], points.q[index])


def distorted_window(tile: Tile, predict: PolyMap, margin: float) -> Window:
    """Window of the distorted image (row0, row1, col0, col1) a base tile maps into."""
    n = 9
    xs = np.r_[np.linspace(tile.col0, tile.col1 - 1, n), np.full(n, tile.col1 - 1), np.linspace(tile.col0, tile.col1 - 1, n), np.full(n, tile.col0)]
    ys = np.r_[np.full(n, tile.row0), np.linspace(tile.row0, tile.row1 - 1, n), np.full(n, tile.row1 - 1), np.linspace(tile.row0, tile.row1 - 1, n)]
    px, py = predict(xs, ys)
    return Window.around(py, px, margin)


def _tile_task(tile, base_reader, dist_reader, band, dist_band, bpts, dpts, predict, dwin, opts, guided, refine=True):
    m = opts.margin
    r0, r1, c0, c1 = tile.window(m)
    base = base_reader.read(r0, r1, c0, c1)[band]
    dr0, dr1, dc0, dc1 = dwin
    dist = dist_reader.read(dr0, dr1, dc0, dc1)[dist_band]
    if guided:
        return correspond_guided(base, (r0, c0), bpts, dist, (dr0, dc0), predict, opts)
    return correspond(base, (r0, c0), bpts, dist, (dr0, dc0), dpts, predict, opts, refine=refine)


@dataclass(frozen=True)
class CorrespondenceResult:
    """Gathered tie points, the robust global polynomial, and per-tile statistics."""

    tiepoints: TiePoints
    mapping: PolyMap
    stats: list[TileMatchStats]


def tile_points(grid: TileGrid, base_points: InterestPoints, dist_points: InterestPoints, predict: PolyMap,
                dshape: tuple[int, int], opts: CorrespondenceOptions
                ) -> Iterator[tuple[Tile, InterestPoints, InterestPoints, Window]]:
    """What each tile's correspondence task gets: per tile whose core holds base points and whose
    predicted window in the distorted scene (``dshape``) is not empty, the tile, its base
    points, the distorted points in that window and the window (the points routed to tiles in
    one pass, :meth:`~geocoder.tiles.TileGrid.route` and :class:`~geocoder.tiles.PointsByRow`)."""
    routed = grid.route(base_points.x, base_points.y)
    dist_rows = PointsByRow(dist_points.x, dist_points.y)
    margin = opts.d_max + opts.margin * 2 + 2
    for tile in grid:
        inside = routed.get(tile.key)
        if inside is None:
            continue
        dwin = distorted_window(tile, predict, margin).clip(*dshape)
        if not dwin.empty:
            yield tile, _subset(base_points, inside), _subset(dist_points, dist_rows.in_window(dwin)), dwin


def match_tiles(
    base_reader: WindowReader,
    dist_reader: WindowReader,
    grid: TileGrid,
    base_points: InterestPoints,
    dist_points: InterestPoints,
    predict: PolyMap,
    *,
    band: int = 0,
    dist_band: int = 0,
    opts: CorrespondenceOptions = CorrespondenceOptions(),
    guided: bool = False,
    refine: bool = True,
    job: Job | None = None,
    stage: str = "correspondence",
) -> tuple[TiePoints, list[TileMatchStats]]:
    """Match every tile in parallel: point pairs (seed 000 sec. 4.4; refined by least squares
    unless ``refine`` is False) or, with ``guided``, least squares from the prediction
    (:func:`~geocoder.match.correspondence.correspond_guided`)."""
    dshape = dist_reader.shape[1:]
    token = dask.base.tokenize(base_reader.store, dist_reader.store, band, dist_band, predict.coef, opts, guided, refine)
    tasks = {}
    for tile, bpts, dpts, dwin in tile_points(grid, base_points, dist_points, predict, dshape, opts):
        tasks[tile.key] = dask.delayed(_tile_task, pure=True)(
            tile, base_reader, dist_reader, band, dist_band, bpts, dpts, predict, dwin, opts, guided, refine,
            dask_key_name=f"correspond-{tile.key}-{token}",
        )
    results = list(run_tiles(job, f"{stage}-{token[:12]}", tasks, phase=stage).values())
    tps = TiePoints.concatenate([r[0] for r in results])
    return tps, [r[1] for r in results]


#: Base points in the overlap per polynomial term that pass 1 needs before its pairs may stay
#: unrefined (:func:`refine_first_pass`). An unrefined pair scatters by 0.5-0.6 px per axis
#: (tests/test_correspondence.py) and about half the base points pair, so 250 per term give the
#: pass's polynomial ~0.05 px on average where the pairs are. With the 20-40 pairs of the small
#: overlaps of tests/test_mosaic_neighbours.py it was ~0.5 px off: the guided pass then kept
#: 29 of 54 points on one pair, and the block's RMSE rose 0.2 -> 0.27 px.
UNREFINED_POINTS_PER_TERM = 250


def refine_first_pass(points: InterestPoints, predict: PolyMap, dist_shape: tuple[int, int], *, order: int,
                      passes: int) -> bool:
    """Whether correspondence pass 1 must refine its pairs by least squares.

    Pass 1's tie points become the job's when no guided pass follows (``passes < 2``);
    otherwise its polynomial only predicts where the guided passes refine every base point,
    and whole-pixel pairs do that as well when there are many: at least
    :data:`UNREFINED_POINTS_PER_TERM` base points per term of the order-``order`` polynomial
    whose prediction falls inside the distorted scene (``dist_shape``, rows and columns).
    """
    if passes < 2:
        return True
    return _inside(points, predict, dist_shape) < UNREFINED_POINTS_PER_TERM * len(exponents(order))


#: Cell (base pixels) of pass 1's thinning (:func:`first_pass_points`): the strongest base point of
#: every such cell of the base grid, on a scene large enough to keep :data:`FIRST_PASS_MARGIN` times
#: what unrefined pairs need.
FIRST_PASS_CELL = 64
FIRST_PASS_MARGIN = 2


def _inside(points: InterestPoints, predict: PolyMap, dist_shape: tuple[int, int]) -> int:
    """How many of ``points`` the prediction places inside the distorted scene (rows, columns)."""
    x, y = predict(points.x, points.y)
    return int(((x >= 0) & (x < dist_shape[1]) & (y >= 0) & (y < dist_shape[0])).sum())


def first_pass_points(points: InterestPoints, predict: PolyMap, dist_shape: tuple[int, int], *, order: int,
                      cell: int | None = None) -> InterestPoints:
    """The base points an unrefined pass 1 pairs: the strongest (largest ``w``) of every ``cell``
    x ``cell`` square of the base grid, when they still number :data:`FIRST_PASS_MARGIN` times
    :data:`UNREFINED_POINTS_PER_TERM` per polynomial term inside the distorted scene; else all.

    Pass 1's polynomial only predicts where the guided passes refine every base point, and a
    scene of 8192² px has ~80,000 of them where ~1,500 tell the quadratic to 0.05 px: pairing
    every one was 6-9 of the job's 14-17 correspondence task-seconds. The squares are global
    (a point's square does not depend on the tiling), ties go to the earlier point.

    Parameters
    ----------
    points : InterestPoints
        The base scene's points (global pixels, sorted by row and column).
    predict : PolyMap
        Base -> distorted prediction of pass 1.
    dist_shape : tuple of int
        Rows and columns of the distorted scene.
    order : int
        Order of the polynomial fitted to pass 1's pairs.
    cell : int, optional
        Side of the squares (default :data:`FIRST_PASS_CELL`).

    Returns
    -------
    InterestPoints
        A subset of ``points`` in their order.
    """
    cell = FIRST_PASS_CELL if cell is None else int(cell)
    if len(points) == 0:
        return points
    cy = (points.y // cell).astype(np.int64)
    cx = (points.x // cell).astype(np.int64)
    square = cy * (int(cx.max()) + 1) + cx
    by_square = np.lexsort((-points.w, square))  # stable: equal w keep their order
    first = np.ones(len(points), dtype=bool)
    first[1:] = square[by_square][1:] != square[by_square][:-1]
    keep = np.sort(by_square[first])
    thinned = InterestPoints(points.x[keep], points.y[keep], points.w[keep], points.q[keep])
    need = FIRST_PASS_MARGIN * UNREFINED_POINTS_PER_TERM * len(exponents(order))
    return thinned if _inside(thinned, predict, dist_shape) >= need else points


def first_pass(points: InterestPoints, predict: PolyMap, dist_shape: tuple[int, int], *, order: int,
               passes: int) -> tuple[InterestPoints, bool]:
    """The base points correspondence pass 1 pairs, and whether it refines its pairs:
    :func:`refine_first_pass`, and :func:`first_pass_points` where it does not (the one decision
    of :func:`geocoder.pipeline.register.find_tiepoints` and the mosaic's pairs)."""
    if refine_first_pass(points, predict, dist_shape, order=order, passes=passes):
        return points, True
    return first_pass_points(points, predict, dist_shape, order=order), False


def fit_global(tiepoints: TiePoints, *, order: int = 2) -> tuple[TiePoints, PolyMap]:
    """Robust global polynomial base -> distorted over all tie points (eq 20b then 22b)."""
    mapping = fit_polymap(tiepoints.base_x, tiepoints.base_y, tiepoints.dist_x, tiepoints.dist_y, order=order)
    info = mapping.fit_info
    return tiepoints.with_fit(info.residuals, info.inliers), mapping
