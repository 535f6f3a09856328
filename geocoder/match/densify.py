"""Every pixel from the lattice: start field along the scan lines, then one least-squares pass.

Region growing (:mod:`geocoder.match.grow`) with ``col_step = k`` matches every scan line
but only every k-th column. Along a line the field is smooth (the turbulence of a scanner is
shared by the whole line), so the pixels between two matched lattice columns start from the
linear interpolation of their positions, also across untextured stretches where the lattice
failed (up to ``max_gap``); beyond the last matched lattice column of a run the start follows
that match's affine (:data:`MIN_EXTEND` px), or where the run is long enough, its last chord
as far as the run's curvature allows (up to ``max_extend``). Every started pixel is then
matched by :func:`geocoder.kernels.fieldlsq.field_lsq`: the normal equations of all
templates at once from window sums on the distorted image resampled at the start field,
with ALSC's acceptance tests and its covariance. A pixel with no matched lattice column
near it on its line is not started and stays unmatched.

All of it is numpy/numba on in-memory windows: no Dask, no I/O, no Python per pixel.
"""

from __future__ import annotations

import numba
import numpy as np

from ..kernels.alsc import AlscOptions
from ..kernels.fieldlsq import FieldLsqResult, field_lsq
from ..kernels.fieldlsq_bands import field_lsq_bands

__all__ = ["lattice_start", "rows_between", "densify_window"]


#: Past a line's first and last match the start follows the match's affine for this many px;
#: beyond, where the run of matches is long enough to tell the line's slope and curvature
#: (three matches :data:`CHORD_SPAN` px apart), along the slope of the last chord as far as the
#: curvature (its estimate plus twice that estimate's noise, from the matches' sigmas) keeps it
#: within :data:`CHORD_TOL` px (at most ``max_extend``). The tolerance is the match's own reach
#: (``max_shift`` 0.5 px of the dense default): the bound counts twice the curvature's noise, and
#: every start is verified. On the nine cases of ``benchmarks/bench_dense_cases.py`` 0.25 -> 0.5 raised
#: the textured coverage 0.1-1.6 points (Landsat 88.1 -> 89.7 %) with matched RMSE and calibration
#: unchanged (strong S2 0.045 -> 0.046 px); 1.0 and no bound raised it further but let worse matches
#: in (strong S2 0.047, 0.049 px; smooth S2 calibration x 0.73 -> 0.67). Where one band is flat
#: (``bench_bands.py``'s weak aerial crop, band 1 blurred over half) 0.5 carries starts further into
#: the flat half: matched there 5.4 -> 10.1 %, at 0.054 px instead of 0.029 (within their sigma).
MIN_EXTEND = 32
CHORD_SPAN = 64
CHORD_TOL = 0.5


@numba.njit(nogil=True, cache=True)
def _chord_reach(x, y, sx, sy, idx, i, j, j2, max_extend):  # pragma: no cover - compiled
    """Slopes (x, y) of the chord from match ``j`` to the end match ``i`` and how far (px) past
    ``i`` they stay within CHORD_TOL of a line whose curvature is that of the chords j2-j, j-i
    (plus twice its noise: the matches' sigmas ``sx, sy``)."""
    ci, cj, c2 = idx[i], idx[j], idx[j2]
    d1, d0 = abs(ci - cj), abs(cj - c2)
    slope_x, slope_y = (x[ci] - x[cj]) / (ci - cj), (y[ci] - y[cj]) / (ci - cj)
    mid = 0.5 * (d1 + d0)  # between the two chords' midpoints
    curv = 0.0
    for v, s, slope in ((x, sx, slope_x), (y, sy, slope_y)):
        second = abs(slope - (v[cj] - v[c2]) / (cj - c2))
        noise = np.sqrt((s[ci] / d1) ** 2 + (s[cj] * (1.0 / d1 + 1.0 / d0)) ** 2 + (s[c2] / d0) ** 2)
        curv = max(curv, (second + 2.0 * noise) / mid)
    if not np.isfinite(curv):
        return slope_x, slope_y, 0
    if curv * (max_extend * max_extend + max_extend * d1) <= 2.0 * CHORD_TOL:
        return slope_x, slope_y, max_extend
    # 0.5 curv (L^2 + L d1) = CHORD_TOL: how far the chord's slope carries
    return slope_x, slope_y, int(0.5 * (np.sqrt(d1 * d1 + 8.0 * CHORD_TOL / curv) - d1))


