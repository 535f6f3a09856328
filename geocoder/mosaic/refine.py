"""Dense refinement of one block scene: its field against the reference (or a neighbour composite).

:func:`refine_scene` runs the registration's dense stage on the reference's grid, predicted by
the scene's adjusted model and seeded by its matches, and stores the field of the reference
tiles its footprint touches (group ``dense/<n>`` of the mosaic's store). Unmatched pixels take
their scene row's estimate (:mod:`geocoder.mosaic.scanlines`); rows without one, the nearest
match along the reference row (:func:`carry_along_rows`), then along the column.
"""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np
import xarray as xr
from affine import Affine

from ..geometry import pixel_to_world
from ..kernels.polynomial import fit_polymap
from ..pipeline.job import Job
from ..pipeline.register import RegisterOptions
from ..status import Status
from ..tiles import TileGrid

__all__ = ["CARRY_PX", "CARRY_ROWS", "carry_along_rows", "refine_scene"]


def refine_scene(job: Job, key: str, store: str, n: int, ref, ref_reader, reader, model, tp, to_ref, shape,
            transform: Affine, opts: RegisterOptions, dem=None, tag: str = "", sigma_known: bool = True) -> dict | None:
    """Dense field of block scene ``n`` against the reference (or ``ref_reader``'s image on its
    grid), written to group ``dense/<n><tag>`` of ``store`` on the reference tiles its footprint
    touches; its location (see :func:`geocoder.mosaic.output.scene_xy`)."""
    from ..pipeline.dense import DenseOptions, dense_field, grow_tiles, seeds_from_tiepoints
    from ..pipeline.resample import polynomial_displacement
    from ..quality.postfilter import PostFilterOptions

    sub = Job(job.file("dense", f"scene-{n}{tag}"), key)
    try:
        h, w = shape
        # reference pixel -> scene pixel as the adjusted model says, fitted over the footprint
        sy, sx = np.mgrid[0 : h - 1 : 33j, 0 : w - 1 : 33j]
        rx, ry = to_ref(sx.ravel(), sy.ravel())
        ex, ny = pixel_to_world(transform, rx, ry)
        xy = model[0].project(model[1], np.column_stack([ex, ny, np.zeros(ex.size) if dem is None else dem(ex, ny)]))
        mapping = fit_polymap(rx, ry, xy[:, 0], xy[:, 1], order=3, robust=False)
        chunks = ref.data.chunks[1:]
        grid = TileGrid.from_chunks(chunks)
        result = grow_tiles(ref_reader, reader, grid, seeds_from_tiepoints(tp, mapping), mapping, sub.file("state.zarr"),
                            band=opts.band - 1, dist_band=opts.band - 1, opts=DenseOptions(), job=sub)
        pdx, pdy = polynomial_displacement(mapping, chunks)
        field_ = dense_field(result, (pdx, pdy), PostFilterOptions())
        # the whole tiles of the reference that the footprint touches
        edges_r, edges_c = np.r_[0, np.cumsum(grid.rows)], np.r_[0, np.cumsum(grid.cols)]
        ia = max(int(np.searchsorted(edges_r, ry.min(), side="right")) - 1, 0)
        ib = min(int(np.searchsorted(edges_r, ry.max(), side="right")), len(grid.rows))
        ja = max(int(np.searchsorted(edges_c, rx.min(), side="right")) - 1, 0)
        jb = min(int(np.searchsorted(edges_c, rx.max(), side="right")), len(grid.cols))
        r0, r1, c0, c1 = int(edges_r[ia]), int(edges_r[ib]), int(edges_c[ja]), int(edges_c[jb])
        if r0 >= r1 or c0 >= c1:
            return None
        group = f"dense/{n}{tag}"
        if not sub.done("field"):
            rows = (tuple(grid.rows[ia:ib]), (c1 - c0,))  # whole rows of the footprint: carried along them
            # the matched field once into the sub-job (the scene rows' sums and the estimates read it)
            raw = sub.file("matched.zarr")
            if not sub.done("matched"):
                xr.Dataset({name: (("y", "x"), field_[name][r0:r1, c0:c1].rechunk(rows))
                            for name in ("dx", "dy", "status", "sigma_x", "sigma_y")}).to_zarr(
                    raw, mode="w", zarr_format=3, consolidated=False)
                sub.save("matched")
            matched = xr.open_zarr(raw, zarr_format=3, consolidated=False, chunks={"y": rows[0], "x": rows[1]})
            parts = [matched[name].data for name in ("dx", "dy", "status")] + [a[r0:r1, c0:c1].rechunk(rows) for a in (pdx, pdy)]
            # unmatched pixels: the model plus the field's smooth correction and their scene row's shift
            # (geocoder.mosaic.scanlines); what is left (rows without matches), from the nearest match
            # along the reference row, then along the column
            table = _scene_line_table(parts, r0, c0, shape)
            est = da.map_blocks(_estimate_block, *parts, table=table, row0=r0, col0=c0, shape=shape,
                                new_axis=0, chunks=((3,), *rows), dtype=np.float32)
            parts = [est[0], est[1], est[2], *parts[3:]]
            carried = da.map_blocks(carry_along_rows, *parts, max_px=CARRY_PX, new_axis=0, chunks=((3,), *rows),
                                    dtype=np.float32)
            # rows with no match at all (the template's margin at a scene's top and bottom): from the next rows
            carried = da.map_overlap(_carry_along_columns, carried, *parts[3:],
                                     depth=[{0: 0, 1: CARRY_ROWS, 2: 0}, {0: CARRY_ROWS, 1: 0}, {0: CARRY_ROWS, 1: 0}],
                                     boundary="none", dtype=np.float32, max_rows=CARRY_ROWS)
            part = xr.Dataset(
                {"dx": (("y", "x"), carried[0]), "dy": (("y", "x"), carried[1]),
                 "status": (("y", "x"), carried[2].astype(np.uint8)),
                 **{name: (("y", "x"), matched[name].data if sigma_known else da.full_like(matched[name].data, np.nan))
                    for name in ("sigma_x", "sigma_y")}},
                attrs={"row0": r0, "col0": c0, "long_name": "displacement reference pixel -> scene pixel",
                       "filled": "matched; FILLED: short holes interpolated by the post-filter; ESTIMATED: the model "
                                 "plus the field's smooth correction along the scene rows and the row's own shift "
                                 "(geocoder.mosaic.scanlines); FILLED also where a scene row has no shift: the "
                                 f"correction of the nearest match within {CARRY_PX} px of the reference row",
                       "sigma": "sigma_x, sigma_y: standard deviations of the matched pixels' dx, dy (NaN elsewhere)"
                                if sigma_known else "sigma_x, sigma_y: unknown (NaN): matched against refined neighbours, "
                                "whose own error the match's sigma leaves out (5x optimistic, measured)"})
            part.to_zarr(store, group=group, mode="w", zarr_format=3, consolidated=False)
            sub.save("field")
        return {"store": f"{store}/{group}", "group": group, "row0": r0, "col0": c0, "shape": (r1 - r0, c1 - c0)}
    finally:
        sub.release()


