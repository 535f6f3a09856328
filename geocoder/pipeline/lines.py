"""Per-line estimates for the unmatched pixels of a dense field, on Dask (:mod:`geocoder.quality.lines`).

Two steps: the residual sums of every row (one task per tile, added across the tiles of a
row band) are gathered, a few numbers per row; from them the client computes each row's
correction and fit, and :func:`line_field` applies them with one task per tile that reads
its rows of the stored field with the columns its steps reach (a graph of some ten
elementwise tasks per tile and halos passed between workers took twice as long).
"""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np

from ..kernels.polynomial import PolyMap
from ..quality.lines import (
    FIT_SUMS,
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


def tile_sums(dx, dy, px, py, status, sigma_x, sigma_y, *, col0: int, width: int) -> np.ndarray:
    """The per-row sums of one tile of a dense field that :func:`row_corrections` adds up:
    :data:`~geocoder.quality.lines.SUMS` then :data:`~geocoder.quality.lines.FIT_SUMS`, shape
    ``(n, rows, 1)``; ``dx, dy`` the field (the polynomial where not usable), ``px, py`` the
    polynomial, ``col0`` the tile's first column in a scene ``width`` wide."""
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    lines = line_sums(dx, dy, px, py, usable, sigma_x, sigma_y, col0)
    fits = fit_sums(dx - px, dy - py, sigma_x, sigma_y, status == Status.MATCHED, col0=col0, width=width)
    return np.concatenate([lines, fits])[..., None]


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


def _block_sums(dx, dy, px, py, status, sigma_x, sigma_y, block_info=None, *, width: int):
    col0 = block_info[0]["array-location"][1][0]
    return tile_sums(dx, dy, px, py, status, sigma_x, sigma_y, col0=col0, width=width)


def row_corrections(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], options: LineOptions,
                    *, correlation: int = 51, sums: np.ndarray | None = None) -> tuple[LineCorrection, LineFit | None]:
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
        n = len(SUMS) + len(FIT_SUMS)
        sums = da.map_blocks(_block_sums, dx, field["dy"], polynomial[0], polynomial[1], field["status"],
                             field["sigma_x"], field["sigma_y"], new_axis=0,
                             chunks=((n,), dx.chunks[0], (1,) * len(dx.chunks[1])), dtype=np.float64,
                             width=dx.shape[1])
        (sums,) = dask.compute(sums)
    rows = line_corrections(combine_sums(sums[: len(SUMS)]), min_count=options.min_count, max_gap=options.max_gap,
                            end_rows=options.end_rows)
    if options.fit_order < 0:
        return rows, None
    fits = line_fits(sums[len(SUMS):].sum(axis=-1), order=options.fit_order,
                     min_count=max(options.min_count, 2 * correlation), correlation=correlation)
    return rows, fits


#: Columns of the per-row table of :func:`line_field` (from :class:`LineCorrection`), before the
#: fits' :data:`~geocoder.quality.lines.FIT_TABLE` columns.
ROW_TABLE = ("first", "last", "cx", "cy", "sx", "sy")


