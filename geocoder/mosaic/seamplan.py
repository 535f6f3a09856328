"""The seam stage of a mosaic: coarse samples of every scene (tile-parallel), the label map cut on one node.

1. One task per coarse window of the output (whole cells of ``factor x factor`` pixels, so the
   cells do not depend on the output's tiling) samples every scene that covers it through its
   adjusted model at ``samples x samples`` points per cell and returns, per scene, the cells'
   mean balanced grey value, centre score and whether the scene covers them entirely
   (:class:`~geocoder.mosaic.seams.CoarseScene`). A task holds one window of one scene at a
   time: memory grows with the tile, not the mosaic.
2. On the client, the per-scene cells are put together (``1 / factor**2`` of each scene) and
   the label map is cut (:func:`~geocoder.mosaic.seams.least_cost_labels`); it is written to
   the output store (group ``seams``, array ``label``), where every output tile reads the
   window it needs.
"""

from __future__ import annotations

import math

import dask
import numpy as np
from affine import Affine

from ..tiles import TileGrid
from .compose import centre_score
from .outgrid import Reprojected, to_map
from .seams import CoarseScene, least_cost_labels

#: Group and array of the coarse label map in a mosaic's store.
SEAM_GROUP = "seams"
#: Largest side of the coarse label map (the factor grows in powers of two to keep under it).
MAX_COARSE = 4096
#: Half-width of a pair's corridor, as a fraction of the smaller scene's side.
CORRIDOR = 0.125


def seam_factor(shape: tuple[int, int], *, base: int = 8, largest: int = 64) -> int:
    """Output pixels per coarse cell: ``base``, doubled while the coarse grid is larger than :data:`MAX_COARSE`.

    Parameters
    ----------
    shape : (rows, cols)
        The mosaic, in output pixels.
    base, largest : int
        The smallest and largest factor (powers of two).

    Returns
    -------
    int
    """
    f = base
    while max(shape) / f > MAX_COARSE and f < largest:
        f *= 2
    return f


