"""Per-scan-line estimates of a block scene's dense field where nothing was matched.

A block scene's dense field lives on the reference's grid (reference pixel -> scene pixel),
but its turbulence belongs to the scene's scan lines: an airborne line scanner's roll and
pitch shift a whole scene row at once, and a rotated scene's row crosses many reference rows.
Where nothing was matched, the residual ``field - model`` is modelled as ``P(u, v) + t(row)``:

* ``P``, a low-order polynomial of the scene column ``u`` (and ``u`` times powers of the scene
  row ``v``, :data:`geocoder.quality.line_fits.TERMS`): how the adjusted model errs along the rows
  (with sparse control the model of a scene far from it can be pixels off, smoothly). It is fitted to the matches of
  every row about that row's own mean, so the rows' shifts do not enter it;
* ``t``, each scene row's own shift: the mean residual of its matches after ``P``; rows without
  matches interpolated across short gaps (:func:`geocoder.quality.lines.line_corrections`).

The matches are gathered by the scene row the adjusted model puts them on
(:func:`scene_line_sums`, added over the footprint's row bands: a few dozen numbers per scene
row), solved on one node (:func:`line_table`, the same solution as the registration's
:func:`geocoder.pipeline.lines.row_corrections`), and every unmatched pixel of the scene whose row
has a shift takes ``model + P + t`` (:func:`line_estimates`), status ``ESTIMATED``, along the
whole row: roll and pitch move the whole line, and ``P`` is smooth. Where a scene shares only
the ends of its rows with its refined neighbours (an outer strip's middle scene), this carries
each row's shift across the row; the nearest match of the same *reference* row could not.
"""

from __future__ import annotations

import numpy as np

from ..quality.line_fits import (
    NTERM_SUMS,
    TERMS,
    smooth_fit,
    smooth_values,
    term_values,
    terms,
)
from ..quality.lines import (
    SUMS,
    combine_sums,
    line_corrections,
)
from ..status import Status

__all__ = ["combine_line_sums", "line_estimates", "line_table", "scene_line_sums"]


def _scene_lines(pdx: np.ndarray, pdy: np.ndarray, row0: int, col0: int) -> tuple[np.ndarray, np.ndarray]:
    """Scene row (nearest) and scene column of every pixel of a block, as the model puts it."""
    h, w = pdx.shape
    ry = np.arange(row0, row0 + h, dtype=np.float64)[:, None]
    rx = np.arange(col0, col0 + w, dtype=np.float64)[None, :]
    return np.rint(ry + pdy).astype(np.int64), rx + pdx


#: Rows of :func:`scene_line_sums`: :data:`~geocoder.quality.lines.SUMS`, then the moments of
#: the smooth part's terms (:func:`geocoder.quality.line_fits.term_sums`).
NSUMS = len(SUMS) + NTERM_SUMS


def scene_line_sums(dx: np.ndarray, dy: np.ndarray, status: np.ndarray, pdx: np.ndarray, pdy: np.ndarray, *,
                    row0: int, col0: int, shape: tuple[int, int]) -> np.ndarray:
    """Sums of the matched pixels of a block, per scene row (:data:`NSUMS` quantities).

    Parameters
    ----------
    dx, dy : ndarray (h, w)
        The dense field (reference pixel -> scene pixel) on a block of the reference grid.
    status : ndarray (h, w)
        Its :class:`~geocoder.status.Status`; only ``MATCHED`` pixels count.
    pdx, pdy : ndarray (h, w)
        The adjusted model's displacement on the same block.
    row0, col0 : int
        The block's first reference pixel (row, column).
    shape : (int, int)
        The scene's rows and columns.

    Returns
    -------
    ndarray (NSUMS, rows), float64
        Per scene row: :data:`~geocoder.quality.lines.SUMS` of the residuals ``d - p`` (no
        sigmas: the neighbours' errors are not in the matches', see
        :mod:`geocoder.mosaic.dense_neighbours`; ``first``, ``last`` in scene columns), then
        the terms' moments as :func:`~geocoder.quality.line_fits.term_sums` has them, by scene row.
        Blocks add up (:func:`combine_line_sums`).
    """
    lines = shape[0]
    line, col = _scene_lines(pdx, pdy, row0, col0)
    use = (np.asarray(status) == Status.MATCHED) & (line >= 0) & (line < lines)
    line, col = line[use], col[use]
    ex = np.asarray(dx, np.float64)[use] - pdx[use]
    ey = np.asarray(dy, np.float64)[use] - pdy[use]
    values = [None, ex, ey, ex * ex, ey * ey, None, None, None, None, None,
              *term_values(terms(col, line.astype(np.float64), shape), ex, ey)]
    out = np.zeros((NSUMS, lines))
    out[0] = np.bincount(line, minlength=lines)
    for k, v in enumerate(values):
        if v is not None:
            out[k] = np.bincount(line, weights=v, minlength=lines)
    out[8], out[9] = np.inf, -np.inf
    np.minimum.at(out[8], line, col)
    np.maximum.at(out[9], line, col)
    return out