@numba.njit(nogil=True, cache=True)
def _lattice_start(x, y, a11, a21, sx, sy, matched, max_gap, max_extend, x0, y0, started):  # pragma: no cover - compiled
    h, w = matched.shape
    nxt = np.empty(w, dtype=np.int64)  # next matched column at or after each column, per line
    idx = np.empty(w, dtype=np.int64)  # the line's matched columns
    # per matched column that ends a run (right) or starts one (left): the slopes its extension
    # follows and how far (read at those columns only)
    ext = np.empty((2, 3, w))
    for r in range(h):
        k = 0
        for c in range(w):
            if matched[r, c]:
                idx[k] = c
                k += 1
        for i in range(k):
            c = idx[i]
            for side in range(2):  # 0: extended to the right (toward larger columns), 1: to the left
                outer = i + 1 if side == 0 else i - 1
                if 0 <= outer < k and abs(idx[outer] - c) <= max_gap:
                    continue  # inside its run: interpolated, never extended
                ext[side, 0, c] = a11[r, c] if side == 0 else -a11[r, c]
                ext[side, 1, c] = a21[r, c] if side == 0 else -a21[r, c]
                ext[side, 2, c] = min(MIN_EXTEND, max_extend)
                step = -1 if side == 0 else 1  # toward the inner matches of the run
                j = -1
                j2 = -1
                m = i
                while 0 <= m + step < k and abs(idx[m + step] - idx[m]) <= max_gap:
                    m += step
                    if j < 0 and abs(idx[m] - c) >= CHORD_SPAN:
                        j = m
                    elif j >= 0 and abs(idx[m] - idx[j]) >= CHORD_SPAN:
                        j2 = m
                        break
                if j2 >= 0:
                    slope_x, slope_y, reach = _chord_reach(x[r], y[r], sx[r], sy[r], idx, i, j, j2, max_extend)
                    if reach > ext[side, 2, c]:
                        sgn = 1.0 if side == 0 else -1.0
                        ext[side, 0, c] = sgn * slope_x
                        ext[side, 1, c] = sgn * slope_y
                        ext[side, 2, c] = reach
        left = -1
        following = -1
        for c in range(w - 1, -1, -1):
            if matched[r, c]:
                following = c
            nxt[c] = following
        for c in range(w):
            if matched[r, c]:
                left = c
            right = nxt[c]
            if left >= 0 and right >= 0 and right - left <= max_gap:
                if right == left:
                    x0[r, c] = x[r, c]
                    y0[r, c] = y[r, c]
                else:
                    f = (c - left) / (right - left)
                    x0[r, c] = (1.0 - f) * x[r, left] + f * x[r, right]
                    y0[r, c] = (1.0 - f) * y[r, left] + f * y[r, right]
                started[r, c] = True
            elif left >= 0 and c - left <= ext[0, 2, left]:
                x0[r, c] = x[r, left] + ext[0, 0, left] * (c - left)
                y0[r, c] = y[r, left] + ext[0, 1, left] * (c - left)
                started[r, c] = True
            elif right >= 0 and right - c <= ext[1, 2, right]:
                x0[r, c] = x[r, right] + ext[1, 0, right] * (right - c)
                y0[r, c] = y[r, right] + ext[1, 1, right] * (right - c)
                started[r, c] = True