def coarse_tile(window: tuple[int, int, int, int], transform: Affine | Reprojected, models: list, readers: list, shapes: list,
                balance: np.ndarray, boxes: np.ndarray, factor: int, samples: int, dem=None) -> dict:
    """Coarse cells of one window of the output in every scene that covers it (worker side).

    Parameters
    ----------
    window : (r0, r1, c0, c1)
        Output pixels; ``r0`` and ``c0`` are multiples of ``factor``.
    transform : Affine or Reprojected
        The output grid (:mod:`geocoder.mosaic.outgrid`).
    models : list of (model, params)
        The adjusted model of every block scene (map -> scene pixel).
    readers : list of WindowReader
    shapes : list of (rows, cols)
    balance : ndarray, shape (K, B, 2)
        Gain and offset per scene and band.
    boxes : ndarray, shape (K, 4)
        Every scene's footprint box in output pixels (``row0, row1, col0, col1``).
    factor : int
        Output pixels per cell.
    samples : int
        Samples per cell and axis.
    dem : callable, optional
        ``dem(E, N)``: ground heights; 0 without.

    Returns
    -------
    dict
        Scene index -> ``(cell row0, cell col0, value, score, full)`` of the window's cells.
    """
    r0, r1, c0, c1 = window
    near = np.flatnonzero((boxes[:, 0] < r1) & (boxes[:, 1] > r0) & (boxes[:, 2] < c1) & (boxes[:, 3] > c0))
    i0, j0 = r0 // factor, c0 // factor
    nr, nc = -(-(r1 - r0) // factor), -(-(c1 - c0) // factor)
    step = factor / samples
    off = step * (np.arange(samples) + 0.5) - 0.5
    ys = (np.arange(i0, i0 + nr)[:, None] * factor + off[None, :]).ravel()
    xs = (np.arange(j0, j0 + nc)[:, None] * factor + off[None, :]).ravel()
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    cy, cx = np.meshgrid((np.arange(i0, i0 + nr) + 0.5) * factor - 0.5, (np.arange(j0, j0 + nc) + 0.5) * factor - 0.5,
                         indexing="ij")
    ex, ny = to_map(transform, np.concatenate([gx.ravel(), cx.ravel()]), np.concatenate([gy.ravel(), cy.ravel()]))
    ground = np.column_stack([ex, ny, np.zeros(ex.size) if dem is None else dem(ex, ny)])
    m = gx.size
    out = {}
    for k in near:
        model, params = models[k]
        xy = model.project(params, ground)
        x, y = xy[:m, 0].reshape(gx.shape), xy[:m, 1].reshape(gx.shape)
        inside = centre_score(x, y, shapes[k]) <= 1.0
        centre = centre_score(xy[m:, 0], xy[m:, 1], shapes[k]).reshape(nr, nc)
        if not inside.any():
            continue
        v = readers[k].sample(x, y, method="bilinear")
        v = balance[k, :, 0, None, None] * v + balance[k, :, 1, None, None]
        v = np.where(inside, v.mean(axis=0), np.nan).reshape(nr, samples, nc, samples)
        good = np.isfinite(v)
        count = good.sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            value = np.where(count > 0, np.nansum(v, axis=(1, 3)) / count, np.nan).astype(np.float32)
        full = count == samples * samples
        score = np.where(count > 0, centre, np.nan)
        out[int(k)] = (i0, j0, value, score, full)
    return out


def plan_seams(job, store: str, grid_shape: tuple[int, int], tile: int, transform: Affine | Reprojected, models: list, readers: list,
               shapes: list, balance: np.ndarray, boxes: np.ndarray, pairs: list[tuple[int, int]], *,
               samples: int = 4, dem=None) -> dict:
    """Cut the seams of a mosaic on its coarse grid and write the label map into ``store``.

    Parameters
    ----------
    job : Job
        Keeps the coarse tiles and the label map for a rerun.
    store : str
        The output store (group :data:`SEAM_GROUP` is written).
    grid_shape : (rows, cols)
        The mosaic in output pixels.
    tile : int
        Tile size of the coarse pass (rounded up to whole cells).
    transform, models, readers, shapes, balance, boxes
        As :func:`coarse_tile`.
    pairs : list of (i, j)
        Overlapping pairs of block scenes.
    samples : int
        Samples per cell and axis.
    dem : callable, optional
        ``dem(E, N)``: ground heights (:class:`~geocoder.mosaic.heights.MapDEM`); 0 without.

    Returns
    -------
    dict
        ``factor`` (output pixels per cell), ``shape`` (cells), ``store`` (the label array's
        location), ``changed`` (cells the cuts moved from the centre rule).
    """
    import zarr

    from .seams import centre_labels

    factor = seam_factor(grid_shape)
    samples = min(samples, factor)
    cshape = (-(-grid_shape[0] // factor), -(-grid_shape[1] // factor))
    info = {"factor": factor, "shape": list(cshape), "store": f"{store}/{SEAM_GROUP}"}
    ctile = factor * math.ceil(tile / factor)
    cgrid = TileGrid.regular(*grid_shape, ctile)
    if job.done("seams"):
        job.count("seam cells", run=0, skipped=len(cgrid))  # as run_tiles would, for the job's report
        g = zarr.open_group(store, mode="r")[SEAM_GROUP]
        return {**info, "changed": int(g.attrs.get("changed", 0))}
    tasks = {f"seam-{t.key}": dask.delayed(coarse_tile, pure=True)(
        (t.row0, t.row1, t.col0, t.col1), transform, models, readers, shapes, balance, boxes, factor, samples, dem)
        for t in cgrid}
    results = job.run_tiles("seam cells", tasks, phase="seam cells")
    # every scene's cells over its box (clipped to the coarse grid)
    cboxes = np.column_stack([np.clip(boxes[:, 0] // factor, 0, cshape[0]), np.clip(-(-boxes[:, 1] // factor), 0, cshape[0]),
                              np.clip(boxes[:, 2] // factor, 0, cshape[1]), np.clip(-(-boxes[:, 3] // factor), 0, cshape[1])])
    scenes = []
    for a0, a1, b0, b1 in cboxes:
        h, w = max(int(a1 - a0), 0), max(int(b1 - b0), 0)
        scenes.append(CoarseScene(int(a0), int(b0), np.full((h, w), np.nan, np.float32), np.full((h, w), np.nan),
                                  np.zeros((h, w), bool)))
    for part in results.values():
        for k, (i0, j0, value, score, full) in part.items():
            s = scenes[k]
            r0, c0 = i0 - s.row0, j0 - s.col0
            a0, b0 = max(r0, 0), max(c0, 0)
            a1, b1 = min(r0 + value.shape[0], s.value.shape[0]), min(c0 + value.shape[1], s.value.shape[1])
            if a0 >= a1 or b0 >= b1:
                continue
            sl = (slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0))
            s.value[a0:a1, b0:b1] = value[sl]
            s.score[a0:a1, b0:b1] = score[sl]
            s.full[a0:a1, b0:b1] = full[sl]
    side = min(min(sh) for sh in shapes)
    label = least_cost_labels(cshape, scenes, pairs, width=max(CORRIDOR * side / factor, 1.0))
    changed = int(np.count_nonzero(label != centre_labels(cshape, scenes)))
    g = zarr.open_group(store, mode="r+")
    sg = g.require_group(SEAM_GROUP)
    arr = sg.create_array("label", shape=cshape, chunks=(min(512, cshape[0]), min(512, cshape[1])), dtype="uint16",
                          fill_value=65535, overwrite=True)
    arr[...] = label
    sg.attrs.update({"factor": factor, "changed": changed,
                     "long_name": "scene index of every coarse cell (factor x factor output pixels); 65535: none"})
    job.save("seams")
    return {**info, "changed": changed}


def read_labels(seams: dict, window: tuple[int, int, int, int]) -> tuple[np.ndarray, int, int]:
    """The cells of the label map under an output window (worker side).

    Returns ``(cells, cell row0, cell col0)``; the window may reach outside the mosaic.
    """
    import zarr

    f = seams["factor"]
    h, w = seams["shape"]
    r0, r1, c0, c1 = window
    a0, a1 = min(max(r0 // f, 0), h - 1), min(max(-(-r1 // f), 1), h)
    b0, b1 = min(max(c0 // f, 0), w - 1), min(max(-(-c1 // f), 1), w)
    arr = zarr.open_group(seams["store"], mode="r")["label"]
    return np.asarray(arr[a0:a1, b0:b1]), a0, b0
