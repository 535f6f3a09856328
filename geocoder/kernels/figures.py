"""A scene's figures from its chunks in one pass each: valid count, range and block-mean overview.

Ingesting a scene, :func:`geocoder.pipeline.register.register` needs the matching band's number
of finite pixels, their minimum and maximum (the content check) and its block mean over
``factor``-pixel squares (the coarse alignment's overview, NaN-aware, incomplete squares at the
right and bottom edge left out as ``xarray``'s ``coarsen(boundary="trim")`` does). Dask's
reductions made each of those its own task per chunk (six per chunk and scene, ~900 tasks with
their partial reductions for two 8192² scenes: two fifths of the job's); :func:`chunk_figures` makes them in one loop over a
chunk, and :func:`combine_figures` adds the chunks' parts, whatever the chunks' alignment to the
squares.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["ChunkFigures", "chunk_figures", "combine_figures"]

#: ``(count, minimum, maximum, first cell row, first cell column, cell sums, cell counts)`` of one chunk.
ChunkFigures = tuple


@numba.njit(nogil=True, cache=True)
def _chunk_pass(block, row0, col0, factor, cell_r0, cell_c0, nrows, ncols, sums, counts):  # pragma: no cover
    n = 0
    lo = np.inf
    hi = -np.inf
    h, w = block.shape
    for r in range(h):
        cr = (row0 + r) // factor - cell_r0
        for c in range(w):
            v = block[r, c]
            if not np.isfinite(v):
                continue
            n += 1
            lo = min(lo, v)
            hi = max(hi, v)
            cc = (col0 + c) // factor - cell_c0
            if cr < nrows and cc < ncols:
                sums[cr, cc] += v
                counts[cr, cc] += 1
    return n, lo, hi


def chunk_figures(block: np.ndarray, band: int, row0: int, col0: int, factor: int, cells: tuple[int, int]
                  ) -> ChunkFigures:
    """One chunk's part of the figures of one band.

    Parameters
    ----------
    block : ndarray (bands, h, w)
        The chunk, NaN where nodata.
    band : int
        The band (0-based).
    row0, col0 : int
        The chunk's first pixel in the scene.
    factor : int
        Side of the overview's squares (px).
    cells : (int, int)
        The overview's shape: the scene's complete squares.

    Returns
    -------
    ChunkFigures
        The chunk's finite pixels' count, minimum and maximum (+inf, -inf without), and the
        sums and counts of its finite pixels on the squares it touches, from the first one's
        row and column in the overview.
    """
    a = np.asarray(block[band])
    h, w = a.shape
    cell_r0, cell_c0 = row0 // factor, col0 // factor
    nrows = max(min((row0 + h - 1) // factor + 1, cells[0]) - cell_r0, 0)
    ncols = max(min((col0 + w - 1) // factor + 1, cells[1]) - cell_c0, 0)
    sums = np.zeros((nrows, ncols))
    counts = np.zeros((nrows, ncols), np.int64)
    n, lo, hi = _chunk_pass(a, int(row0), int(col0), int(factor), cell_r0, cell_c0, nrows, ncols, sums, counts)
    return int(n), float(lo), float(hi), cell_r0, cell_c0, sums, counts


def combine_figures(parts: list[ChunkFigures], cells: tuple[int, int]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The scene's figures from all its chunks' :func:`chunk_figures`.

    Returns
    -------
    count, minimum, maximum : ndarray (1,)
        Of the band's finite pixels (as one band of a ``(band, y, x)`` scene).
    overview : ndarray of float32 (cells)
        The squares' means of their finite pixels, NaN where a square has none.
    """
    sums = np.zeros(cells)
    counts = np.zeros(cells, np.int64)
    n, lo, hi = 0, np.inf, -np.inf
    for pn, plo, phi, r0, c0, psum, pcount in parts:
        n, lo, hi = n + pn, min(lo, plo), max(hi, phi)
        sums[r0 : r0 + psum.shape[0], c0 : c0 + psum.shape[1]] += psum
        counts[r0 : r0 + pcount.shape[0], c0 : c0 + pcount.shape[1]] += pcount
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / counts, np.nan).astype(np.float32)
    return np.array([n]), np.array([lo], np.float32), np.array([hi], np.float32), mean
