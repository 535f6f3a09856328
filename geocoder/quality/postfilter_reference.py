"""Numpy reference of :func:`geocoder.quality.postfilter.postfilter` (for the tests).

The same rules, vectorised over the pixels with ``numpy.nanmedian`` and ``numpy.polyfit``
instead of sorted sliding windows and per-row kernels: slow, and written to be read against
the rules in :mod:`geocoder.quality.postfilter`'s docstring.
"""

from __future__ import annotations

import warnings

import numpy as np

from .postfilter import (
    _BLUNDER,
    _FILLED,
    _MAD_SCALE,
    _MATCHED,
    _NO_TEXTURE,
    MIN_NEIGHBOURS,
    PostFilterOptions,
    _prepare,
)

__all__ = ["postfilter_reference"]


def _reference_flags(dx, dy, st, half, kk, min_dev):
    """One blunder pass on the whole array (vectorised over pixels)."""
    ny, nx = st.shape
    w = 2 * half + 1
    matched = st == _MATCHED
    pad = ((0, 0), (half, half))
    mpad = np.pad(matched, pad, constant_values=False)
    mwin = np.lib.stride_tricks.sliding_window_view(mpad, w, axis=1).copy()
    mwin[..., half] = False  # exclude the pixel itself
    count = mwin.sum(axis=-1)
    out = np.zeros((ny, nx), dtype=bool)
    for d in (dx, dy):
        dpad = np.pad(d.astype(np.float64), pad, constant_values=np.nan)
        win = np.where(mwin, np.lib.stride_tricks.sliding_window_view(dpad, w, axis=1), np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: no neighbours
            med = np.nanmedian(win, axis=-1)
            mad = np.nanmedian(np.abs(win - med[..., None]), axis=-1)
            t = np.maximum(kk * mad, min_dev)
            out |= np.abs(d.astype(np.float64) - med) > t
    return out & matched & (count >= MIN_NEIGHBOURS)


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, first and last columns of the maximal True runs of a 2-D mask."""
    ny, nx = mask.shape
    edge = np.zeros((ny, nx + 2), dtype=np.int8)
    edge[:, 1:-1] = mask
    d = np.diff(edge, axis=1)
    r0, c0 = np.nonzero(d == 1)
    c1 = np.nonzero(d == -1)[1]
    return r0, c0, c1 - 1  # np.nonzero is row-major, so the starts and ends pair up


def postfilter_reference(
    dx: np.ndarray,
    dy: np.ndarray,
    status: np.ndarray,
    *,
    options: PostFilterOptions = PostFilterOptions(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy implementation of :func:`postfilter` (vectorised per pass, one loop over holes).

    Kept for the tests; the same rules, with ``numpy.polyfit`` for the fill, so filled
    values agree with :func:`postfilter` to rounding only.
    """
    dx, dy, st = _prepare(dx, dy, status, options)
    bad = (st == _MATCHED) & ~(np.isfinite(dx) & np.isfinite(dy))
    st[bad], dx[bad], dy[bad] = _BLUNDER, np.nan, np.nan
    half, kk = options.window // 2, options.k * _MAD_SCALE
    for _ in range(options.passes):
        flag = _reference_flags(dx, dy, st, half, kk, float(options.min_dev))
        if not flag.any():
            break
        st[flag], dx[flag], dy[flag] = _BLUNDER, np.nan, np.nan
    if options.max_gap == 0 or st.size == 0:
        return dx, dy, st
    nx = st.shape[1]
    support, reach = options.support, 2 * options.support
    degree = min(options.order, 2 * support - 1)
    hole = np.isin(st, (_FILLED, _BLUNDER, _NO_TEXTURE))
    matched = st == _MATCHED
    for r, s, e in zip(*_runs(hole)):
        if e - s + 1 > options.max_gap or s == 0 or e == nx - 1 or not (matched[r, s - 1] and matched[r, e + 1]):
            continue
        cols = []
        for seg_st, seg_cols in ((st[r, max(s - reach, 0) : s][::-1], np.arange(s - 1, max(s - reach, 0) - 1, -1)),
                                 (st[r, e + 1 : e + 1 + reach], np.arange(e + 1, min(e + 1 + reach, nx)))):  # fmt: skip
            barrier = ~np.isin(seg_st, (_MATCHED, _FILLED, _BLUNDER, _NO_TEXTURE))
            stop = int(np.argmax(barrier)) if barrier.any() else seg_st.size
            good = seg_cols[:stop][seg_st[:stop] == _MATCHED][:support]
            cols.append(good)
        if min(len(cols[0]), len(cols[1])) < support:
            continue
        xs = np.concatenate(cols)
        half_len = 0.5 * (e - s)
        u = ((xs - s) - half_len) / (half_len + reach)
        uh = ((np.arange(s, e + 1) - s) - half_len) / (half_len + reach)
        for d in (dx, dy):
            coef = np.polyfit(u, d[r, xs].astype(np.float64), degree)
            d[r, s : e + 1] = np.polyval(coef, uh)
        st[r, s : e + 1] = _FILLED
    return dx, dy, st
