"""Foerstner interest operator and point selection (seed 000, eqs 30-33, sec. 4.4.1).

The operator works on the 2x2 gradients of every pixel quad, which sit at half-pixel
positions (r + 0.5, c + 0.5). A window of ``n - 1`` by ``n - 1`` of them (``n`` odd) is
centred exactly on pixel (r, c) and covers an ``n`` x ``n`` block of pixels. Using the
x/y components of the quad gradient instead of the two diagonal Roberts differences is a
rotation by 45 degrees and a scale: ``q`` and the ranking by ``w`` are unchanged (both are
built from rotation-invariant det N and tr N).

References
----------
Paderes, Mikhail & Foerstner (1984), eqs 30-33 and sec. 4.4.1 (``../shared/seeds/000``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

# Defaults of the operator and the point selection (seed 000 sec. 4.4.1), defined once here and
# used by :class:`geocoder.pipeline.detect.InterestOptions`.
#: Odd size of the pixel block the normal matrix is summed over.
DEFAULT_WINDOW = 7
#: Smallest roundness ``q`` of a point.
DEFAULT_Q_MIN = 0.25
#: A point needs ``w > f * mean(w)``.
DEFAULT_F = 1.5
#: Radius of the non-maximum suppression.
DEFAULT_RADIUS = 4
#: Side of the square cells of the distribution.
DEFAULT_CELL = 64
#: Most points per cell.
DEFAULT_CAP = 8


@dataclass(frozen=True)
class InterestPoints:
    """Selected interest points, in the pixel frame of the image they were found in.

    Attributes
    ----------
    x, y : ndarray of float64
        Column and row of every point (pixel centres, so integral values).
    w : ndarray of float64
        Interest value ``w = det N / tr N = 1 / tr Q`` (eq 33).
    q : ndarray of float64
        Roundness ``q = 4 det N / (tr N)^2`` (eq 30).
    """

    x: np.ndarray
    y: np.ndarray
    w: np.ndarray
    q: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    @staticmethod
    def concatenate(parts: list[InterestPoints]) -> InterestPoints:
        """Join point sets, keeping a deterministic (row, column) order."""
        if not parts:
            return InterestPoints(*(np.empty(0) for _ in range(4)))
        x, y, w, q = (np.concatenate([getattr(p, k) for p in parts]) for k in "xywq")
        order = np.lexsort((x, y))
        return InterestPoints(x[order], y[order], w[order], q[order])


def _box_sum(a: np.ndarray, size: int) -> np.ndarray:
    """Sum of every ``size`` x ``size`` window ('valid' positions only), by cumulative sums."""
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1), dtype=np.float64)
    np.cumsum(np.cumsum(a, axis=0, dtype=np.float64), axis=1, out=c[1:, 1:])
    return c[size:, size:] - c[:-size, size:] - c[size:, :-size] + c[:-size, :-size]


def foerstner(image: np.ndarray, *, window: int = DEFAULT_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Foerstner interest value ``w`` and roundness ``q`` of every pixel (numba).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey values; NaN marks nodata.
    window : int, keyword-only
        Odd size ``n`` of the pixel block the normal matrix N is summed over.

    Returns
    -------
    w, q : ndarray of float32, shape (H, W)
        ``w = det N / tr N`` and ``q = 4 det N / (tr N)^2`` (eqs 30-33); both are 0 where the
        window leaves the array or touches a NaN pixel, or where the image is flat.

    Notes
    -----
    Every box sum adds its ``(n - 1)^2`` quad products in the same order wherever the
    pixel sits in the array, so a pixel's values do not depend on the block it was
    computed in (tiles with halos give the whole image's values bit for bit).
    """
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    img = np.ascontiguousarray(image, dtype=np.float64)
    h, wd = img.shape
    w = np.zeros((h, wd), dtype=np.float32)
    q = np.zeros((h, wd), dtype=np.float32)
    if h < window or wd < window:
        return w, q
    _foerstner_kernel(img, window, w, q)
    return w, q


