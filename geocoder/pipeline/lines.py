"""Per-line estimates for the unmatched pixels of a dense field, on Dask (:mod:`geocoder.quality.lines`).

Two steps: the residual sums of every row (one task per tile, added across the tiles of a
row band) are gathered, a few numbers per row; the corrections computed from them on the
client then enter the lazy output arrays as one column per row band.
"""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np

from ..quality.lines import (
    FIT_SUMS,
    FIT_TABLE,
    SUMS,
    LineCorrection,
    LineFit,
    LineOptions,
    combine_sums,
    fit_sums,
    fit_table,
    hole_estimates,
    line_coordinate,
    line_corrections,
    line_fits,
    line_sums,
    shrink_block,
    smooth_matches,
)
from ..status import Status


def _block_sums(dx, dy, px, py, status, sigma_x, sigma_y, block_info=None, *, width: int):
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    col0 = block_info[0]["array-location"][1][0]
    lines = line_sums(dx, dy, px, py, usable, sigma_x, sigma_y, col0)
    fits = fit_sums(dx - px, dy - py, sigma_x, sigma_y, status == Status.MATCHED, col0=col0, width=width)
    return np.concatenate([lines, fits])[..., None]


def row_corrections(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], options: LineOptions,
                    *, correlation: int = 51) -> tuple[LineCorrection, LineFit | None]:
    """Compute the correction of every row of a dense field (its matched and filled pixels),
    and the fit along every row that its matches are shrunk toward (None with
    ``options.fit_order = -1``), from one pass over the field.

    Parameters
    ----------
    field : dict of dask.array.Array
        ``dx``, ``dy``, ``status`` of :func:`geocoder.pipeline.dense.dense_field`.
    polynomial : tuple of dask.array.Array
        The global polynomial's ``dx, dy`` on the same grid.
    options : LineOptions
    correlation : int
        Template length along the line (px): a row's fit needs twice as many matches.

    Returns
    -------
    LineCorrection, LineFit or None
    """
    dx = field["dx"]
    n = len(SUMS) + len(FIT_SUMS)
    parts = da.map_blocks(_block_sums, dx, field["dy"], polynomial[0], polynomial[1], field["status"], field["sigma_x"],
                          field["sigma_y"], new_axis=0, chunks=((n,), dx.chunks[0], (1,) * len(dx.chunks[1])),
                          dtype=np.float64, width=dx.shape[1])
    (parts,) = dask.compute(parts)
    sums = combine_sums(parts[: len(SUMS)])
    rows = line_corrections(sums, min_count=options.min_count, max_gap=options.max_gap)
    if options.fit_order < 0:
        return rows, None
    fits = line_fits(parts[len(SUMS):].sum(axis=-1), order=options.fit_order,
                     min_count=max(options.min_count, 2 * correlation), correlation=correlation)
    return rows, fits


def _per_row(values: np.ndarray, like: da.Array, dtype) -> da.Array:
    """One value per row as an (H, 1) array in the row chunks of ``like`` (broadcasts along rows)."""
    return da.from_array(np.asarray(values, dtype)[:, None], chunks=(like.chunks[0], (1,)))


def _hole_block(stack: np.ndarray, *, max_hole: int, edge: int) -> np.ndarray:
    dx, dy, px, py, status, sx, sy = stack
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    target = (status == Status.NO_TEXTURE) | (status == Status.BLUNDER)
    cx, cy, nx, ny, ok = hole_estimates(dx - px, dy - py, sx * sx, sy * sy, usable, target, max_hole=max_hole, edge=edge)
    return np.stack([cx, cy, nx, ny, ok, ok, ok]).astype(np.float32)


def _along_lines(block, field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], depth: int,
                 **kwargs) -> da.Array:
    """``block`` on the stack ``(dx, dy, px, py, status, sigma_x, sigma_y)`` of every tile with
    ``depth`` columns more on either side (lazy, (7, H, W) float32, the field's tiles).

    A tile reading its rows that far beyond its edges gives the same result for any tiling.
    """
    stack = da.stack([field["dx"], field["dy"], polynomial[0], polynomial[1], field["status"].astype(np.float32),
                      field["sigma_x"], field["sigma_y"]])
    stack = stack.astype(np.float32).rechunk({0: 7})
    out = da.map_overlap(block, stack, depth={0: 0, 1: 0, 2: depth}, boundary="none", dtype=np.float32, **kwargs)
    # map_overlap merges a block narrower than the depth into its neighbour: back to the tiles
    return out.rechunk({1: field["dx"].chunks[0], 2: field["dx"].chunks[1]})


