"""Per-line estimates for the unmatched pixels of a dense field, on Dask (:mod:`geocoder.quality.lines`).

Two steps: the residual sums of every row (one task per tile, added across the tiles of a
row band) are gathered, a few numbers per row; from them the client computes each row's
correction and fit, and :func:`line_field` applies them with one task per tile that reads
its rows of the stored field with the columns its steps reach (a graph of some ten
elementwise tasks per tile and halos passed between workers took twice as long).
"""

from __future__ import annotations

from dataclasses import replace

import dask
import dask.array as da
import numpy as np

from ..kernels.polynomial import PolyMap
from ..quality.line_fits import (
    FIT_SUMS,
    FIT_TABLE,
    NTERM_SUMS,
    LineFit,
    departure_table,
    departures,
    fit_sums,
    fit_table,
    line_coordinate,
    line_fits,
    shrink_block,
    smooth_fit,
    smooth_values,
    term_sums,
)
from ..quality.lines import (
    SUMS,
    LineCorrection,
    LineOptions,
    combine_sums,
    estimate_unmatched,
    hole_estimates,
    line_corrections,
    line_sums,
    smooth_matches,
)
from ..runtime import shared_input
from ..status import Status
from ..storage import open_array
from ..tiles import Window


def tile_sums(dx, dy, px, py, status, sigma_x, sigma_y, *, row0: int, col0: int, shape: tuple[int, int]) -> np.ndarray:
    """The per-row sums of one tile of a dense field that :func:`row_corrections` adds up:
    :data:`~geocoder.quality.lines.SUMS`, :data:`~geocoder.quality.line_fits.FIT_SUMS`, then the
    :func:`~geocoder.quality.line_fits.term_sums`, shape ``(n, rows, 1)``; ``dx, dy`` the field
    (the polynomial where not usable), ``px, py`` the polynomial, ``row0, col0`` the tile's
    first pixel in a scene of ``shape``."""
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    lines = line_sums(dx, dy, px, py, usable, sigma_x, sigma_y, col0)
    fits = fit_sums(dx - px, dy - py, sigma_x, sigma_y, status == Status.MATCHED, col0=col0, width=shape[1])
    moments = term_sums(dx - px, dy - py, usable, row0=row0, col0=col0, shape=shape)
    return np.concatenate([lines, fits, moments])[..., None]


def field_window(stack: np.ndarray, mapping: PolyMap, rows: tuple[int, int], cols: tuple[int, int]) -> tuple:
    """A window of the stored dense field (``stack``: dx, dy, status, ... over ``rows`` x ``cols``)
    as :func:`geocoder.pipeline.dense.dense_field` returns it: float32 ``dx, dy`` (the
    polynomial where not matched or filled), the polynomial ``px, py``, uint8 ``status`` and
    the usable mask."""
    from .resample import poly_grid

    px, py = (poly_grid(mapping, rows, cols, k).astype(np.float32) for k in (0, 1))
    status = stack[2].astype(np.uint8)
    good = (status == Status.MATCHED) | (status == Status.FILLED)
    dx, dy = (np.where(good, stack[k], p).astype(np.float32) for k, p in ((0, px), (1, py)))
    return dx, dy, px, py, status, good


def _block_sums(dx, dy, px, py, status, sigma_x, sigma_y, block_info=None, *, shape: tuple[int, int]):
    (row0, _), (col0, _) = block_info[0]["array-location"]
    return tile_sums(dx, dy, px, py, status, sigma_x, sigma_y, row0=row0, col0=col0, shape=shape)


