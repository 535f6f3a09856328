"""Per-line estimates for the unmatched pixels of a dense field, on Dask (:mod:`geocoder.quality.lines`).

Two steps: the residual sums of every row (one task per tile, added across the tiles of a
row band) are gathered, a few numbers per row; the corrections computed from them on the
client then enter the lazy output arrays as one column per row band.
"""

from __future__ import annotations

import dask
import dask.array as da
import numpy as np

from ..quality.lines import SUMS, LineCorrection, LineOptions, combine_sums, line_corrections, line_sums
from ..status import Status


def _block_sums(dx, dy, px, py, status, sigma_x, sigma_y, block_info=None):
    usable = (status == Status.MATCHED) | (status == Status.FILLED)
    col0 = block_info[0]["array-location"][1][0]
    return line_sums(dx, dy, px, py, usable, sigma_x, sigma_y, col0)[..., None]


def row_corrections(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], options: LineOptions) -> LineCorrection:
    """Compute the correction of every row of a dense field (its matched and filled pixels).

    Parameters
    ----------
    field : dict of dask.array.Array
        ``dx``, ``dy``, ``status`` of :func:`geocoder.pipeline.dense.dense_field`.
    polynomial : tuple of dask.array.Array
        The global polynomial's ``dx, dy`` on the same grid.
    options : LineOptions

    Returns
    -------
    LineCorrection
    """
    dx = field["dx"]
    parts = da.map_blocks(_block_sums, dx, field["dy"], polynomial[0], polynomial[1], field["status"], field["sigma_x"],
                          field["sigma_y"], new_axis=0, chunks=((len(SUMS),), dx.chunks[0], (1,) * len(dx.chunks[1])),
                          dtype=np.float64)
    (parts,) = dask.compute(parts)
    sums = combine_sums(parts)
    return line_corrections(sums, min_count=options.min_count, max_gap=options.max_gap)


def apply_corrections(field: dict[str, da.Array], polynomial: tuple[da.Array, da.Array], rows: LineCorrection) -> dict[str, da.Array]:
    """The field with every unmatched pixel of a corrected row estimated (lazy).

    Pixels flagged ``NO_TEXTURE`` or ``BLUNDER`` in a row with a correction, between the
    first and last column its correction may reach, take the polynomial plus the
    correction, status ``ESTIMATED`` and the correction's sigma; all other pixels are
    unchanged.

    Parameters
    ----------
    field : dict of dask.array.Array
        ``dx``, ``dy``, ``status``, ``sigma_x``, ``sigma_y`` (and others, passed through).
    polynomial : tuple of dask.array.Array
        The global polynomial's ``dx, dy``.
    rows : LineCorrection
        From :func:`row_corrections`.

    Returns
    -------
    dict of dask.array.Array
        The same keys as ``field``.
    """
    chunks = (field["dx"].chunks[0], (1,))

    def column(values: np.ndarray) -> da.Array:
        return da.from_array(values.astype(np.float32)[:, None], chunks=chunks)

    status = field["status"]
    cols = da.arange(field["dx"].shape[1], chunks=field["dx"].chunks[1])[None, :]
    within = (cols >= column(np.nan_to_num(rows.first, nan=np.inf))) & (cols <= column(np.nan_to_num(rows.last, nan=-np.inf)))
    est = ((status == Status.NO_TEXTURE) | (status == Status.BLUNDER)) & within
    out = dict(field)
    out["dx"] = da.where(est, polynomial[0] + column(np.nan_to_num(rows.cx)), field["dx"]).astype(np.float32)
    out["dy"] = da.where(est, polynomial[1] + column(np.nan_to_num(rows.cy)), field["dy"]).astype(np.float32)
    out["status"] = da.where(est, np.uint8(Status.ESTIMATED), status).astype(np.uint8)
    out["sigma_x"] = da.where(est, column(rows.sx), field["sigma_x"]).astype(np.float32)
    out["sigma_y"] = da.where(est, column(rows.sy), field["sigma_y"]).astype(np.float32)
    return out