#: Largest distance (px) along a row over which a dense correction is carried from the nearest match.
CARRY_PX = 64



def _scene_line_table(parts: list, row0: int, col0: int, shape: tuple[int, int]) -> np.ndarray:
    """Corrections per scene row (:func:`geocoder.mosaic.scanlines.line_table`) of a footprint's
    field, from the row bands' sums (gathered: a few numbers per scene row)."""
    from .scanlines import combine_line_sums, line_table, scene_line_sums

    starts = row0 + np.r_[0, np.cumsum(parts[0].chunks[0])[:-1]]
    blocks = [p.to_delayed()[:, 0] for p in parts]
    sums = [dask.delayed(scene_line_sums)(*(b[k] for b in blocks), row0=int(starts[k]), col0=col0, shape=shape)
            for k in range(len(starts))]
    total = dask.delayed(lambda *s: combine_line_sums(np.stack(s, axis=-1)))(*sums).compute()
    return line_table(total, min_count=LINE_MIN_COUNT, max_gap=CARRY_ROWS, end_rows=CARRY_ROWS)


#: Fewest matches a scene row needs for a correction of its own.
LINE_MIN_COUNT = 16


def _estimate_block(dx, dy, status, pdx, pdy, block_info=None, *, table: np.ndarray, row0: int, col0: int,
                    shape: tuple[int, int]) -> np.ndarray:
    from .scanlines import line_estimates

    row0 += block_info[0]["array-location"][0][0]
    return line_estimates(dx, dy, status, pdx, pdy, table, row0=row0, col0=col0, shape=shape)


def carry_along_rows(dx: np.ndarray, dy: np.ndarray, status: np.ndarray, pdx: np.ndarray, pdy: np.ndarray, *,
                     max_px: int = CARRY_PX) -> np.ndarray:
    """Unmatched pixels take the correction (field minus model) of the nearest match in their row.

    The line-to-line turbulence of a line scanner shifts a whole scan line; the model knows
    the rest of the geometry. So where the dense field has no match (low texture, the
    template's margin along the scene's edges), the correction of the nearest matched or
    filled pixel of the same row, at most ``max_px`` away, is added to the model's
    displacement ``(pdx, pdy)``; those pixels become ``FILLED``. Returns ``(3, h, w)``:
    ``dx, dy, status``.
    """
    good = (status == Status.MATCHED) | (status == Status.FILLED)
    h, w = good.shape
    col = np.broadcast_to(np.arange(w), (h, w))
    left = np.maximum.accumulate(np.where(good, col, -1), axis=1)
    right = np.minimum.accumulate(np.where(good, col, 2 * w)[:, ::-1], axis=1)[:, ::-1]
    dl = np.where(left >= 0, col - left, 2 * w)
    dr = np.where(right < w, right - col, 2 * w)
    near = np.where(dl <= dr, left, right)
    carry = ~good & (status != Status.ESTIMATED) & (np.minimum(dl, dr) <= max_px)
    src = np.clip(near, 0, w - 1)
    cx = np.take_along_axis(np.asarray(dx - pdx), src, axis=1)
    cy = np.take_along_axis(np.asarray(dy - pdy), src, axis=1)
    out_dx = np.where(carry, pdx + cx, dx)
    out_dy = np.where(carry, pdy + cy, dy)
    out_status = np.where(carry, Status.FILLED, status)
    return np.stack([out_dx, out_dy, out_status]).astype(np.float32)


#: Largest distance (rows) over which a correction is carried into a row without any match.
CARRY_ROWS = 8


def _carry_along_columns(carried: np.ndarray, pdx: np.ndarray, pdy: np.ndarray, *, max_rows: int) -> np.ndarray:
    """:func:`carry_along_rows` across rows: pixels still without a correction take the one of
    the nearest row that has one (same column, at most ``max_rows`` away)."""
    dx, dy, status = carried
    t = carry_along_rows(dx.T, dy.T, status.T, pdx.T, pdy.T, max_px=max_rows)
    return np.transpose(t, (0, 2, 1))