def hole_estimates_lazy(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], options: LineOptions) -> da.Array:
    """:func:`geocoder.quality.lines.hole_estimates` over the whole field (lazy, (7, H, W) float32:
    ``cx, cy, nx, ny, ok`` and ``ok`` twice more).

    One task per tile reads its rows with ``max_hole + edge`` columns more on either side,
    so a hole that crosses a tile's edge sees both of its ends: the same for any tiling.
    """
    return _along_lines(_hole_block, field, polynomial, options.max_hole + options.edge + 1,
                        max_hole=options.max_hole, edge=options.edge)


def apply_corrections(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], rows: LineCorrection,
                      options: LineOptions = LineOptions()) -> dict[str, da.Array]:
    """The field with every unmatched pixel of a corrected row estimated (lazy).

    Pixels flagged ``NO_TEXTURE`` or ``BLUNDER`` in a hole of at most ``options.max_hole``
    pixels bounded by usable pixels on both sides of their line take the polynomial plus the
    residual interpolated between the hole's ends (:func:`hole_estimates_lazy`); the others in a
    row with a correction, between the first and last column its correction may reach, the
    polynomial plus the row's correction. Both get status ``ESTIMATED`` and their sigma; all
    other pixels are unchanged.

    Parameters
    ----------
    field : dict of dask.array.Array
        ``dx``, ``dy``, ``status``, ``sigma_x``, ``sigma_y`` (and others, passed through).
    polynomial : tuple of dask.array.Array
        The global polynomial's ``dx, dy``.
    rows : LineCorrection
        From :func:`row_corrections`.
    options : LineOptions
        ``max_hole`` and ``edge`` of the interpolation across holes.

    Returns
    -------
    dict of dask.array.Array
        The same keys as ``field``.
    """
    def column(values: np.ndarray) -> da.Array:
        return _per_row(values, field["dx"], np.float32)

    status = field["status"]
    cols = da.arange(field["dx"].shape[1], chunks=field["dx"].chunks[1])[None, :]
    within = (cols >= column(np.nan_to_num(rows.first, nan=np.inf))) & (cols <= column(np.nan_to_num(rows.last, nan=-np.inf)))
    target = (status == Status.NO_TEXTURE) | (status == Status.BLUNDER)
    holes = hole_estimates_lazy(field, polynomial, options)
    # a hole needs its ends' noise or its line's spread for a sigma
    known = (da.isfinite(holes[2]) & da.isfinite(holes[3])) | (column(np.isfinite(rows.sx) & np.isfinite(rows.sy)) > 0)
    by_hole = target & (holes[4] > 0) & known
    by_line = target & within & ~by_hole
    est = by_hole | by_line
    out = dict(field)
    for k, (c, corr, sig) in enumerate((("dx", rows.cx, rows.sx), ("dy", rows.cy, rows.sy))):
        poly = polynomial[k]
        line = column(np.nan_to_num(corr))
        spread = column(np.nan_to_num(sig, nan=np.inf)) ** 2  # how far the line is from one shift
        noise = holes[2 + k]
        # how much of the ends' departure from the line's mean to keep: all of it where the line
        # is far from one shift, none where the ends differ from the mean by their noise only
        keep = da.where(np.isfinite(spread), spread / da.maximum(spread + noise, 1e-12), 1.0)
        value = line + keep * (holes[k] - line)
        out[c] = da.where(by_hole, poly + value, da.where(by_line, poly + line, field[c])).astype(np.float32)
        s = f"sigma_{c[1]}"
        # the posterior variance of the shrunk departure, keep * noise (= (1 - keep) * spread);
        # with nothing known of the ends' noise (keep = 0), the line's spread
        hole_sigma = da.sqrt(da.where(keep > 0, keep * noise, spread))
        out[s] = da.where(by_hole, hole_sigma, da.where(by_line, column(sig), field[s])).astype(np.float32)
    out["status"] = da.where(est, np.uint8(Status.ESTIMATED), status).astype(np.uint8)
    return out


