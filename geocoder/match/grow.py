"""Best-first region growing of least-squares matches (Otto & Chau 1989; seed 003 sec. 7).

Seeds are matched first; every accepted match predicts its unmatched neighbours on the
lattice (grid step ``step``) through its own affine, and those predictions wait in a
priority queue ordered by the quality of the match that made them (the largest variance of
its shift, smaller first). The first acceptable match of a pixel is kept; a pixel whose
match fails may be tried again from another neighbour, up to ``max_tries`` times. All of it
runs in numba: no Python per pixel.

State arrays are window-sized: ``params`` (h, w, 12) holds the ALSC fields
(:data:`geocoder.kernels.alsc.FIELDS`, positions in the distorted window's frame) and
``code`` (h, w) int8 the exit code of the last attempt (``UNVISITED`` before any).
Seeds are rows of :data:`SEED_COLUMNS` (see :func:`seed_rows`).
"""

from __future__ import annotations

import numba
import numpy as np

from ..kernels.alsc import (
    F_A11,
    F_A12,
    F_A21,
    F_A22,
    F_SIGMA_X,
    F_SIGMA_Y,
    F_X,
    F_Y,
    FIELDS,
    NFIELDS,
    NPARAMS,
    AlscOptions,
    Exit,
    alsc_point,
    samples,
)
from ..kernels.alsc_bands import alsc_point_bands

__all__ = ["NFIELDS", "SEED_COLUMNS", "SEED_COL", "SEED_PARAMS", "SEED_ROW", "SEED_WIDTH", "SEED_X", "SEED_Y",
           "UNVISITED", "grow", "grow_window", "seed_rows"]

UNVISITED = -1

#: Columns of a seed row: the pixel (row, col) of the base window, then the start parameters
#: of its match in the order of :data:`geocoder.kernels.alsc.FIELDS` (distorted window frame).
SEED_COLUMNS = ("row", "col", *FIELDS[:NPARAMS])
SEED_ROW = SEED_COLUMNS.index("row")
SEED_COL = SEED_COLUMNS.index("col")
SEED_PARAMS = SEED_COLUMNS.index(FIELDS[0])  # first of the NPARAMS start parameters
SEED_X = SEED_PARAMS + F_X
SEED_Y = SEED_PARAMS + F_Y
SEED_WIDTH = len(SEED_COLUMNS)

_ACCEPTED = int(Exit.ACCEPTED)

