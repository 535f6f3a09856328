"""Least-squares matches between the lattice columns of the region growing.

Region growing (:mod:`geocoder.match.grow`) with ``col_step = k > 1`` matches every row but
only every k-th column (global lattice). Along a scan line the displacement field is smooth,
so the pixels between two converged lattice neighbours start from the linear interpolation
of their eight parameters and take one verified Gauss-Newton step
(:func:`~geocoder.kernels.alsc.alsc_step`: normal equations evaluated once, sigma from the
full 8x8 inverse, the usual acceptance tests). When that step is not short (``step_tol``),
or the interpolation is not possible because only one lattice neighbour matched, the pixel
gets a full match (:func:`~geocoder.kernels.alsc.alsc_point`) from the interpolation or the
neighbour's affine prediction. A pixel whose two lattice neighbours both failed stays
unmatched.

Every pixel depends on its two lattice neighbours only (never on another filled pixel), so
the result does not depend on the order of the pixels nor on the tiling, and a tile can be
filled as soon as the lattice matches of its core and of ``k`` columns on either side are
final. All of it runs in numba: no Python per pixel.
"""

from __future__ import annotations

import numba
import numpy as np

from ..kernels.alsc import F_A11, F_A21, F_X, F_Y, NFIELDS, NPARAMS, AlscOptions, Exit, alsc_point, alsc_step, samples

__all__ = ["fill_lines", "fill_window", "fill_reference"]

_ACCEPTED = int(Exit.ACCEPTED)
_NOT_CONVERGED = int(Exit.NOT_CONVERGED)


@numba.njit(nogil=True, cache=True)
def fill_lines(
    base, dist, params, code, region, col_step, col_origin, step_tol, radius, radius_y, cubic,
    max_iter, tol, max_shift, min_rho, max_sigma, min_det,
):  # pragma: no cover - compiled
    """Match the pixels between lattice columns inside ``region``; returns the number of new matches.

    Parameters
    ----------
    base, dist : float32 windows (see :func:`~geocoder.kernels.alsc.alsc_point`): the base (h, w)
        and the distorted window with its gradients (h', w', 4).
    params : float64 (h, w, NFIELDS)
        ALSC fields of the window (positions in the distorted window's frame); the lattice
        columns hold the matches of the region growing; filled in place.
    code : int8 (h, w)
        Exit codes (0 = matched, -1 = not tried); filled in place.
    region : int64[4]
        ``row0, row1, col0, col1`` (half open) of the pixels to fill; their lattice
        neighbours may lie outside it (anywhere in the window).
    col_step, col_origin : int
        Lattice columns are those with ``(col - col_origin) % col_step == 0``.
    step_tol : float
        Largest ``(x, y)`` step (px) accepted after the one step from the interpolation.
    radius ... min_det
        As for :func:`~geocoder.kernels.alsc.alsc_point`.
    """
    h, w = code.shape
    out = np.empty(NFIELDS, np.float64)
    init = np.empty(NPARAMS, np.float64)
    new = 0
    for r in range(region[0], region[1]):
        for c in range(region[2], region[3]):
            off = (c - col_origin) % col_step
            if off == 0 or code[r, c] == _ACCEPTED:
                continue
            cl = c - off
            cr = cl + col_step
            left = cl >= 0 and code[r, cl] == _ACCEPTED
            right = cr < w and code[r, cr] == _ACCEPTED
            if left and right:
                wr = off / col_step
                for j in range(NPARAMS):
                    init[j] = (1.0 - wr) * params[r, cl, j] + wr * params[r, cr, j]
                e = alsc_step(
                    base, dist, c, r, init, out, radius, radius_y, cubic, step_tol, max_shift, min_rho, max_sigma,
                    min_det,
                )
                if e == _NOT_CONVERGED:
                    e = alsc_point(
                        base, dist, c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho,
                        max_sigma, min_det,
                    )
            elif left or right:
                pc = cl if left else cr
                du = float(c - pc)
                init[F_X] = params[r, pc, F_X] + params[r, pc, F_A11] * du
                init[F_Y] = params[r, pc, F_Y] + params[r, pc, F_A21] * du
                for j in range(F_A11, NPARAMS):
                    init[j] = params[r, pc, j]
                e = alsc_point(
                    base, dist, c, r, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho,
                    max_sigma, min_det,
                )
            else:
                continue
            code[r, c] = e
            if e == _ACCEPTED:
                for j in range(NFIELDS):
                    params[r, c, j] = out[j]
                new += 1
    return new


def fill_window(
    base: np.ndarray,
    dist: np.ndarray,
    params: np.ndarray,
    code: np.ndarray,
    region: tuple[int, int, int, int],
    *,
    options: AlscOptions,
    col_step: int,
    col_origin: int = 0,
    step_tol: float = 0.02,
) -> int:
    """Python entry to :func:`fill_lines` with options unpacked; returns the number of new matches.

    ``base`` and ``dist`` are 2-D windows; the gradients of ``dist`` are made here.
    """
    if col_step < 2:
        return 0
    return int(
        fill_lines(
            np.ascontiguousarray(base, dtype=np.float32), samples(dist), params, code,
            np.asarray(region, dtype=np.int64), int(col_step), int(col_origin), float(step_tol),
            *options.kernel_args(),
        )
    )


def fill_reference(
    base: np.ndarray,
    dist: np.ndarray,
    params: np.ndarray,
    code: np.ndarray,
    region: tuple[int, int, int, int],
    *,
    options: AlscOptions,
    col_step: int,
    col_origin: int = 0,
    step_tol: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Numpy/reference version of :func:`fill_lines` (for the tests): new ``params, code``.

    Uses :func:`~geocoder.kernels.alsc_reference.alsc_step_reference` and
    :func:`~geocoder.kernels.alsc_reference.alsc_reference` pixel by pixel (slow; small windows only).
    """
    from ..kernels.alsc import Exit
    from ..kernels.alsc_reference import alsc_reference, alsc_step_reference

    params = params.copy()
    code = code.copy()
    lattice_params = params.copy()
    lattice_code = code.copy()
    h, w = code.shape
    for r in range(region[0], region[1]):
        for c in range(region[2], region[3]):
            off = (c - col_origin) % col_step
            if off == 0 or code[r, c] == 0:
                continue
            cl, cr = c - off, c - off + col_step
            left = cl >= 0 and lattice_code[r, cl] == 0
            right = cr < w and lattice_code[r, cr] == 0
            if left and right:
                wr = off / col_step
                init = (1.0 - wr) * lattice_params[r, cl, :8] + wr * lattice_params[r, cr, :8]
                out, e = alsc_step_reference(base, dist, c, r, init, step_tol=step_tol, options=options)
                if e == Exit.NOT_CONVERGED:
                    out, e = alsc_reference(base, dist, c, r, init, options=options)
            elif left or right:
                pc = cl if left else cr
                p = lattice_params[r, pc, :8]
                init = p.copy()
                init[0] = p[0] + p[2] * (c - pc)
                init[1] = p[1] + p[4] * (c - pc)
                out, e = alsc_reference(base, dist, c, r, init, options=options)
            else:
                continue
            code[r, c] = e
            if e == Exit.ACCEPTED:
                params[r, c] = out
    return params, code