def lattice_start(x: np.ndarray, y: np.ndarray, a11: np.ndarray, a21: np.ndarray, matched: np.ndarray, *,
                  max_gap: int, max_extend: int, sigma_x: np.ndarray | None = None,
                  sigma_y: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start positions of every pixel from the matched lattice pixels of its scan line.

    Parameters
    ----------
    x, y, a11, a21 : float (h, w)
        Positions and the first column of the affine of the lattice matches (read only where
        ``matched``).
    matched : bool (h, w)
        Matched lattice pixels.
    max_gap : int
        Two matched pixels of a line at most this far apart (px) are interpolated: the
        field along a scan line is smooth, and every start is verified by the match.
    max_extend : int
        Beyond the last matched pixel of a line, starts follow its affine :data:`MIN_EXTEND`
        px (at most ``max_extend``); where the run of matches holds three at least
        :data:`CHORD_SPAN` px apart, the slope of its last chord as far as the curvature of
        the last two chords (plus twice its noise) keeps that within :data:`CHORD_TOL` px, at
        most ``max_extend``.
    sigma_x, sigma_y : float (h, w), optional
        The lattice matches' sigmas (px): the curvature's noise counts against the reach
        (None: noise-free).

    Returns
    -------
    x0, y0 : float64 (h, w)
        Start positions (NaN where not started).
    started : bool (h, w)
    """
    h, w = matched.shape
    x0 = np.full((h, w), np.nan)
    y0 = np.full((h, w), np.nan)
    started = np.zeros((h, w), dtype=np.bool_)
    zero = np.zeros((h, w))
    _lattice_start(np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(a11, np.float64),
                   np.asarray(a21, np.float64), zero if sigma_x is None else np.asarray(sigma_x, np.float64),
                   zero if sigma_y is None else np.asarray(sigma_y, np.float64), np.asarray(matched, np.bool_),
                   int(max_gap), int(max_extend), x0, y0, started)
    return x0, y0, started


@numba.njit(nogil=True, cache=True)
def _rows_between(x, y, started, first_row, row_step, height, origin):  # pragma: no cover - compiled
    h, w = x.shape
    for i in range(h):
        off = (first_row + i - origin) % row_step
        if off == 0:
            continue
        above, below = i - off, i - off + row_step
        # a line whose lattice row on either side is in the scene but not in the arrays is left
        # alone: its start must not depend on the window
        known = (above >= 0 or first_row + above < 0) and (below < h or first_row + below >= height)
        f = off / row_step
        for c in range(w):
            a = known and above >= 0 and started[above, c]
            b = known and below < h and started[below, c]
            # displacements across the lines: ``y`` is a position, one more for every line down
            if a and b:
                x[i, c] = (1.0 - f) * x[above, c] + f * x[below, c]
                y[i, c] = (1.0 - f) * (y[above, c] + off) + f * (y[below, c] - (row_step - off))
            elif a:
                x[i, c] = x[above, c]
                y[i, c] = y[above, c] + off
            elif b:
                x[i, c] = x[below, c]
                y[i, c] = y[below, c] - (row_step - off)
            else:
                x[i, c] = np.nan
                y[i, c] = np.nan
            started[i, c] = a or b


def rows_between(x0: np.ndarray, y0: np.ndarray, started: np.ndarray, first_row: int, row_step: int,
                 height: int, origin: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starts of the scan lines between the lattice's rows, from the lattice rows on either side.

    The lattice's rows are the global rows ``(r - origin) % row_step == 0``; a line between two of them
    starts where both are started from their linear interpolation across the lines, where
    one is, from that one (so does a line past the scene's last lattice row). Every start is
    verified by the match, and the every-pixel pass averages the starts over its template's
    rows first. A line whose lattice row above or below is in the scene but not in the arrays
    is not started (the caller reads a lattice row more on either side).

    Parameters
    ----------
    x0, y0 : float64 (h, w)
        Starts of the lattice rows (:func:`lattice_start`), NaN elsewhere.
    started : bool (h, w)
    first_row : int
        Global row of the arrays' first row.
    row_step : int
    height : int
        Rows of the scene (a lattice row past it does not exist).
    origin : int
        A global lattice row.

    Returns
    -------
    x0, y0, started : new arrays, the lattice rows unchanged
    """
    if row_step == 1:
        return x0, y0, started
    x, y, start = np.array(x0, dtype=np.float64), np.array(y0, dtype=np.float64), np.array(started, dtype=np.bool_)
    _rows_between(x, y, start, int(first_row), int(row_step), int(height), int(origin))
    return x, y, start


def densify_window(
    base: np.ndarray,
    dist: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    started: np.ndarray,
    region: tuple[int, int, int, int],
    *,
    options: AlscOptions,
    iterations: int,
    tol: float,
    min_fill: float = 0.5,
    gradients: str = "template",
) -> FieldLsqResult:
    """Match every started pixel of ``region`` (see :func:`geocoder.kernels.fieldlsq.field_lsq`).

    ``base`` and ``dist`` (n, h, w) with ``n > 1``: on all bands at once
    (:func:`geocoder.kernels.fieldlsq_bands.field_lsq_bands`, the template's gradients only).
    """
    if np.ndim(base) == 3 and np.shape(base)[0] > 1:
        if gradients != "template":
            raise ValueError(f"matching several bands needs densify_gradients='template', got {gradients!r}")
        return field_lsq_bands(
            base, dist, x0, y0, started, region, radius=options.radius, radius_y=options.ry,
            iterations=iterations, tol=tol, max_shift=options.max_shift, min_rho=options.min_rho,
            max_sigma=options.max_sigma, min_det=options.min_det, min_fill=min_fill,
        )
    if np.ndim(base) == 3:
        base, dist = base[0], dist[0]
    return field_lsq(
        base, dist, x0, y0, started, region, radius=options.radius, radius_y=options.ry,
        iterations=iterations, tol=tol, max_shift=options.max_shift, min_rho=options.min_rho,
        max_sigma=options.max_sigma, min_det=options.min_det, min_fill=min_fill, gradients=gradients,
    )