_N4 = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int64)
_N8 = np.array([[0, 1], [1, 0], [0, -1], [-1, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=np.int64)


@numba.njit(nogil=True, cache=True)
def _heap_push(keys, items, parents, size, key, item, parent):
    if size == keys.size:
        nk = np.empty(keys.size * 2, keys.dtype)
        ni = np.empty(items.size * 2, items.dtype)
        npr = np.empty(parents.size * 2, parents.dtype)
        nk[:size] = keys[:size]
        ni[:size] = items[:size]
        npr[:size] = parents[:size]
        keys, items, parents = nk, ni, npr
    i = size
    keys[i], items[i], parents[i] = key, item, parent
    while i > 0:
        p = (i - 1) // 2
        if keys[p] < keys[i] or (keys[p] == keys[i] and items[p] <= items[i]):
            break
        keys[p], keys[i] = keys[i], keys[p]
        items[p], items[i] = items[i], items[p]
        parents[p], parents[i] = parents[i], parents[p]
        i = p
    return keys, items, parents, size + 1


@numba.njit(nogil=True, cache=True)
def _heap_pop(keys, items, parents, size):
    key, item, parent = keys[0], items[0], parents[0]
    size -= 1
    keys[0], items[0], parents[0] = keys[size], items[size], parents[size]
    i = 0
    while True:
        left = 2 * i + 1
        if left >= size:
            break
        c = left
        right = left + 1
        if right < size and (keys[right] < keys[left] or (keys[right] == keys[left] and items[right] < items[left])):
            c = right
        if keys[i] < keys[c] or (keys[i] == keys[c] and items[i] <= items[c]):
            break
        keys[c], keys[i] = keys[i], keys[c]
        items[c], items[i] = items[i], items[c]
        parents[c], parents[i] = parents[i], parents[c]
        i = c
    return key, item, parent, size


@numba.njit(nogil=True, cache=True)
def _match(base, dist, c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho, max_sigma,
           min_det):  # pragma: no cover - compiled
    if base.shape[0] == 1:
        return alsc_point(base[0], dist[0], c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift,
                          min_rho, max_sigma, min_det)
    return alsc_point_bands(base, dist, c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho,
                            max_sigma, min_det)


@numba.njit(nogil=True, cache=True)
def _quality(p):
    return max(p[F_SIGMA_X], p[F_SIGMA_Y])  # smaller is better


@numba.njit(nogil=True, cache=True)
def grow(
    base, dist, seeds, params, code, tries, region, step, lattice_origin,
    neighbours, max_tries, col_step, row_step, param_stride, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho,
    max_sigma, min_det,
):
    """Grow matches from ``seeds`` inside ``region``; returns the number of new matches.

    Parameters
    ----------
    base : float32 (bands, rows, cols)
        Base window.
    dist : float32 (bands, rows, cols, 4)
        Distorted window with its gradients (:func:`~geocoder.kernels.alsc.samples`); with
        several bands every match is on all of them at once
        (:func:`~geocoder.kernels.alsc_bands.alsc_point_bands`).
    seeds : float64 (k, SEED_WIDTH)
        Rows of :data:`SEED_COLUMNS`: ``row, col`` (base window) then the start parameters
        (distorted window frame).
    params, code, tries : window-sized state, updated in place; ``params`` holds every
        ``param_stride``-th column only, from ``lattice_origin[1] % param_stride`` (1: every column).
        The columns of a lattice's matches are all there is to keep when ``param_stride`` is its
        column spacing (a window of 12 float64 fields per pixel costs 16 times the memory and time).
    region : int64[4]
        ``row0, row1, col0, col1`` (half open, base window) where matches may be made.
    step : int
        Lattice spacing; only pixels with ``(row - lattice_origin[0]) % (step * row_step) == 0`` and
        ``(col - lattice_origin[1]) % (step * col_step) == 0`` are matched.
    neighbours : int64 (m, 2)
        Neighbour offsets in lattice units (4- or 8-neighbourhood).
    col_step : int
        Extra spacing of the lattice columns (along the scan line): the columns between are
        left to :func:`geocoder.match.fill.fill_lines` or :mod:`geocoder.match.densify`.
    row_step : int
        Extra spacing of the lattice rows (across the scan lines): the rows between start from
        their neighbours' (:func:`geocoder.match.densify.rows_between`).
    """
    h, w = code.shape
    p0 = lattice_origin[1] % param_stride
    cap = max(1024, seeds.shape[0] * 8)
    keys = np.empty(cap, np.float64)
    items = np.empty(cap, np.int64)
    parents = np.empty(cap, np.int64)
    size = 0
    out = np.empty(NFIELDS, np.float64)
    init = np.empty(NPARAMS, np.float64)
    new = 0
    r0, r1, c0, c1 = region[0], region[1], region[2], region[3]
    # seeds first, in the order given; an accepted seed is queued as its own parent
    for k in range(seeds.shape[0]):
        r, c = int(seeds[k, SEED_ROW]), int(seeds[k, SEED_COL])
        for j in range(NPARAMS):
            init[j] = seeds[k, SEED_PARAMS + j]
        # a seed between lattice columns moves to the lattice column on its left, its start
        # predicted through its own affine
        shift = (c - lattice_origin[1]) % (step * col_step) if col_step > 1 else 0
        if shift != 0:
            c -= shift
            init[F_X] -= init[F_A11] * shift
            init[F_Y] -= init[F_A21] * shift
        # and one between lattice rows to the lattice row above
        shift = (r - lattice_origin[0]) % (step * row_step) if row_step > 1 else 0
        if shift != 0:
            r -= shift
            init[F_X] -= init[F_A12] * shift
            init[F_Y] -= init[F_A22] * shift
        if r < r0 or r >= r1 or c < c0 or c >= c1 or code[r, c] == _ACCEPTED:
            continue
        if (r - lattice_origin[0]) % step != 0 or (c - lattice_origin[1]) % step != 0:
            continue
        e = _match(
            base, dist, c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho, max_sigma, min_det,
        )
        code[r, c] = e
        if e == _ACCEPTED:
            params[r, (c - p0) // param_stride, :] = out
            new += 1
            keys, items, parents, size = _heap_push(keys, items, parents, size, _quality(out), r * w + c, -1)
    while size > 0:
        key, item, parent, size = _heap_pop(keys, items, parents, size)
        r, c = item // w, item % w
        if parent >= 0:
            # a prediction for (r, c) from an accepted neighbour: match it
            if code[r, c] == _ACCEPTED or tries[r, c] >= max_tries:
                continue
            pr, pc = parent // w, parent % w
            du, dv = float(c - pc), float(r - pr)
            p = params[pr, (pc - p0) // param_stride]
            init[F_X] = p[F_X] + p[F_A11] * du + p[F_A12] * dv
            init[F_Y] = p[F_Y] + p[F_A21] * du + p[F_A22] * dv
            for j in range(F_A11, NPARAMS):
                init[j] = p[j]
            tries[r, c] += 1
            e = _match(
                base, dist, c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho, max_sigma,
                min_det,
            )
            code[r, c] = e
            if e != _ACCEPTED:
                continue
            params[r, (c - p0) // param_stride, :] = out
            new += 1
            key = _quality(out)
        # (r, c) is accepted: queue its unmatched neighbours with it as the parent
        for n in range(neighbours.shape[0]):
            rr = r + neighbours[n, 0] * step * row_step
            cc = c + neighbours[n, 1] * step * col_step
            if rr < r0 or rr >= r1 or cc < c0 or cc >= c1:
                continue
            if code[rr, cc] == _ACCEPTED or tries[rr, cc] >= max_tries:
                continue
            keys, items, parents, size = _heap_push(keys, items, parents, size, key, rr * w + cc, r * w + c)
    return new


def grow_window(
    base: np.ndarray,
    dist: np.ndarray,
    seeds: np.ndarray,
    params: np.ndarray,
    code: np.ndarray,
    region: tuple[int, int, int, int],
    *,
    options: AlscOptions,
    step: int = 1,
    lattice_origin: tuple[int, int] = (0, 0),
    neighbours: int = 4,
    max_tries: int = 2,
    col_step: int = 1,
    row_step: int = 1,
    param_stride: int = 1,
) -> int:
    """Python entry to :func:`grow` with options unpacked; returns the number of new matches.

    ``params`` holds every ``param_stride``-th column of the window (see :func:`grow`).
    ``base`` and ``dist`` are one band (2-D) or several (3-D, bands first: matched on all of
    them at once); the gradients of ``dist`` are made here (:func:`~geocoder.kernels.alsc.samples`).
    """
    if param_stride > 1 and (step * col_step) % param_stride:
        raise ValueError(f"param_stride {param_stride} must divide the lattice's column spacing {step * col_step}")
    tries = np.zeros(code.shape, np.uint8)
    offsets = _N4 if neighbours == 4 else _N8
    o = options

    def bands(a: np.ndarray) -> np.ndarray:
        a = np.asarray(a)
        return np.ascontiguousarray(a[None] if a.ndim == 2 else a, dtype=np.float32)

    return int(
        grow(
            bands(base), samples(bands(dist)), np.ascontiguousarray(seeds, dtype=np.float64), params, code, tries,
            np.asarray(region, dtype=np.int64), int(step), np.asarray(lattice_origin, dtype=np.int64),
            offsets, int(max_tries), int(col_step), int(row_step), int(param_stride), *o.kernel_args(),
        )
    )


def seed_rows(row: np.ndarray, col: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Seed rows (:data:`SEED_COLUMNS`) from pixels and the start parameters of their matches.

    Parameters
    ----------
    row, col : ndarray, shape (n,)
        Pixel of every seed.
    params : ndarray, shape (n, NPARAMS)
        Start parameters in the order of :data:`geocoder.kernels.alsc.FIELDS`.

    Returns
    -------
    ndarray of float64, shape (n, SEED_WIDTH)
    """
    params = np.asarray(params)
    if params.ndim != 2 or params.shape[1] != NPARAMS:
        raise ValueError(f"params must have shape (n, {NPARAMS}), got {params.shape}")
    out = np.empty((params.shape[0], SEED_WIDTH), dtype=np.float64)
    out[:, SEED_ROW] = row
    out[:, SEED_COL] = col
    out[:, SEED_PARAMS : SEED_PARAMS + NPARAMS] = params
    return out