def _smooth_block(stack: np.ndarray, *, window: int, correlation: int) -> np.ndarray:
    dx, dy, px, py, status, sx, sy = stack
    matched = status == Status.MATCHED
    rx, ry, sgx, sgy = smooth_matches(dx - px, dy - py, sx, sy, matched, window=window, correlation=correlation)
    return np.stack([px + rx, py + ry, sgx, sgy, status, status, status]).astype(np.float32)


def smooth_field(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], options: LineOptions, *,
                 correlation: int) -> dict[str, da.Array]:
    """The matched pixels smoothed along their lines (:func:`geocoder.quality.lines.smooth_matches`; lazy).

    One task per tile reads its rows with half a window more on either side, so the result
    does not depend on the tiling. Only ``MATCHED`` pixels change (value and sigma).

    Parameters
    ----------
    field : dict of dask.array.Array
        ``dx``, ``dy``, ``status``, ``sigma_x``, ``sigma_y`` (and others, passed through).
    polynomial : tuple of dask.array.Array
        The global polynomial's ``dx, dy``.
    options : LineOptions
        ``smooth``: the window (0: the field is returned as it is).
    correlation : int
        Template length along the line (px).

    Returns
    -------
    dict of dask.array.Array
        The same keys as ``field``.
    """
    if not options.smooth:
        return field
    out = _along_lines(_smooth_block, field, polynomial, options.smooth // 2 + 1, window=options.smooth,
                       correlation=correlation)
    res = dict(field)
    for k, name in enumerate(("dx", "dy", "sigma_x", "sigma_y")):
        res[name] = out[k]
    return res


def shrink_to_lines(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array],
                    fits: LineFit | None) -> dict[str, da.Array]:
    """Every match pulled toward its line's fit by how little the line departs from it (lazy).

    A matched pixel's residual ``r`` (after the polynomial) becomes ``f + k (r - f)``, ``f``
    its line's fit (:func:`geocoder.quality.lines.line_fits`) at its column and
    ``k = tau2 / (tau2 + sigma^2)``: where the line follows the fit to the matches' noise
    (``tau2`` small: turbulence that moves the whole line, or nothing the polynomial does not
    know) the pixel takes the fit, which rests on the whole line; where the line departs
    from it (relief, a local distortion) the match stands. Its sigma is the posterior one,
    ``k sigma^2 + (1 - k)^2 v_fit``, with ``v_fit`` the fit's variance at that column. Only
    ``MATCHED`` pixels of rows with a fit change; the sums behind the fits are added over
    whole rows, so the result does not depend on the tiling.

    Parameters
    ----------
    field : dict of dask.array.Array
        ``dx``, ``dy``, ``status``, ``sigma_x``, ``sigma_y`` (and others, passed through).
    polynomial : tuple of dask.array.Array
        The global polynomial's ``dx, dy``.
    fits : LineFit or None
        From :func:`row_corrections` (None: the field is returned as it is).

    Returns
    -------
    dict of dask.array.Array
        The same keys as ``field``.
    """
    if fits is None or not fits.ok.any():
        return field
    dx = field["dx"]
    width = dx.shape[1]
    u = da.from_array(line_coordinate(np.arange(width), width), chunks=(dx.chunks[1],))
    table = da.from_array(fit_table(fits), chunks=(dx.chunks[0], (len(FIT_TABLE),)))
    stack = da.blockwise(_shrink_block, "kij", dx, "ij", field["dy"], "ij", polynomial[0], "ij", polynomial[1], "ij",
                         field["status"], "ij", field["sigma_x"], "ij", field["sigma_y"], "ij", u, "j", table, "ip",
                         new_axes={"k": 4}, concatenate=True, dtype=np.float32)
    out = dict(field)
    for k, name in enumerate(("dx", "dy", "sigma_x", "sigma_y")):
        out[name] = stack[k]
    return out


def _shrink_block(dx, dy, px, py, status, sx, sy, u, table) -> np.ndarray:
    return np.stack(shrink_block(dx, dy, px, py, status == Status.MATCHED, sx, sy, u, table))
