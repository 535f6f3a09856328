"""Least-squares matching of one template on several co-registered bands at once (seed 003 sec. 11).

The multispectral Otto-Chau matcher: every band ``b`` of the template is matched under ONE
affine geometry and its OWN linear radiometry, ::

    base_b(col + u, row + v) ~ gain_b * dist_b(x + a11 u + a12 v, y + a21 u + a22 v) + offset_b

so the geometry is estimated from the texture of all bands together: a band without texture
in a patch adds nothing but its own two radiometric unknowns, and the patch still matches if
another band has texture there. Each Gauss-Newton iteration forms every band's 8x8 normal
equations exactly as :func:`geocoder.kernels.alsc.alsc_point` does (its moments, at the band's
radiometry), eliminates the band's two radiometric unknowns (the Schur complement of its 2x2
radiometric block), adds the reduced 6x6 geometric systems of all bands, solves them, and
back-substitutes each band's radiometry: the least-squares solution of the joint system of
``6 + 2 n`` unknowns. The relaxation, the convergence test and the exit codes are
``alsc_point``'s (the gain tested for ``DEGENERATE``, and reported, is the bands' mean
weighted by their templates' contrast: a band without texture has no defined gain); the statistics are the joint system's: ``sigma0^2 = sum_b e_b.e_b / (n_b npix
- 6 - 2 n_b)``, the shift block of ``sigma0^2`` times the inverse of the reduced geometric
matrix, and ``rho`` the correlation of all bands' templates and resampled patches pooled, each
about its own band's mean (bands weigh by their contrast, so a flat band does not pull it down).

Bands should come with unit noise in grey values (the caller scales each band by its noise
over the whole image, the same for every tile: :func:`band_scales`), since the joint least
squares weighs them by it.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .alsc import (
    _ACCEPTED,
    _NMOM,
    _NOT_CONVERGED,
    _OUTSIDE,
    _SEE,
    _SG,
    _SGG,
    _SINGULAR,
    _STG,
    F_GAIN,
    F_ITERATIONS,
    F_OFFSET,
    F_RHO,
    F_SIGMA_X,
    F_SIGMA_Y,
    NFIELDS,
    NPARAMS,
    _factor,
    _moments,
    _normal_equations,
    _relaxation,
    _shift_covariance,
    _solve,
    _verdict,
)

__all__ = ["alsc_point_bands", "band_scales"]

_NGEO = 6


def band_scales(stack: np.ndarray) -> np.ndarray:
    """``(n, 2)`` location (median) and noise of every band of ``stack`` (n, rows, cols), NaN ignored.

    Grey values ``(v - location) / noise`` give every band unit noise, so that the joint
    least squares of :func:`alsc_point_bands` and the every-pixel pass weighs the bands as
    their noise says (maximum likelihood), whatever their contrast. The noise is the median
    absolute response to the 3x3 Laplacian-difference mask ``[[1,-2,1],[-2,4,-2],[1,-2,1]]``
    (Immerkaer 1996, made robust to texture by the median): ``1.4826 median|L| / 6``; where
    that is 0 (noise-free data), the band's spread (MAD) instead.
    """
    out = np.empty((stack.shape[0], 2))
    for b, band in enumerate(stack):
        v = np.asarray(band, dtype=np.float64)
        finite = v[np.isfinite(v)]
        if finite.size == 0:
            out[b] = 0.0, 1.0
            continue
        med = float(np.median(finite))
        lap = (v[:-2, :-2] - 2 * v[:-2, 1:-1] + v[:-2, 2:] - 2 * v[1:-1, :-2] + 4 * v[1:-1, 1:-1] - 2 * v[1:-1, 2:]
               + v[2:, :-2] - 2 * v[2:, 1:-1] + v[2:, 2:])
        lap = np.abs(lap[np.isfinite(lap)])
        noise = 1.4826 * float(np.median(lap)) / 6.0 if lap.size else 0.0
        if not noise > 0:
            noise = 1.4826 * float(np.median(np.abs(finite - med)))
        out[b] = med, noise if noise > 0 else 1.0
    return out


@numba.njit(nogil=True, cache=True)
def _template_stats(base, col, row, rx, ry):  # pragma: no cover - compiled
    """Mean and sum of squares about it of one band's template; NaN mean if a value is not finite."""
    npix = (2 * rx + 1) * (2 * ry + 1)
    st = 0.0
    for r in range(row - ry, row + ry + 1):
        for c in range(col - rx, col + rx + 1):
            t = float(base[r, c])
            if not (t - t == 0.0):
                return np.nan, 0.0
            st += t
    tmean = st / npix
    stt = 0.0
    for r in range(row - ry, row + ry + 1):
        for c in range(col - rx, col + rx + 1):
            t = float(base[r, c]) - tmean
            stt += t * t
    return tmean, stt