@numba.njit(nogil=True, cache=True)
def _foerstner_kernel(img, window, w, q):  # pragma: no cover - compiled
    """Fill ``w, q`` (zeros on entry) from quad gradients and ``(n - 1)``-square box sums.

    Box sums are separable: first along columns over ``n - 1`` quad rows, then along rows,
    each a plain sum of ``n - 1`` terms (no running sums, so no dependence on the origin).
    The quad products live in a ring of ``n - 1`` rows and the column sums in one row, so
    the work arrays stay in cache whatever the image size.
    """
    h, wd = img.shape
    n = window - 1
    k = window // 2
    qh, qw = h - 1, wd - 1
    ring = np.zeros((n, 4, qw))  # quad rows r .. r + n - 1 at slot row % n: gx^2, gy^2, gx gy, bad
    ow = qw - n + 1
    col = np.empty((4, qw))  # sums over the ring's rows
    box = np.empty((4, ow))  # and along them
    for r in range(qh - n + 1):
        first = r if r == 0 else r + n - 1  # the quad rows that enter the ring now
        for qr in range(first, r + n):
            prod = ring[qr % n]
            for c in range(qw):
                a = img[qr, c]
                b = img[qr, c + 1]
                cc = img[qr + 1, c]
                d = img[qr + 1, c + 1]
                gx = 0.5 * ((b - a) + (d - cc))
                gy = 0.5 * ((cc - a) + (d - b))
                if not (math.isfinite(gx) and math.isfinite(gy)):
                    prod[0, c] = 0.0
                    prod[1, c] = 0.0
                    prod[2, c] = 0.0
                    prod[3, c] = 1.0
                else:
                    prod[0, c] = gx * gx
                    prod[1, c] = gy * gy
                    prod[2, c] = gx * gy
                    prod[3, c] = 0.0
        # the same additions in the same order per pixel as plain loops over i and j, but
        # with the pixels innermost, so that they vectorise
        for m in range(4):
            for c in range(qw):
                col[m, c] = 0.0
            for i in range(n):
                src = ring[(r + i) % n, m]
                for c in range(qw):
                    col[m, c] += src[c]
            for c in range(ow):
                box[m, c] = 0.0
            for j in range(n):
                for c in range(ow):
                    box[m, c] += col[m, c + j]
        for c in range(ow):
            sxx = box[0, c]
            syy = box[1, c]
            sxy = box[2, c]
            det = sxx * syy - sxy * sxy
            tr = sxx + syy
            if box[3, c] < 0.5 and tr > 0 and det > 0:
                w[r + k, c + k] = det / tr
                q[r + k, c + k] = 4.0 * det / (tr * tr)


