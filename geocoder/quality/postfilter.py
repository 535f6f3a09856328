"""Scan-line post-filter of a dense displacement field (seed 003, Allison & Muller, sec. 10).

A dense field from area-based matching holds, per base pixel, a displacement
``(dx, dy)`` (NaN where there is no match) and a status code
(:class:`geocoder.status.Status`).  Rows are scan lines of an airborne line
scanner: along a row the true displacement is smooth apart from genuine
small-scale relief, while matching blunders show up as isolated jumps.  Every
row is processed on its own (no vertical continuity is used):

0. A ``MATCHED`` pixel whose ``dx`` or ``dy`` is not finite is an inconsistent
   match; it becomes ``BLUNDER`` (a purely local rule, done whatever ``passes``).
1. **Blunders.**  For each ``MATCHED`` pixel at column ``c`` the *neighbours*
   are the ``MATCHED`` pixels at columns ``c - h .. c + h`` (``h = window // 2``)
   other than ``c`` itself.  With at least :data:`MIN_NEIGHBOURS` neighbours,
   ``m`` = their median and ``s = 1.4826 * median(|d_j - m|)`` (MAD) are
   computed separately for ``dx`` and ``dy``; the pixel is a blunder when
   ``|d - m| > max(k * s, min_dev)`` for ``dx`` or for ``dy``.  Within a pass
   all pixels are judged on the state at the start of the pass, then every
   blunder is removed at once (status ``BLUNDER``, ``dx = dy = NaN``).  The
   next pass repeats this without the removed pixels; a pass that finds
   nothing ends the detection (further passes could not find anything either).
2. **Holes.**  A hole is a maximal run of columns whose status is ``BLUNDER``,
   ``NO_TEXTURE`` or ``FILLED`` (an already filled pixel may be refilled).
   ``OUTSIDE``, ``MODEL`` (and any unknown code) are barriers.  A hole
   ``[s, e]`` is filled when

   * ``e - s + 1 <= max_gap``,
   * both ``s - 1`` and ``e + 1`` are inside the row and ``MATCHED`` (so a hole
     touching a row end, an ``OUTSIDE`` or a ``MODEL`` pixel is never filled:
     no extrapolation), and
   * on each side, walking away from the hole over at most ``2 * support``
     columns (``s - 1 .. s - 2 support`` and ``e + 1 .. e + 2 support``),
     skipping hole pixels and stopping at a barrier or the row end, at least
     ``support`` ``MATCHED`` pixels are met; the nearest ``support`` of each
     side are kept.

   ``dx`` and ``dy`` are then fitted separately, by least squares, with a
   polynomial in the column of degree ``min(order, 2 support - 1)`` to those
   ``2 support`` pixels, and the polynomial is evaluated in the hole (status
   ``FILLED``).  Longer or unsupported holes are left exactly as they are.

Only relative column offsets enter the arithmetic, so the result does not
depend on where a row segment starts: running :func:`postfilter` on column
tiles extended by :func:`halo` columns on each side (not padded at the image
border, or padded with ``OUTSIDE``) and cropping back reproduces the result on
the whole image bit for bit.  (Reflecting, wrapping or edge-repeating padding
would not: it invents data beyond the row ends.)

:func:`postfilter` runs numba kernels, one row at a time (``nogil``, so dask
threads run rows of different tiles in parallel).  The first blunder pass keeps
sorted sliding windows of the neighbour values, so the median and the MAD cost
O(window) per pixel without sorting; later passes only revisit pixels within
``window // 2`` of a pixel removed in the pass before, as no other window has
changed.  :mod:`geocoder.quality.postfilter_reference` is a vectorised numpy
implementation of the same rules (``numpy.nanmedian``, ``numpy.polyfit``), kept for the tests.
The sorted windows' small numba kernels (insert, remove, replace, find) and the two passes
are why the module is over 500 lines.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..status import Status

__all__ = ["MIN_NEIGHBOURS", "PostFilterOptions", "halo", "postfilter"]

#: Fewest ``MATCHED`` neighbours in the window for a pixel to be judged at all: with a
#: single neighbour, median and MAD cannot tell which of the two is the blunder (each
#: would reject the other).  Two neighbours that disagree give a large MAD, so a good
#: pixel beside a blunder is kept, while two that agree expose a spike between them.
MIN_NEIGHBOURS = 2

#: Normal-distribution consistency factor of the median absolute deviation.
_MAD_SCALE = 1.4826

# Status codes as plain ints: numba freezes module-level ints as compile-time constants.
_MATCHED = int(Status.MATCHED)
_FILLED = int(Status.FILLED)
_BLUNDER = int(Status.BLUNDER)
_NO_TEXTURE = int(Status.NO_TEXTURE)


@dataclass(frozen=True)
class PostFilterOptions:
    """Options of :func:`postfilter`.

    Attributes
    ----------
    window : int
        Full width (odd, >= 3) of the running median along the row, over
        ``MATCHED`` pixels only, the pixel itself excluded.
    k : float
        A pixel is a blunder if ``|d - median| > max(k * 1.4826 * MAD, min_dev)``.
    min_dev : float
        Floor (px) of the blunder threshold.
    max_gap : int
        Longest hole (px) that may be filled (0: no filling).
    support : int
        ``MATCHED`` pixels used on each side of a hole for the fit (>= 1); they
        must lie within ``2 * support`` px of the hole's edge.
    order : int
        Polynomial order (0, 1 or 2) of the fill along the row; lowered to
        ``2 * support - 1`` if the support is too short.
    passes : int
        Blunder detection passes (a removed blunder can unmask another); 0
        disables the detection.
    """

    window: int = 9
    k: float = 4.0
    min_dev: float = 0.5
    max_gap: int = 24
    support: int = 6
    order: int = 2
    passes: int = 2


def _check(options: PostFilterOptions) -> None:
    if not isinstance(options, PostFilterOptions):
        raise TypeError(f"options must be PostFilterOptions, not {type(options).__name__}")
    if int(options.window) != options.window or options.window < 3 or options.window % 2 != 1:
        raise ValueError(f"window must be an odd integer >= 3, got {options.window!r}")
    if not (np.isfinite(options.k) and options.k > 0):
        raise ValueError(f"k must be a positive number, got {options.k!r}")
    if not (np.isfinite(options.min_dev) and options.min_dev >= 0):
        raise ValueError(f"min_dev must be a number >= 0, got {options.min_dev!r}")
    if int(options.max_gap) != options.max_gap or options.max_gap < 0:
        raise ValueError(f"max_gap must be an integer >= 0, got {options.max_gap!r}")
    if int(options.support) != options.support or options.support < 1:
        raise ValueError(f"support must be an integer >= 1, got {options.support!r}")
    if options.order not in (0, 1, 2):
        raise ValueError(f"order must be 0, 1 or 2, got {options.order!r}")
    if int(options.passes) != options.passes or options.passes < 0:
        raise ValueError(f"passes must be an integer >= 0, got {options.passes!r}")


def halo(options: PostFilterOptions = PostFilterOptions()) -> int:
    """Columns of context needed on each side of a tile for an exact tiled result.

    ``halo = passes * (window // 2) + (max_gap - 1 + 2 * support)`` (the second
    term is 0 when ``max_gap == 0``).

    Why: a blunder pass decides a pixel from the pixels within ``h = window // 2``
    columns, as they stood after the previous pass, so after ``passes`` passes
    the status of a column is exact once the tile holds the ``passes * h``
    columns on each side of it.  A hole pixel ``i`` that gets filled lies in a
    hole ``[s, e]`` with ``e - s + 1 <= max_gap`` whose support reaches
    ``2 * support`` columns beyond the edges, i.e. at most
    ``max_gap - 1 + 2 * support`` columns from ``i``; a hole that runs further
    than that is longer than ``max_gap`` and is not filled, and a hole cut by
    the tile edge looks as if it touched the row end, which is not filled
    either.  The fill needs the final status of those columns, hence the sum.
    Each term is reached on its own (see the tests), so one column less can
    change the result.

    Parameters
    ----------
    options : PostFilterOptions
        The options :func:`postfilter` will run with.

    Returns
    -------
    int
        Halo width in columns; rows are independent, so no vertical halo is needed.
    """
    _check(options)
    fill = options.max_gap - 1 + 2 * options.support if options.max_gap > 0 else 0
    return int(options.passes * (options.window // 2) + fill)


# --------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------


@numba.njit(nogil=True, cache=True)
def _at(srt, skip, k):  # pragma: no cover - compiled
    """Element ``k`` of the sorted array ``srt`` with its element ``skip`` taken out."""
    return srt[k] if k < skip else srt[k + 1]


@numba.njit(nogil=True, cache=True)
def _deviates(v, srt, skip, n, kk, min_dev):  # pragma: no cover - compiled
    """Whether ``v`` is a blunder against ``n`` sorted neighbour values.

    The neighbours are ``srt`` (sorted) without its element ``skip`` (``skip >= n``:
    without none), so the sliding window can hold the pixel's own value too.
    """
    m = n // 2
    med = _at(srt, skip, m) if n % 2 == 1 else 0.5 * (_at(srt, skip, m - 1) + _at(srt, skip, m))
    dev = abs(v - med)
    if dev <= min_dev:  # the threshold is at least min_dev: no need for the MAD
        return False
    # MAD without sorting the deviations: values 0..i are <= med <= values j.., so the
    # absolute deviations form two non-decreasing sequences, med - value(i), med -
    # value(i - 1), ... and value(j) - med, value(j + 1) - med, ...; merge them up to
    # the middle rank(s).
    i = (n - 1) // 2
    j = i + 1
    prev = 0.0
    cur = 0.0
    for _ in range(m + 1):
        lo = med - _at(srt, skip, i) if i >= 0 else np.inf
        hi = _at(srt, skip, j) - med if j < n else np.inf
        prev = cur
        if lo <= hi:
            cur = lo
            i -= 1
        else:
            cur = hi
            j += 1
    mad = cur if n % 2 == 1 else 0.5 * (prev + cur)
    return dev > max(kk * mad, min_dev)


@numba.njit(nogil=True, cache=True)
def _find(srt, n, v):  # pragma: no cover - compiled
    """Leftmost index of ``srt[:n]`` (sorted) whose value is >= ``v``."""
    k = 0
    for q in range(n):  # a branch-free count beats a binary search on these short arrays
        k += srt[q] < v
    return k


@numba.njit(nogil=True, cache=True)
def _insert(srt, n, v):  # pragma: no cover - compiled
    k = _find(srt, n, v)
    for q in range(n, k, -1):
        srt[q] = srt[q - 1]
    srt[k] = v


@numba.njit(nogil=True, cache=True)
def _remove(srt, n, v):  # pragma: no cover - compiled
    k = _find(srt, n, v)  # srt holds v, so srt[k] == v
    for q in range(k, n - 1):
        srt[q] = srt[q + 1]


@numba.njit(nogil=True, cache=True)
def _replace(srt, n, old, new):  # pragma: no cover - compiled
    """Replace one ``old`` by ``new`` in ``srt[:n]``, keeping it sorted."""
    q = _find(srt, n, old)
    if new > old:
        while q + 1 < n and srt[q + 1] < new:
            srt[q] = srt[q + 1]
            q += 1
    else:
        while q > 0 and srt[q - 1] > new:
            srt[q] = srt[q - 1]
            q -= 1
    srt[q] = new


@numba.njit(nogil=True, cache=True)
def _first_pass(dx, dy, st, half, kk, min_dev, min_nb, flag, sx, sy):  # pragma: no cover - compiled
    """Judge every MATCHED pixel of a row, with sorted sliding windows (O(window) per pixel).

    ``sx``/``sy`` hold the sorted values of the MATCHED pixels in ``[c - half, c + half]``,
    the pixel itself included; it is skipped when the median and MAD are taken.
    """
    nx = st.shape[0]
    cnt = 0
    found = False
    for j in range(min(half, nx)):
        if st[j] == _MATCHED:
            _insert(sx, cnt, np.float64(dx[j]))
            _insert(sy, cnt, np.float64(dy[j]))
            cnt += 1
    for c in range(nx):
        j = c + half  # enters the window
        i = c - half - 1  # leaves it
        come = j < nx and st[j] == _MATCHED
        go = i >= 0 and st[i] == _MATCHED
        if come and go:
            _replace(sx, cnt, np.float64(dx[i]), np.float64(dx[j]))
            _replace(sy, cnt, np.float64(dy[i]), np.float64(dy[j]))
        elif come:
            _insert(sx, cnt, np.float64(dx[j]))
            _insert(sy, cnt, np.float64(dy[j]))
            cnt += 1
        elif go:
            _remove(sx, cnt, np.float64(dx[i]))
            _remove(sy, cnt, np.float64(dy[i]))
            cnt -= 1
        flag[c] = False
        if st[c] != _MATCHED or cnt - 1 < min_nb:
            continue
        # Exact shortcut: the pixel's own value and the neighbours' median both lie in the
        # window's range, so a range within min_dev (<= the threshold) rules a blunder out.
        if sx[cnt - 1] - sx[0] <= min_dev and sy[cnt - 1] - sy[0] <= min_dev:
            continue
        vx = np.float64(dx[c])
        vy = np.float64(dy[c])
        if _deviates(vx, sx, _find(sx, cnt, vx), cnt - 1, kk, min_dev) or _deviates(
            vy, sy, _find(sy, cnt, vy), cnt - 1, kk, min_dev
        ):
            flag[c] = True
            found = True
    return found


@numba.njit(nogil=True, cache=True)
def _sort(buf, n):  # pragma: no cover - compiled
    for i in range(1, n):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v


@numba.njit(nogil=True, cache=True)
def _gathered(v, buf, n, lo, hi, kk, min_dev):  # pragma: no cover - compiled
    """:func:`_deviates` on unsorted neighbours ``buf[:n]`` spanning ``[lo, hi]``.

    Exact shortcut: the median lies in ``[lo, hi]``, so ``|v - median| <= max(v - lo,
    hi - v)`` (rounding is monotonic); within ``min_dev`` the pixel cannot deviate.
    """
    if v - lo <= min_dev and hi - v <= min_dev:
        return False
    _sort(buf, n)
    return _deviates(v, buf, n, n, kk, min_dev)


@numba.njit(nogil=True, cache=True)
def _next_pass(dx, dy, st, half, kk, min_dev, min_nb, check, flag, bx, by):  # pragma: no cover - compiled
    """Judge the MATCHED pixels marked in ``check``, gathering their neighbours."""
    nx = st.shape[0]
    found = False
    for c in range(nx):
        flag[c] = False
        if st[c] != _MATCHED or not check[c]:
            continue
        n = 0
        lox = hix = loy = hiy = 0.0
        for j in range(max(c - half, 0), min(c + half + 1, nx)):
            if j != c and st[j] == _MATCHED:
                vx = np.float64(dx[j])
                vy = np.float64(dy[j])
                if n == 0:
                    lox = hix = vx
                    loy = hiy = vy
                else:
                    lox = min(lox, vx)
                    hix = max(hix, vx)
                    loy = min(loy, vy)
                    hiy = max(hiy, vy)
                bx[n] = vx
                by[n] = vy
                n += 1
        if n < min_nb:
            continue
        if _gathered(np.float64(dx[c]), bx, n, lox, hix, kk, min_dev) or _gathered(
            np.float64(dy[c]), by, n, loy, hiy, kk, min_dev
        ):
            flag[c] = True
            found = True
    return found


@numba.njit(nogil=True, cache=True)
def _blunders_row(dx, dy, st, half, kk, min_dev, passes, min_nb, check, flag, bx, by):  # pragma: no cover - compiled
    nx = st.shape[0]
    for c in range(nx):  # step 0: non-finite matches
        if st[c] == _MATCHED and not (np.isfinite(dx[c]) and np.isfinite(dy[c])):
            st[c] = _BLUNDER
            dx[c] = np.nan
            dy[c] = np.nan
    for p in range(passes):
        # Pass 1 judges every pixel.  Later passes judge only the pixels whose window
        # changed in the previous pass (``check``): any other MATCHED pixel was judged
        # good on the very same neighbours before, so it would be judged good again.
        if p == 0:
            found = _first_pass(dx, dy, st, half, kk, min_dev, min_nb, flag, bx, by)
        else:
            found = _next_pass(dx, dy, st, half, kk, min_dev, min_nb, check, flag, bx, by)
        if not found:
            break
        for c in range(nx):
            check[c] = False
        for c in range(nx):
            if flag[c]:
                st[c] = _BLUNDER
                dx[c] = np.nan
                dy[c] = np.nan
                for j in range(max(c - half, 0), min(c + half + 1, nx)):
                    check[j] = True


@numba.njit(nogil=True, cache=True)
def _is_hole(s):  # pragma: no cover - compiled
    return s == _FILLED or s == _BLUNDER or s == _NO_TEXTURE


@numba.njit(nogil=True, cache=True)
def _collect(st, start, step, reach, support, cols):  # pragma: no cover - compiled
    """Nearest ``support`` MATCHED columns from ``start`` in direction ``step`` within ``reach`` columns."""
    nx = st.shape[0]
    n = 0
    for d in range(reach):
        j = start + step * d
        if j < 0 or j >= nx:
            break
        s = st[j]
        if s == _MATCHED:
            cols[n] = j
            n += 1
            if n == support:
                break
        elif not _is_hole(s):
            break
    return n


@numba.njit(nogil=True, cache=True)
def _solve_inplace(a, b, m):  # pragma: no cover - compiled
    """Solve ``a[:m, :m] x = b[:m, :]`` by Gaussian elimination with partial pivoting; ``b`` gets ``x``."""
    for col in range(m):
        p = col
        for r in range(col + 1, m):
            if abs(a[r, col]) > abs(a[p, col]):
                p = r
        if a[p, col] == 0.0:
            return False
        if p != col:
            for q in range(m):
                a[col, q], a[p, q] = a[p, q], a[col, q]
            for q in range(b.shape[1]):
                b[col, q], b[p, q] = b[p, q], b[col, q]
        for r in range(col + 1, m):
            f = a[r, col] / a[col, col]
            for q in range(col, m):
                a[r, q] -= f * a[col, q]
            for q in range(b.shape[1]):
                b[r, q] -= f * b[col, q]
    for col in range(m - 1, -1, -1):
        for q in range(b.shape[1]):
            acc = b[col, q]
            for r in range(col + 1, m):
                acc -= a[col, r] * b[r, q]
            b[col, q] = acc / a[col, col]
    return True


@numba.njit(nogil=True, cache=True)
def _fill_row(dx, dy, st, max_gap, support, degree, left, right, a, b):  # pragma: no cover - compiled
    nx = st.shape[0]
    reach = 2 * support
    m = degree + 1
    c = 0
    while c < nx:
        if not _is_hole(st[c]):
            c += 1
            continue
        s = c
        while c < nx and _is_hole(st[c]):
            c += 1
        e = c - 1  # hole [s, e]; c = e + 1
        if e - s + 1 > max_gap or s == 0 or e == nx - 1 or st[s - 1] != _MATCHED or st[e + 1] != _MATCHED:
            continue
        if _collect(st, s - 1, -1, reach, support, left) < support:
            continue
        if _collect(st, e + 1, 1, reach, support, right) < support:
            continue
        # Abscissa relative to the hole centre, scaled by the largest possible offset:
        # only column differences enter, so the fit does not depend on the row's origin.
        half_len = 0.5 * (e - s)
        scale = half_len + reach
        for i in range(m):
            for q in range(m):
                a[i, q] = 0.0
            b[i, 0] = 0.0
            b[i, 1] = 0.0
        for side in range(2):
            cols = left if side == 0 else right
            for i in range(support):
                j = cols[i]
                u = ((j - s) - half_len) / scale
                p = 1.0
                for r in range(m):
                    q_pow = p * p  # u^(r + q) for q = r
                    for q in range(r, m):
                        a[r, q] += q_pow
                        q_pow *= u
                    b[r, 0] += p * dx[j]
                    b[r, 1] += p * dy[j]
                    p *= u
        for r in range(m):
            for q in range(r):
                a[r, q] = a[q, r]
        if not _solve_inplace(a, b, m):
            continue
        for j in range(s, e + 1):
            u = ((j - s) - half_len) / scale
            vx = b[m - 1, 0]
            vy = b[m - 1, 1]
            for r in range(m - 2, -1, -1):
                vx = vx * u + b[r, 0]
                vy = vy * u + b[r, 1]
            dx[j] = vx
            dy[j] = vy
            st[j] = _FILLED


@numba.njit(nogil=True, cache=True)
def _postfilter_kernel(dx, dy, st, half, kk, min_dev, passes, min_nb, max_gap, support, degree):  # pragma: no cover
    ny, nx = st.shape
    flag = np.zeros(nx, dtype=np.bool_)
    check = np.zeros(nx, dtype=np.bool_)
    bx = np.empty(2 * half + 1, dtype=np.float64)
    by = np.empty(2 * half + 1, dtype=np.float64)
    left = np.empty(support, dtype=np.int64)
    right = np.empty(support, dtype=np.int64)
    a = np.empty((3, 3), dtype=np.float64)
    b = np.empty((3, 2), dtype=np.float64)
    for r in range(ny):
        _blunders_row(dx[r], dy[r], st[r], half, kk, min_dev, passes, min_nb, check, flag, bx, by)
        if max_gap > 0:
            _fill_row(dx[r], dy[r], st[r], max_gap, support, degree, left, right, a, b)


def _prepare(dx, dy, status, options):
    _check(options)
    dx = np.asarray(dx)
    dy = np.asarray(dy)
    status = np.asarray(status)
    if dx.ndim != 2 or dx.shape != dy.shape or dx.shape != status.shape:
        raise ValueError(f"dx, dy and status must be 2-D arrays of one shape, got {dx.shape}, {dy.shape}, {status.shape}")
    if not np.issubdtype(status.dtype, np.integer):
        raise TypeError(f"status must be an integer array, got {status.dtype}")
    return (
        np.array(dx, dtype=np.float32, order="C", copy=True),
        np.array(dy, dtype=np.float32, order="C", copy=True),
        np.array(status, dtype=np.uint8, order="C", copy=True),
    )


def postfilter(
    dx: np.ndarray,
    dy: np.ndarray,
    status: np.ndarray,
    *,
    options: PostFilterOptions = PostFilterOptions(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove blunders from a dense displacement field and fill short holes, row by row.

    See the module docstring for the exact rules.

    Parameters
    ----------
    dx, dy : ndarray, shape (rows, cols)
        Displacement components on the base grid (NaN where not matched).
    status : ndarray of int, shape (rows, cols)
        :class:`geocoder.status.Status` codes.
    options : PostFilterOptions
        Filter settings.

    Returns
    -------
    dx, dy : ndarray of float32
        New arrays; blunders are NaN, filled pixels hold the fitted values, every
        other pixel is copied unchanged.
    status : ndarray of uint8
        New status array (``BLUNDER`` and ``FILLED`` where the filter acted).
    """
    dx, dy, st = _prepare(dx, dy, status, options)
    if st.size:
        _postfilter_kernel(
            dx, dy, st,
            options.window // 2, options.k * _MAD_SCALE, float(options.min_dev), int(options.passes),
            MIN_NEIGHBOURS, int(options.max_gap), int(options.support),
            min(int(options.order), 2 * int(options.support) - 1),
        )  # fmt: skip
    return dx, dy, st