def row_corrections(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], options: LineOptions,
                    *, correlation: int = 51, line_correlation: int = 1,
                    sums: np.ndarray | None = None) -> tuple[LineCorrection, LineFit | None]:
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
    line_correlation : int
        Template height (rows): how many neighbouring lines share a line's errors
        (:func:`~geocoder.quality.line_fits.shrink_coefficients`).
    sums : ndarray, shape (n, H, tile columns), optional
        The tiles' :func:`tile_sums` side by side, if computed already (by the stored
        post-filter pass, :func:`geocoder.pipeline.dense.dense_field`); else one pass over
        ``field`` computes them.

    Returns
    -------
    LineCorrection, LineFit or None
    """
    if sums is None:
        dx = field["dx"]
        n = len(SUMS) + len(FIT_SUMS) + NTERM_SUMS
        sums = da.map_blocks(_block_sums, dx, field["dy"], polynomial[0], polynomial[1], field["status"],
                             field["sigma_x"], field["sigma_y"], new_axis=0,
                             chunks=((n,), dx.chunks[0], (1,) * len(dx.chunks[1])), dtype=np.float64,
                             shape=dx.shape)
        (sums,) = dask.compute(sums)
    k = len(SUMS) + len(FIT_SUMS)
    coef, adjusted = smooth_fit(combine_sums(sums[: len(SUMS)]), sums[k:].sum(axis=-1))
    rows = replace(line_corrections(adjusted, min_count=options.min_count, max_gap=options.max_gap,
                                    end_rows=options.end_rows, correlation=correlation), smooth=coef)
    if options.fit_order < 0:
        return rows, None
    fits = line_fits(sums[len(SUMS):k].sum(axis=-1), order=options.fit_order,
                     min_count=max(options.min_count, 2 * correlation), correlation=correlation,
                     line_correlation=line_correlation)
    return rows, fits


#: Columns of the per-row table of :func:`line_field` (from :class:`LineCorrection`), before the
#: fits' :data:`~geocoder.quality.line_fits.FIT_TABLE` columns.
ROW_TABLE = ("first", "last", "cx", "cy", "sx", "sy")


def line_field(store: str, chunks: tuple[tuple[int, ...], tuple[int, ...]], mapping: PolyMap, rows: LineCorrection,
               fits: LineFit | None, options: LineOptions, *, correlation: int) -> dict[str, da.Array]:
    """The stored dense field with the per-line steps applied, one task per tile (lazy).

    In order, as :mod:`geocoder.quality.lines` defines them: every match that departs from its
    line beyond its noise flagged ``BLUNDER`` (``options.max_departure``,
    :func:`~geocoder.quality.line_fits.departures`), every unmatched pixel of a
    corrected row estimated (across a hole of at most ``options.max_hole`` px from the
    residuals at its ends, else along the whole row from the smooth part along the lines plus
    the row's shift, :func:`_estimates`; status ``ESTIMATED`` with its sigma), every match
    shrunk toward its line's fit and every filled pixel set on it (``fits``, None: not;
    :func:`~geocoder.quality.line_fits.shrink_block`; a filled pixel of a row without a fit is
    estimated like an unmatched one), and with ``options.smooth`` the
    matches smoothed along their lines. Pixels without a usable match
    start from the polynomial ``mapping``.

    Each task reads its rows of the field (array ``field`` of the state ``store``, written by
    :func:`geocoder.pipeline.dense.dense_field` with ``store=True``) with as many columns on
    either side as the steps reach (``max_hole + edge + 1``, plus ``smooth // 2 + 1``), so the
    result does not depend on the tiling, and computes the polynomial there itself: no task
    reads another's output and no halo crosses between workers.

    Parameters
    ----------
    store : str
        The dense state store holding ``field`` (6, H, W): dx, dy, status, sigma_x, sigma_y, rho.
    chunks : tuple of tuple of int
        Row and column chunks (the tiles) of the result.
    mapping : PolyMap
        The global polynomial.
    rows, fits : LineCorrection, LineFit or None
        From :func:`row_corrections`.
    options : LineOptions
    correlation : int
        Template length along the line (px), for the smoothing.

    Returns
    -------
    dict of dask.array.Array
        ``dx``, ``dy``, ``sigma_x``, ``sigma_y``, ``correlation`` (float32) and ``status`` (uint8).
    """
    shrink = fits is not None and bool(fits.ok.any())
    width = sum(chunks[1])
    depart = options.max_departure > 0
    table = np.column_stack([rows.first, rows.last, rows.cx, rows.cy, rows.sx, rows.sy,
                             *([fit_table(fits)] if shrink else []),
                             *([departure_table(fits, np.column_stack([rows.cx, rows.cy]), rows.own,
                                                np.column_stack([rows.sx, rows.sy]) ** 2)] if depart else [])
                             ]).astype(np.float64)
    # the table as ONE input of every tile's task: with a few inputs in all, the tasks count as
    # root tasks and the scheduler hands them out as workers free up (its queuing), instead of
    # all at once; their results then waited for the output's writes, so a worker held as many
    # tiles as the scene had rows of tiles (167 against 101 MiB held at 8192² and 4096²). On
    # every worker, so that fewer tiles than that are not all drawn to one (shared_input).
    token = dask.base.tokenize(store, mapping.to_dict(), table, fits is not None, options, correlation, chunks, rows.smooth)
    tab = shared_input(table, f"line-table-{token}")
    stack = da.map_blocks(_line_block, tab, chunks=((6,), *chunks), dtype=np.float32, name=f"line-field-{token}",
                          store=store, shape=(sum(chunks[0]), width), mapping=mapping, options=options, shrink=shrink, depart=depart,
                          fitted=fits is not None, correlation=correlation, smooth_part=rows.smooth)
    out = {name: stack[k] for k, name in enumerate(("dx", "dy", "status", "sigma_x", "sigma_y", "correlation"))}
    out["status"] = out["status"].astype(np.uint8)
    return out


def _line_block(table: np.ndarray, block_info=None, *, store: str, shape: tuple[int, int],
                mapping: PolyMap, options: LineOptions, shrink: bool, depart: bool, fitted: bool, correlation: int,
                smooth_part: np.ndarray | None) -> np.ndarray:
    width = shape[1]
    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    smooth = options.smooth // 2 + 1 if options.smooth else 0
    reach = options.max_hole + options.edge + 1 + smooth
    _, _, a, b = Window(r0, r1, c0, c1).grow(0, reach).clip(shape[0], width)
    f = open_array(store, "field")[:, r0:r1, a:b]
    dx, dy, px, py, status, _ = field_window(f, mapping, (r0, r1), (a, b))
    sx, sy, rho = f[3], f[4], f[5]
    t = table[r0:r1]  # (rows of the block, ROW_TABLE [+ FIT_TABLE] [+ the departures' table])
    rows = t[:, : len(ROW_TABLE)]
    part = (np.zeros((2, r1 - r0, b - a)) if smooth_part is None
            else smooth_values(smooth_part, np.arange(a, b)[None, :], np.arange(r0, r1)[:, None], shape))
    if depart:
        off = departures(dx, dy, px, py, part, status == Status.MATCHED, sx, sy, line_coordinate(np.arange(a, b), width),
                         t[:, -len(FIT_TABLE):], k=options.max_departure, floor=options.departure_floor)
        status = np.where(off, np.uint8(Status.BLUNDER), status)
        dx, dy = np.where(off, px, dx), np.where(off, py, dy)
    holes = _hole_block(dx, dy, px, py, status, sx, sy, max_hole=options.max_hole, edge=options.edge)
    # the holes from the whole read; the rest only on the columns of the core and of its
    # smoothing, whose estimates and shrinkage are exact
    sa, sb = max(c0 - smooth, 0) - a, min(c1 + smooth, width) - a
    w = (slice(None), slice(sa, sb))
    dx, dy, px, py, status, sx, sy, rho = (v[w] for v in (dx, dy, px, py, status, sx, sy, rho))
    cols = np.arange(a + sa, a + sb)
    part = part[:, :, sa:sb]
    # a filled pixel is set on its line's fit below; in a row without one it has no sigma and is
    # estimated like an unmatched pixel
    unfitted = None
    if fitted:
        has_fit = t[:, len(ROW_TABLE) : len(ROW_TABLE) + 1] > 0 if shrink else np.zeros((t.shape[0], 1), bool)
        unfitted = (status == Status.FILLED) & ~has_fit
    dx, dy, sx, sy, status = _estimates(dx, dy, px, py, status, sx, sy, holes[:, :, sa:sb], rows, part, unfitted)
    if shrink:
        u = line_coordinate(cols, width)
        dx, dy, sx, sy = shrink_block(dx, dy, px, py, status == Status.MATCHED, sx, sy, u, t[:, len(ROW_TABLE) : len(ROW_TABLE) + len(FIT_TABLE)],
                                      filled=status == Status.FILLED)
    if smooth:
        stack = np.stack([dx, dy, px, py, status.astype(np.float32), sx, sy]).astype(np.float32)
        dx, dy, sx, sy = _smooth_block(stack, window=options.smooth, correlation=correlation)
    core = (slice(None), slice(c0 - a - sa, c1 - a - sa))
    return np.stack([dx[core], dy[core], status[core].astype(np.float32), sx[core], sy[core], rho[core]]).astype(np.float32)


def _hole_block(dx, dy, px, py, status, sx, sy, *, max_hole: int, edge: int) -> np.ndarray:
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    target = (status == Status.NO_TEXTURE) | (status == Status.BLUNDER)
    cx, cy, nx, ny, ok = hole_estimates(dx - px, dy - py, sx * sx, sy * sy, usable, target, max_hole=max_hole, edge=edge)
    return np.stack([cx, cy, nx, ny, ok], dtype=np.float32)


def _estimates(dx, dy, px, py, status, sx, sy, holes, rows: np.ndarray, part: np.ndarray, more=None):
    """Every unmatched pixel of a corrected row estimated (float32 ``dx, dy, sigma_x, sigma_y``, uint8 ``status``).

    A row's estimate is the polynomial plus the smooth part along the lines (``part``,
    :func:`~geocoder.quality.line_fits.smooth_fit` at the block's pixels, ``(2, h, w)``) plus the
    row's shift (:data:`ROW_TABLE`'s ``cx, cy``), along the whole row: roll and pitch move a
    whole scan line, and the smooth part is how the polynomial errs, fitted to every line's
    matches. Its sigma is the row's spread about that (``sx, sy``). Pixels flagged
    ``NO_TEXTURE`` or ``BLUNDER`` (and ``more``, a mask of further pixels to estimate, as the
    filled pixels of rows without a line fit) in a hole bounded by usable pixels on both sides of their line
    (``holes``: :func:`_hole_block`) take the residual interpolated between the hole's ends
    instead, shrunk toward the row's estimate by how far the line is from it beyond the ends'
    noise. Measured on issue 14's cases (``benchmarks/bench_dense_cases.py``): where the
    polynomial alone was 0.7-1.4 px RMSE off (an untextured quarter, the lines' ends),
    0.04-0.09 px.
    """
    target = (status == Status.NO_TEXTURE) | (status == Status.BLUNDER)
    if more is not None:
        target = target | more
    out = np.empty((4, *status.shape), np.float32)
    new_status = status.astype(np.uint8)
    estimate_unmatched(dx, dy, px, py, sx, sy, holes, np.asarray(rows, np.float64), part, target, out, new_status,
                       int(Status.ESTIMATED))
    return out[0], out[1], out[2], out[3], new_status


def _smooth_block(stack: np.ndarray, *, window: int, correlation: int) -> np.ndarray:
    dx, dy, px, py, status, sx, sy = stack
    matched = status == Status.MATCHED
    rx, ry, sgx, sgy = smooth_matches(dx - px, dy - py, sx, sy, matched, window=window, correlation=correlation)
    return np.stack([px + rx, py + ry, sgx, sgy]).astype(np.float32)