def line_field(store: str, chunks: tuple[tuple[int, ...], tuple[int, ...]], mapping: PolyMap, rows: LineCorrection,
               fits: LineFit | None, options: LineOptions, *, correlation: int) -> dict[str, da.Array]:
    """The stored dense field with the per-line steps applied, one task per tile (lazy).

    In order, as :mod:`geocoder.quality.lines` defines them: every unmatched pixel of a
    corrected row estimated (across a hole of at most ``options.max_hole`` px from the
    residuals at its ends, else from the row's correction; status ``ESTIMATED`` with its
    sigma), every match shrunk toward its line's fit (``fits``, None: not), and with
    ``options.smooth`` the matches smoothed along their lines. Pixels without a usable match
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
    table = np.column_stack([rows.first, rows.last, rows.cx, rows.cy, rows.sx, rows.sy,
                             *([fit_table(fits)] if shrink else [])]).astype(np.float64)
    tab = da.from_array(table.T[:, :, None], chunks=((table.shape[1],), chunks[0], (1,)))
    cols = da.arange(width, chunks=chunks[1]).reshape(1, 1, width)
    token = dask.base.tokenize(store, mapping.to_dict(), table, options, correlation, chunks)
    stack = da.map_blocks(_line_block, tab, cols, chunks=((6,), *chunks), dtype=np.float32, name=f"line-field-{token}",
                          store=store, width=width, mapping=mapping, options=options, shrink=shrink,
                          correlation=correlation)
    out = {name: stack[k] for k, name in enumerate(("dx", "dy", "status", "sigma_x", "sigma_y", "correlation"))}
    out["status"] = out["status"].astype(np.uint8)
    return out


def _line_block(table: np.ndarray, cols: np.ndarray, block_info=None, *, store: str, width: int, mapping: PolyMap,
                options: LineOptions, shrink: bool, correlation: int) -> np.ndarray:
    import zarr

    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    smooth = options.smooth // 2 + 1 if options.smooth else 0
    reach = options.max_hole + options.edge + 1 + smooth
    a, b = max(c0 - reach, 0), min(c1 + reach, width)
    f = zarr.open_group(store, mode="r")["field"][:, r0:r1, a:b]
    dx, dy, px, py, status, good = field_window(f, mapping, (r0, r1), (a, b))
    sx, sy, rho = f[3], f[4], f[5]
    holes = _hole_block(np.stack([dx, dy, px, py, status.astype(np.float32), sx, sy]).astype(np.float32),
                        max_hole=options.max_hole, edge=options.edge)
    t = table[:, :, 0].T  # (rows of the block, ROW_TABLE + FIT_TABLE)
    rows = t[:, : len(ROW_TABLE)]
    # the lines' ends from the whole read; the rest only on the columns of the core and of its
    # smoothing, whose estimates and shrinkage are exact
    ends = _line_ends_xy(dx, dy, px, py, sx, sy, good, rows, np.arange(a, b), band=options.edge)
    sa, sb = max(c0 - smooth, 0) - a, min(c1 + smooth, width) - a
    w = (slice(None), slice(sa, sb))
    dx, dy, px, py, status, sx, sy, rho = (v[w] for v in (dx, dy, px, py, status, sx, sy, rho))
    cols = np.arange(a + sa, a + sb)
    dx, dy, sx, sy, status = _estimates(dx, dy, px, py, status, sx, sy, holes[:, :, sa:sb], rows, cols, ends,
                                        reach=options.max_hole)
    if shrink:
        u = line_coordinate(cols, width)
        dx, dy, sx, sy = shrink_block(dx, dy, px, py, status == Status.MATCHED, sx, sy, u, t[:, len(ROW_TABLE):])
    if smooth:
        stack = np.stack([dx, dy, px, py, status.astype(np.float32), sx, sy]).astype(np.float32)
        dx, dy, sx, sy = _smooth_block(stack, window=options.smooth, correlation=correlation)
    core = (slice(None), slice(c0 - a - sa, c1 - a - sa))
    return np.stack([dx[core], dy[core], status[core].astype(np.float32), sx[core], sy[core], rho[core]]).astype(np.float32)


def _hole_block(stack: np.ndarray, *, max_hole: int, edge: int) -> np.ndarray:
    dx, dy, px, py, status, sx, sy = stack
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    target = (status == Status.NO_TEXTURE) | (status == Status.BLUNDER)
    cx, cy, nx, ny, ok = hole_estimates(dx - px, dy - py, sx * sx, sy * sy, usable, target, max_hole=max_hole, edge=edge)
    return np.stack([cx, cy, nx, ny, ok]).astype(np.float32)


#: Fewest usable pixels in the band inside a line's end for an estimate beyond that end.
MIN_END_COUNT = 8


def _line_ends(res: np.ndarray, noise: np.ndarray, usable: np.ndarray, first: np.ndarray, last: np.ndarray,
               cols: np.ndarray, *, band: int, min_count: int = MIN_END_COUNT) -> tuple[np.ndarray, ...]:
    """Mean of ``res`` (h, w), its variance about it and the mean of ``noise`` (the matches'
    variances) over the usable pixels within ``band`` columns inside each end of every row
    (``first``, ``last``: its first and last usable column), shape (2, h) each (left end,
    right end); NaN where fewer than ``min_count``.
    The band is gathered into ``band`` columns of its own, so the sums do not depend on the
    window (``cols``) they are read from."""
    h, w = res.shape
    offsets = np.arange(band)
    means, variances, noises = [], [], []
    for start in (np.nan_to_num(first, nan=-1e9) - cols[0], np.nan_to_num(last, nan=-1e9) - cols[0] - band + 1):
        idx = start.astype(np.int64)[:, None] + offsets[None, :]
        inside = (idx >= 0) & (idx < w)
        idx = np.clip(idx, 0, w - 1)
        m = np.take_along_axis(usable, idx, axis=1) & inside
        r = np.take_along_axis(res, idx, axis=1)
        n = m.sum(axis=1)
        safe = np.maximum(n, 1)
        mean = np.where(m, r, 0.0).sum(axis=1) / safe
        var = np.where(m, (r - mean[:, None]) ** 2, 0.0).sum(axis=1) / safe
        nv = np.where(m, np.take_along_axis(noise, idx, axis=1), 0.0).sum(axis=1) / safe
        ok = n >= min_count
        means.append(np.where(ok, mean, np.nan))
        variances.append(np.where(ok, var, np.nan))
        noises.append(np.where(ok, nv, np.nan))
    return np.array(means), np.array(variances), np.array(noises)


def _line_ends_xy(dx, dy, px, py, sx, sy, usable, rows: np.ndarray, cols: np.ndarray, *, band: int) -> list[tuple]:
    """:func:`_line_ends` of the residuals in x and in y (``rows``: :data:`ROW_TABLE`)."""
    first, last = rows.T[:2]
    with np.errstate(invalid="ignore", divide="ignore"):
        return [_line_ends(d - p, sg.astype(np.float64) ** 2, usable, first, last, cols, band=band)
                for d, p, sg in ((dx, px, sx), (dy, py, sy))]


def _estimates(dx, dy, px, py, status, sx, sy, holes, rows: np.ndarray, cols: np.ndarray, ends: list[tuple], *,
               reach: int):
    """Every unmatched pixel of a corrected row estimated (float32 ``dx, dy, sigma_x, sigma_y``, uint8 ``status``).

    Pixels flagged ``NO_TEXTURE`` or ``BLUNDER`` in a hole bounded by usable pixels on both
    sides of their line (``holes``: :func:`_hole_block`) take the polynomial plus the residual
    interpolated between the hole's ends; the others in a row with a correction, between the
    first and last column its correction may reach, the polynomial plus the row's correction;
    those at most ``reach`` px beyond that first or last column (the line's ends: the
    template's margin, an untextured stretch), the polynomial plus the mean residual of the
    usable pixels within ``band`` columns inside that end (its departure from the line's mean
    shrunk as a hole's), its variance their spread about it plus the line's (how far the
    residual may move between the band and the pixel). The residual near a line's end
    departs from the line's mean by up to a pixel where the global polynomial fits worst, at
    the scene's edges: measured on the issue 14 cases, 0.5 px RMSE with the line's mean,
    0.06-0.1 with the end's. The ends' bands lie inside
    the columns :func:`line_field` reads (``max_hole + edge + 1`` each side), so the result
    does not depend on the tiling. ``rows`` is the :data:`ROW_TABLE` of the block's rows,
    ``cols`` the block's columns, ``ends`` the lines' ends (:func:`_line_ends_xy`, from all
    the columns read: the bands may lie outside ``cols``).
    """
    def column(values: np.ndarray) -> np.ndarray:
        return np.asarray(values, np.float32)[:, None]

    first, last, cx, cy, sgx, sgy = rows.T
    within = (cols[None, :] >= column(np.nan_to_num(first, nan=np.inf))) & \
        (cols[None, :] <= column(np.nan_to_num(last, nan=-np.inf)))
    target = (status == Status.NO_TEXTURE) | (status == Status.BLUNDER)
    # a hole needs its ends' noise or its line's spread for a sigma
    known = (np.isfinite(holes[2]) & np.isfinite(holes[3])) | (column(np.isfinite(sgx) & np.isfinite(sgy)) > 0)
    by_hole = target & (holes[4] > 0) & known
    by_line = target & within & ~by_hole
    c = cols[None, :].astype(np.float64)
    before = (c < np.nan_to_num(first, nan=-np.inf)[:, None]) & (c >= np.nan_to_num(first, nan=np.inf)[:, None] - reach)
    after = (c > np.nan_to_num(last, nan=np.inf)[:, None]) & (c <= np.nan_to_num(last, nan=-np.inf)[:, None] + reach)
    out = []
    with np.errstate(invalid="ignore", divide="ignore"):  # inf / inf where a line has no spread: not kept
        known_end = np.isfinite(ends[0][0]) & np.isfinite(ends[1][0])  # (2, h): left end, right end
        by_end = target & ~by_hole & ~by_line & ((before & known_end[0][:, None]) | (after & known_end[1][:, None]))
        for k, (d, p, corr, sig, s) in enumerate(((dx, px, cx, sgx, sx), (dy, py, cy, sgy, sy))):
            line = column(np.nan_to_num(corr))
            spread = column(np.nan_to_num(sig, nan=np.inf)) ** 2  # how far the line is from one shift
            noise = holes[2 + k]
            # how much of the ends' departure from the line's mean to keep: all of it where the line
            # is far from one shift, none where the ends differ from the mean by their noise only
            keep = np.where(np.isfinite(spread), spread / np.maximum(spread + noise, 1e-12), 1.0)
            value = line + keep * (holes[k] - line)
            mean, var, end_noise = (np.where(before, e[0][:, None], e[1][:, None]) for e in ends[k])
            # the end's departure from the line's mean, shrunk as a hole's: kept where the line is
            # far from one shift, not where the end differs from the mean by its matches' noise
            end_keep = np.where(np.isfinite(spread), spread / np.maximum(spread + end_noise, 1e-12), 1.0)
            end_value = line + end_keep * (mean - line)
            # the band's scatter, and how far the residual may move from the band to the pixel: at
            # most what the line departs from one shift (its spread)
            end_sigma = np.sqrt(var + column(np.nan_to_num(sig)) ** 2)
            out.append(np.where(by_hole, p + value, np.where(by_line, p + line, np.where(by_end, p + end_value, d)))
                       .astype(np.float32))
            # the posterior variance of the shrunk departure, keep * noise (= (1 - keep) * spread);
            # with nothing known of the ends' noise (keep = 0), the line's spread
            hole_sigma = np.sqrt(np.where(keep > 0, keep * noise, spread))
            out.append(np.where(by_hole, hole_sigma, np.where(by_line, column(sig), np.where(by_end, end_sigma, s)))
                       .astype(np.float32))
    status = np.where(by_hole | by_line | by_end, np.uint8(Status.ESTIMATED), status).astype(np.uint8)
    return out[0], out[2], out[1], out[3], status


def _smooth_block(stack: np.ndarray, *, window: int, correlation: int) -> np.ndarray:
    dx, dy, px, py, status, sx, sy = stack
    matched = status == Status.MATCHED
    rx, ry, sgx, sgy = smooth_matches(dx - px, dy - py, sx, sy, matched, window=window, correlation=correlation)
    return np.stack([px + rx, py + ry, sgx, sgy]).astype(np.float32)