def foerstner_reference(image: np.ndarray, *, window: int = DEFAULT_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Numpy reference of :func:`foerstner` (box sums by cumulative sums), for the tests.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey values; NaN marks nodata.
    window : int, keyword-only
        Odd size ``n`` of the pixel block the normal matrix N is summed over.

    Returns
    -------
    w, q : ndarray of float32, shape (H, W)
        ``w = det N / tr N`` and ``q = 4 det N / (tr N)^2`` (eqs 30-33); both are 0 where the
        window leaves the array or touches a NaN pixel, or where the image is flat.
    """
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    img = np.asarray(image, dtype=np.float64)
    h, wd = img.shape
    w = np.zeros((h, wd), dtype=np.float32)
    q = np.zeros((h, wd), dtype=np.float32)
    k = window // 2
    if h < window or wd < window:
        return w, q
    a, b = img[:-1, :-1], img[:-1, 1:]
    c, d = img[1:, :-1], img[1:, 1:]
    gx = 0.5 * ((b - a) + (d - c))
    gy = 0.5 * ((c - a) + (d - b))
    bad = ~np.isfinite(gx) | ~np.isfinite(gy)
    gx[bad] = 0.0
    gy[bad] = 0.0
    n = window - 1
    sxx = _box_sum(gx * gx, n)
    syy = _box_sum(gy * gy, n)
    sxy = _box_sum(gx * gy, n)
    nbad = _box_sum(bad.astype(np.float64), n)
    det = sxx * syy - sxy * sxy
    tr = sxx + syy
    ok = (nbad < 0.5) & (tr > 0) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        wv = np.where(ok, det / tr, 0.0)
        qv = np.where(ok, 4.0 * det / (tr * tr), 0.0)
    w[k : h - k, k : wd - k] = wv
    q[k : h - k, k : wd - k] = qv
    return w, q


@numba.njit(nogil=True, cache=True)
def _strict_maxima(w, rows, cols, radius, row0, col0, width):
    """Keep candidates that beat every neighbour in their window; ties go to the smaller
    global raster index, so the outcome depends only on global coordinates."""
    h, wd = w.shape
    keep = np.ones(rows.size, dtype=np.bool_)
    for i in range(rows.size):
        r, c = rows[i], cols[i]
        v = w[r, c]
        me = (r + row0) * width + (c + col0)
        for rr in range(max(r - radius, 0), min(r + radius + 1, h)):
            for cc in range(max(c - radius, 0), min(c + radius + 1, wd)):
                o = w[rr, cc]
                if o > v or (o == v and (rr + row0) * width + (cc + col0) < me):
                    keep[i] = False
                    break
            if not keep[i]:
                break
    return keep


@numba.njit(nogil=True, cache=True)
def _local_maxima(w, r0, r1, c0, c1):
    """Pixels of ``w[r0:r1, c0:c1]`` (raster order, block coordinates) above 0 and at least as
    large as each of their 8 neighbours (outside the block counts as 0)."""
    h, wd = w.shape
    # the 3 x 3 maximum in two passes (along the rows, then across them); NaN never wins, as a
    # NaN neighbour never beats a pixel
    ra, rb = max(r0 - 1, 0), min(r1 + 1, h)
    along = np.empty((rb - ra, c1 - c0))
    for r in range(ra, rb):
        for c in range(c0, c1):
            m = -np.inf
            for cc in range(max(c - 1, 0), min(c + 2, wd)):
                if w[r, cc] > m:
                    m = w[r, cc]
            along[r - ra, c - c0] = m
    rows = np.empty((r1 - r0) * (c1 - c0), np.int64)
    cols = np.empty_like(rows)
    n = 0
    for r in range(r0, r1):
        for c in range(c0, c1):
            v = w[r, c]
            if not v > 0:
                continue
            m = along[r - ra, c - c0]
            for rr in range(max(r - 1, 0), min(r + 2, h)):
                if along[rr - ra, c - c0] > m:
                    m = along[rr - ra, c - c0]
            if not m > v:
                rows[n] = r
                cols[n] = c
                n += 1
    return rows[:n].copy(), cols[:n].copy()


def select_points(
    w: np.ndarray,
    q: np.ndarray,
    *,
    w_min: float,
    q_min: float = DEFAULT_Q_MIN,
    radius: int = DEFAULT_RADIUS,
    cell: int = DEFAULT_CELL,
    cap: int = DEFAULT_CAP,
    core: tuple[int, int, int, int] | None = None,
    origin: tuple[int, int] = (0, 0),
    width: int | None = None,
) -> InterestPoints:
    """Threshold, suppress non-maxima and thin out interest values (sec. 4.4.1).

    Parameters
    ----------
    w, q : ndarray, shape (h, w)
        Output of :func:`foerstner` for a block (core plus halo) of a larger image.
    w_min : float
        Size threshold C2, usually ``f * mean(w)`` over the whole image (f = 1.5).
    q_min : float
        Form threshold C1 (0.25 in the seed).
    radius : int
        Non-maximum suppression over a ``(2 radius + 1)^2`` window.
    cell, cap : int
        Distribution: at most ``cap`` points (the strongest) per ``cell`` x ``cell`` square
        of the global pixel grid, so points cover the whole scene. Cells are aligned to the
        global origin, hence results do not depend on the tiling as long as tiles are
        multiples of ``cell``.
    core : (row0, row1, col0, col1), optional
        Half-open window of the block this call owns; points outside are dropped (they
        belong to a neighbouring tile). Default: the whole block.
    origin : (row, col)
        Global position of ``w[0, 0]``.
    width : int, optional
        Global image width, for the tie-break order; default the block width.

    Returns
    -------
    InterestPoints
        In global pixel coordinates.
    """
    interest = np.where((q > q_min) & (w > w_min), w, 0).astype(np.float64)
    r0, r1, c0, c1 = core if core is not None else (0, w.shape[0], 0, w.shape[1])
    # a strict maximum of its (2 radius + 1)^2 window is at least as large as its 8
    # neighbours: that cheap test (exact, outside the block counts as 0 as in
    # _strict_maxima) leaves the full window test to a few candidates
    if radius >= 1:
        rows, cols = _local_maxima(interest, r0, r1, c0, c1)
    else:
        rows, cols = np.nonzero(interest[r0:r1, c0:c1])
        rows = (rows + r0).astype(np.int64)
        cols = (cols + c0).astype(np.int64)
    width = int(width if width is not None else w.shape[1])
    keep = _strict_maxima(interest, rows, cols, int(radius), int(origin[0]), int(origin[1]), width)
    rows, cols = rows[keep], cols[keep]
    values = interest[rows, cols]
    gy, gx = rows + origin[0], cols + origin[1]
    if cap > 0 and rows.size:
        cell_id = (gy // cell) * (width // cell + 2) + gx // cell
        raster = gy * width + gx
        order = np.lexsort((raster, -values, cell_id))
        sorted_cells = cell_id[order]
        starts = np.r_[0, np.flatnonzero(np.diff(sorted_cells)) + 1]
        rank = np.arange(order.size) - np.repeat(starts, np.diff(np.r_[starts, order.size]))
        chosen = np.sort(order[rank < cap])
        rows, cols, gy, gx, values = rows[chosen], cols[chosen], gy[chosen], gx[chosen], values[chosen]
    return InterestPoints(
        x=gx.astype(np.float64),
        y=gy.astype(np.float64),
        w=values.astype(np.float64),
        q=q[rows, cols].astype(np.float64),
    )


def detect(
    image: np.ndarray,
    *,
    window: int = DEFAULT_WINDOW,
    q_min: float = DEFAULT_Q_MIN,
    f: float = DEFAULT_F,
    radius: int = DEFAULT_RADIUS,
    cell: int = DEFAULT_CELL,
    cap: int = DEFAULT_CAP,
) -> InterestPoints:
    """Interest points of a whole in-memory image (the reference for the tiled pipeline).

    ``w_min = f * mean(w)`` with the mean over all pixels whose window is valid.
    """
    w, q = foerstner(image, window=window)
    valid = w > 0
    w_min = f * float(w[valid].mean()) if valid.any() else np.inf
    return select_points(w, q, w_min=w_min, q_min=q_min, radius=radius, cell=cell, cap=cap)