def combine_line_sums(parts: np.ndarray) -> np.ndarray:
    """:func:`scene_line_sums` of whole scene rows from those of blocks (last axis)."""
    out = parts.sum(axis=-1)
    out[: len(SUMS)] = combine_sums(parts[: len(SUMS)])
    return out


def line_table(sums: np.ndarray, *, min_count: int, max_gap: int, end_rows: int) -> np.ndarray:
    """The corrections of a scene: the smooth part along its rows and a shift per row
    (:func:`geocoder.quality.line_fits.smooth_fit`, :func:`geocoder.quality.lines.line_corrections`).

    Returns
    -------
    ndarray (4 + 2 len(TERMS), rows)
        ``cx, cy, first, last`` per row (NaN where a row has no shift), then the smooth part's
        coefficients in x and in y (repeated along the rows, so the graph carries one array).
    """
    coef, adjusted = smooth_fit(sums[: len(SUMS)], sums[len(SUMS):])
    rows = line_corrections(adjusted, min_count=min_count, max_gap=max_gap, end_rows=end_rows)
    return np.concatenate([np.stack([rows.cx, rows.cy, rows.first, rows.last]),
                           np.repeat(coef.reshape(-1, 1), sums.shape[1], axis=1)])


def line_estimates(dx: np.ndarray, dy: np.ndarray, status: np.ndarray, pdx: np.ndarray, pdy: np.ndarray,
                   table: np.ndarray, *, row0: int, col0: int, shape: tuple[int, int]) -> np.ndarray:
    """Unmatched pixels of a block: the model plus the smooth part and their row's shift.

    Parameters
    ----------
    dx, dy, status, pdx, pdy : ndarray (h, w)
        As for :func:`scene_line_sums`; ``FILLED`` pixels (short holes the post-filter
        interpolated) are kept as they are.
    table : ndarray
        :func:`line_table` of the scene.
    row0, col0 : int
        The block's first reference pixel.
    shape : (int, int)
        The scene's rows and columns: pixels the model puts outside it are left alone.

    Returns
    -------
    ndarray (3, h, w), float32
        ``dx, dy, status``; the estimated pixels ``ESTIMATED``.
    """
    line, col = _scene_lines(pdx, pdy, row0, col0)
    status = np.asarray(status)
    inside = (line >= 0) & (line < shape[0]) & (col >= -0.5) & (col <= shape[1] - 0.5)
    at = np.clip(line, 0, shape[0] - 1)
    cx, cy = table[0][at], table[1][at]
    coef = table[4:, 0].reshape(2, len(TERMS))
    estimate = inside & (status != Status.MATCHED) & (status != Status.FILLED) & np.isfinite(cx)
    smooth = smooth_values(coef, col, line.astype(np.float64), shape)
    out_dx = np.where(estimate, pdx + smooth[0] + np.nan_to_num(cx), dx)
    out_dy = np.where(estimate, pdy + smooth[1] + np.nan_to_num(cy), dy)
    out_status = np.where(estimate, Status.ESTIMATED, status)
    return np.stack([out_dx, out_dy, out_status]).astype(np.float32)