@numba.njit(nogil=True, cache=True)
def alsc_point_bands(
    base, dist, col, row, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho, max_sigma, min_det,
):  # pragma: no cover - compiled
    """Multispectral least-squares match of one template; returns the exit code.

    Parameters
    ----------
    base : ndarray of float32, shape (n, H, W)
        Base window, ``n`` bands.
    dist : ndarray of float32, shape (n, H', W', 4)
        Distorted window's bands with their gradients (:func:`geocoder.kernels.alsc.samples`).
    col, row, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho, max_sigma, min_det
        As for :func:`geocoder.kernels.alsc.alsc_point`. ``init``'s offset and gain start every
        band; ``out``'s are the bands' means.

    Returns
    -------
    int
        The exit code (:class:`geocoder.kernels.alsc.Exit`).
    """
    nan = np.nan
    nb = base.shape[0]
    for k in range(NPARAMS):
        out[k] = init[k]
    for k in range(NPARAMS, NFIELDS):
        out[k] = nan
    out[F_ITERATIONS] = 0.0
    rx = radius
    ry = radius_y
    npix = (2 * rx + 1) * (2 * ry + 1)
    bh, bw = base.shape[1], base.shape[2]
    if col - rx < 0 or col + rx >= bw or row - ry < 0 or row + ry >= bh:
        return _OUTSIDE
    tmean = np.empty(nb)
    stt = np.empty(nb)
    for b in range(nb):
        m, s = _template_stats(base[b], col, row, rx, ry)
        if not (m - m == 0.0):
            return _OUTSIDE
        tmean[b] = m
        stt[b] = s

    geo = np.empty(NPARAMS)  # the band's parameters: the shared geometry, its radiometry
    rad = np.empty((nb, 2))  # offset, gain per band
    for b in range(nb):
        rad[b, 0] = init[6]
        rad[b, 1] = init[7]
    for k in range(_NGEO):
        geo[k] = init[k]
    mom = np.empty((nb, _NMOM))
    nmat = np.empty((NPARAMS, NPARAMS))
    rhs = np.empty(NPARAMS)
    cr = np.empty((nb, _NGEO, 2))  # C R^-1 per band, for the back-substitution
    rr = np.empty((nb, 2))  # R^-1 r per band
    red = np.empty((_NGEO, _NGEO))
    rrhs = np.empty(_NGEO)
    chol = np.zeros((_NGEO, _NGEO))
    scale = np.empty(_NGEO)
    step = np.empty(_NGEO)
    rstep = np.empty((nb, 2))
    unit = np.empty(_NGEO)
    x0 = init[0]
    y0 = init[1]
    det0 = init[2] * init[5] - init[3] * init[4]

    code = _ACCEPTED
    updates = 0
    omega = 1.0
    prev_x = 0.0
    prev_y = 0.0
    while True:
        outside = False
        singular = False
        for i in range(_NGEO):
            rrhs[i] = 0.0
            for j in range(_NGEO):
                red[i, j] = 0.0
        for b in range(nb):
            geo[6] = rad[b, 0]
            geo[7] = rad[b, 1]
            if not _moments(base[b], dist[b], col, row, geo, rx, ry, cubic, tmean[b], mom[b]):
                outside = True
                break
            _normal_equations(mom[b], rad[b, 1], npix, nmat, rhs)
            # the band's radiometric block R (offset, gain) and its inverse
            r00, r01, r11 = nmat[6, 6], nmat[6, 7], nmat[7, 7]
            det = r00 * r11 - r01 * r01
            if not (det > 0.0 and r00 > 0.0):
                singular = True
                continue
            i00, i01, i11 = r11 / det, -r01 / det, r00 / det
            rr[b, 0] = i00 * rhs[6] + i01 * rhs[7]
            rr[b, 1] = i01 * rhs[6] + i11 * rhs[7]
            for i in range(_NGEO):
                cr[b, i, 0] = nmat[i, 6] * i00 + nmat[i, 7] * i01
                cr[b, i, 1] = nmat[i, 6] * i01 + nmat[i, 7] * i11
            for i in range(_NGEO):
                rrhs[i] += rhs[i] - cr[b, i, 0] * rhs[6] - cr[b, i, 1] * rhs[7]
                for j in range(_NGEO):
                    red[i, j] += nmat[i, j] - cr[b, i, 0] * nmat[j, 6] - cr[b, i, 1] * nmat[j, 7]
        if outside:
            code = _OUTSIDE
            break
        if updates >= max_iter:
            code = _NOT_CONVERGED
            break
        if singular or not _factor(red, scale, chol):
            code = _SINGULAR
            break
        _solve(chol, scale, rrhs, step)
        for b in range(nb):
            for k in range(2):
                rstep[b, k] = rr[b, k]
                for i in range(_NGEO):
                    rstep[b, k] -= cr[b, i, k] * step[i]
        sx = step[0]
        sy = step[1]
        if updates > 0:
            omega = _relaxation(omega, sx, sy, prev_x, prev_y)
        for k in range(_NGEO):
            geo[k] += omega * step[k]
        for b in range(nb):
            rad[b, 0] += omega * rstep[b, 0]
            rad[b, 1] += omega * rstep[b, 1]
        updates += 1
        prev_x = sx
        prev_y = sy
        if math.sqrt(sx * sx + sy * sy) < tol:
            break  # converged: the statistics are those of this evaluation

    # the radiometry reported (and handed on as a start) is the bands' mean weighted by their
    # contrast: a band without texture has no defined gain
    mo = 0.0
    mg = 0.0
    wsum = 0.0
    for b in range(nb):
        mo += stt[b] * rad[b, 0]
        mg += stt[b] * rad[b, 1]
        wsum += stt[b]
    for k in range(_NGEO):
        out[k] = geo[k]
    out[F_OFFSET] = mo / wsum if wsum > 0.0 else rad[0, 0]
    out[F_GAIN] = mg / wsum if wsum > 0.0 else rad[0, 1]
    out[F_ITERATIONS] = float(updates)
    if code == _OUTSIDE:
        return code
    # the correlation of all bands pooled, each about its own means
    num = 0.0
    vt = 0.0
    vg = 0.0
    for b in range(nb):
        sg = mom[b, _SG]
        num += mom[b, _STG]
        vt += stt[b]
        vg += mom[b, _SGG] - sg * sg / npix
    rho = num / math.sqrt(vt * vg) if vt > 0.0 and vg > 0.0 else nan
    out[F_RHO] = rho
    if code == _SINGULAR:
        return code
    if not _factor(red, scale, chol):
        return _SINGULAR
    see = 0.0
    for b in range(nb):
        see += mom[b, _SEE]
    dof = nb * npix - _NGEO - 2 * nb
    s02 = see / dof if dof > 0 else nan
    cxx, cxy, cyy = _shift_covariance(chol, scale, s02, unit, step)
    out[F_SIGMA_X] = math.sqrt(cxx)
    out[F_SIGMA_Y] = math.sqrt(cyy)
    if code == _NOT_CONVERGED:
        return code
    # the gain tested is the contrast-weighted one: the textured bands are not inverted
    return _verdict(geo, x0, y0, det0, out[F_GAIN], rho, cxx, cxy, cyy, max_shift, min_rho, max_sigma, min_det)
