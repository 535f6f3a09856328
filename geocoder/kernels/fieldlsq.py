"""Least-squares matching of every pixel of a window at once, on a field-warped image.

:mod:`geocoder.kernels.alsc` matches one template at a time: each evaluation resamples the
distorted image under that template's own affine, so a pixel costs 4-6 evaluations of 357
samples. When a displacement field ``d0`` is already known to a fraction of a pixel (the
region growing's lattice, interpolated along the scan lines), the distorted image and its
gradients can instead be resampled ONCE per iteration for the whole window at
``p + d(p)``; every template then sees the same warped image ``I``, and all of its normal
equations are window sums of products of per-pixel images, which sliding sums give at
O(1) per pixel whatever the template size.

Per template (``(2 rx + 1) x (2 ry + 1)`` pixels centred on ``p``, offsets ``u, v``) the
model is the Otto-Chau/Gruen one, linearised about the current position ``q(x)`` of EVERY
template pixel ``x`` (not about the centre's), with the radiometry made linear by scaling the
geometric unknowns with the gain::

    T(x) ~ alpha y_p(x) + beta + gx (sx + c11 u + c12 v) + gy (sy + c21 u + c22 v)
    y_p(x) = I(x + q(x)) - g(x) . (q(x) - q(p))

(``T`` the base template, ``I`` the distorted image, ``g = (gx, gy)`` the slopes of its
bilinear interpolant at ``x + q(x)``: the exact derivatives, so that ``I + g . dq`` IS the
interpolant wherever ``dq`` stays in the same cell, which makes the solution that of ALSC
sampled at its own affine, not a function of how rough the neighbours' positions are).
The unknowns are linear: the position of ``p`` moves by ``(sx, sy) / alpha`` and its affine
by ``c / alpha``; ``alpha, beta`` are gain and offset. The centring on ``q(p)`` is done
algebraically from the same window sums, so one set of sums serves every template. The
statistics are those of the last evaluation, as in ALSC: ``sigma0^2 = e.e / (n - 8)`` of the
residuals in the template's grey values, the shift covariance
``sigma0^2 [N^-1]_ss / alpha^2`` (the shift block of the full inverse) and ``rho``, the
correlation coefficient of ``T`` and ``I`` over the template.

The window sums ``sum u^a v^b f`` (``a + b <= 2``) come from prefix sums along each row
(moments about the centre from those of the column index) and a direct sum over the
``2 ry + 1`` rows, kept in a ring buffer of rows, so memory is a few rows per channel.

That is ``gradients="image"``. The default, ``gradients="template"``, takes the design's
slopes from the base template (its central differences: fixed, and free of the resampled
image's noise, which the interpolant's slopes carry into the design and which biases their
fixed point on smooth texture) and needs no linearisation about each centre: every round
averages the field over the template's box, resamples the image at that smooth field, solves

    T(x) ~ alpha I(x + qbar(x)) + beta + gx_T (sx + c11 u + c12 v) + gy_T (sy + c21 u + c22 v)

(the template's move in its own grey values: no division by the gain) and moves the pixel to
``qbar(p) + (sx, sy)``. A pixel's own noise so never feeds back except through the box mean;
the fixed point's remaining noise gain (1.16 for 51 x 7) is folded into sigma.

Dependencies are local: after ``n`` iterations a pixel depends on ``d0`` within ``n`` template
half-sizes of it (``2 n`` with the template's gradients: the box, then the template), and on
the images one template further, so a tile computed with that halo gives the same result for
any tiling. Exit codes are those of :class:`geocoder.kernels.alsc.Exit`, decided in the same order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.ndimage import uniform_filter

from .alsc import Exit

__all__ = ["FieldLsqResult", "field_lsq", "template_solution_reference"]

_ACCEPTED = int(Exit.ACCEPTED)
_OUTSIDE = int(Exit.OUTSIDE)
_SINGULAR = int(Exit.SINGULAR)
_NOT_CONVERGED = int(Exit.NOT_CONVERGED)
_MOVED = int(Exit.MOVED)
_DEGENERATE = int(Exit.DEGENERATE)
_LOW_CORRELATION = int(Exit.LOW_CORRELATION)
_IMPRECISE = int(Exit.IMPRECISE)
_NOT_TRIED = -1

_MIN_PIVOT = 1e-12

# Horizontal moment planes (prefix sums along a row, per channel and power of u).
# quadratic channels (a = 0, 1, 2): gx gx, gx gy, gy gy
_XX, _XY, _YY = 0, 3, 6
# linear channels (a = 0, 1): gx t, gy t, gx, gy, gx i, gy i
_XT, _YT, _X, _Y, _XI, _YI = 9, 11, 13, 15, 17, 19
# scalar channels (a = 0): t t, t, t y, y, y y, count, and t i, i, i i for the correlation
_TT, _T, _TI, _I, _II, _W, _TR, _R, _RR = 21, 22, 23, 24, 25, 26, 27, 28, 29
_NSCALARS = 9
# the precision's channels (final round only), on the smooth central-difference gradients c:
# cx cx, cx cy, cy cy (a = 0, 1, 2); cx i, cy i, cx, cy (a = 0, 1)
_CXX, _CXY, _CYY, _CXR, _CYR, _CX, _CY = 30, 33, 36, 39, 41, 43, 45
_NPLANES_SOLVE = 30
_NPLANES = 47


@numba.njit(nogil=True, cache=True)
def _warp(dist, px, py, region, iw, gxw, gyw):  # pragma: no cover - compiled
    """Bilinear samples of ``dist`` and the slopes of the interpolant at ``(px, py)`` inside ``region``.

    NaN outside the image (the 2x2 taps must lie inside it) or where a tap is NaN.
    """
    hd, wd = dist.shape
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            x = px[r, c]
            y = py[r, c]
            if not (x >= 0.0 and x < wd - 1 and y >= 0.0 and y < hd - 1):
                iw[r, c] = np.nan
                gxw[r, c] = np.nan
                gyw[r, c] = np.nan
                continue
            ix = int(x)
            iy = int(y)
            fx = x - ix
            fy = y - iy
            a = dist[iy, ix]
            b = dist[iy, ix + 1]
            d = dist[iy + 1, ix]
            e = dist[iy + 1, ix + 1]
            top = a + fx * (b - a)
            bottom = d + fx * (e - d)
            iw[r, c] = top + fy * (bottom - top)
            gxw[r, c] = (b - a) + fy * ((e - d) - (b - a))
            gyw[r, c] = bottom - top


@numba.njit(nogil=True, cache=True)
def _sample(image, px, py, region, out):  # pragma: no cover - compiled
    """Bilinear samples of ``image`` at ``(px, py)`` inside ``region`` (NaN outside)."""
    hd, wd = image.shape
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            x = px[r, c]
            y = py[r, c]
            if not (x >= 0.0 and x < wd - 1 and y >= 0.0 and y < hd - 1):
                out[r, c] = np.nan
                continue
            ix = int(x)
            iy = int(y)
            fx = x - ix
            fy = y - iy
            top = image[iy, ix] + fx * (image[iy, ix + 1] - image[iy, ix])
            bottom = image[iy + 1, ix] + fx * (image[iy + 1, ix + 1] - image[iy + 1, ix])
            out[r, c] = top + fy * (bottom - top)


@numba.njit(nogil=True, cache=True, inline="always")
def _add3(pre, q, j, v, x, x2):  # pragma: no cover - compiled
    """Prefix sums of ``v``, ``x v`` and ``x^2 v`` in planes ``q .. q + 2``."""
    pre[q, j + 1] = pre[q, j] + v
    pre[q + 1, j + 1] = pre[q + 1, j] + x * v
    pre[q + 2, j + 1] = pre[q + 2, j] + x2 * v


@numba.njit(nogil=True, cache=True, inline="always")
def _add2(pre, q, j, v, x):  # pragma: no cover - compiled
    """Prefix sums of ``v`` and ``x v`` in planes ``q, q + 1``."""
    pre[q, j + 1] = pre[q, j] + v
    pre[q + 1, j + 1] = pre[q + 1, j] + x * v


@numba.njit(nogil=True, cache=True)
def _row_planes(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, r, c0, c1, rx, nplanes, centre, pre,
                out):  # pragma: no cover - compiled
    """Horizontal window sums of row ``r`` for centres ``c0 + rx .. c1 - rx - 1`` into ``out`` (planes, cols).

    ``pre`` is a work array (planes, cols + 1) for the prefix sums over columns ``c0 .. c1 - 1``.
    The linearised channel is ``y = I - g . (q - q_ref)`` with ``q = (px - col, py - row)`` the
    pixel's current position relative to it and ``q_ref = (qx, qy)`` a constant of the task;
    :func:`_assemble` moves the reference to each template's centre. With ``nplanes =
    _NPLANES`` the precision's channels of the smooth gradients ``(cxw, cyw)`` are summed too.
    """
    n = c1 - c0
    for k in range(nplanes):
        pre[k, 0] = 0.0
    for j in range(n):
        c = c0 + j
        x = float(j)
        x2 = x * x
        tv = float(t[r, c])
        rv = iw[r, c]
        gx = gxw[r, c]
        gy = gyw[r, c]
        iv = rv - gx * (px[r, c] - c - qx) - gy * (py[r, c] - r - qy) if centre else rv
        ok = weight[r, c] and (tv - tv == 0.0) and (iv - iv == 0.0) and (gx - gx == 0.0) and (gy - gy == 0.0)
        if not ok:
            for k in range(nplanes):
                pre[k, j + 1] = pre[k, j]
            continue
        _add3(pre, _XX, j, gx * gx, x, x2)
        _add3(pre, _XY, j, gx * gy, x, x2)
        _add3(pre, _YY, j, gy * gy, x, x2)
        _add2(pre, _XT, j, gx * tv, x)
        _add2(pre, _YT, j, gy * tv, x)
        _add2(pre, _X, j, gx, x)
        _add2(pre, _Y, j, gy, x)
        _add2(pre, _XI, j, gx * iv, x)
        _add2(pre, _YI, j, gy * iv, x)
        pre[_TT, j + 1] = pre[_TT, j] + tv * tv
        pre[_T, j + 1] = pre[_T, j] + tv
        pre[_TI, j + 1] = pre[_TI, j] + tv * iv
        pre[_I, j + 1] = pre[_I, j] + iv
        pre[_II, j + 1] = pre[_II, j] + iv * iv
        pre[_W, j + 1] = pre[_W, j] + 1.0
        pre[_TR, j + 1] = pre[_TR, j] + tv * rv
        pre[_R, j + 1] = pre[_R, j] + rv
        pre[_RR, j + 1] = pre[_RR, j] + rv * rv
        if nplanes > _NPLANES_SOLVE:
            cx = cxw[r, c]
            cy = cyw[r, c]
            if not (cx - cx == 0.0 and cy - cy == 0.0):  # next to nodata: the slopes, never a NaN in a sum
                cx = gx
                cy = gy
            _add3(pre, _CXX, j, cx * cx, x, x2)
            _add3(pre, _CXY, j, cx * cy, x, x2)
            _add3(pre, _CYY, j, cy * cy, x, x2)
            _add2(pre, _CXR, j, cx * rv, x)
            _add2(pre, _CYR, j, cy * rv, x)
            _add2(pre, _CX, j, cx, x)
            _add2(pre, _CY, j, cy, x)
    for j in range(rx, n - rx):
        lo = j - rx
        hi = j + rx + 1
        x = float(j)
        for k in range(nplanes):
            out[k, j] = pre[k, hi] - pre[k, lo]
        # moments about the centre: sum (x' - x) f = S1 - x S0; sum (x' - x)^2 f = S2 - 2 x S1 + x^2 S0
        for q in (_XX, _XY, _YY, _CXX, _CXY, _CYY):
            if q >= nplanes:
                break
            s0 = out[q, j]
            s1 = out[q + 1, j]
            out[q + 2, j] = out[q + 2, j] - 2.0 * x * s1 + x * x * s0
            out[q + 1, j] = s1 - x * s0
        for q in (_XT, _YT, _X, _Y, _XI, _YI, _CXR, _CYR, _CX, _CY):
            if q >= nplanes:
                break
            out[q + 1, j] = out[q + 1, j] - x * out[q, j]


@numba.njit(nogil=True, cache=True)
def _ldl_solve8(a, rhs, sol, full):  # pragma: no cover - compiled
    """Solve the 8x8 system ``a sol = rhs`` by ``a = L D L^T``, written out in scalars.

    Straight-line code keeps the factor in registers (3x faster than the loops). A pivot must
    exceed ``_MIN_PIVOT`` times its diagonal entry (the rule of a Cholesky factor scaled to a
    unit diagonal), so no scaling and no square root are needed. Returns ``(ok, d6, d7, l76)``:
    whether the factor exists, the last two pivots and the last sub-diagonal entry (the shift
    block of the inverse is ``[[1/d6 + l76^2/d7, -l76/d7], [-l76/d7, 1/d7]]``). ``sol`` gets the
    last four unknowns, all eight when ``full``.
    """
    a00 = a[0, 0]
    if not (a00 > 0.0 and a00 < np.inf):
        return False, 0.0, 0.0, 0.0
    d0 = a00
    if not (d0 > _MIN_PIVOT * a00):
        return False, 0.0, 0.0, 0.0
    i0 = 1.0 / d0
    w10 = a[1, 0]
    l10 = w10 * i0
    w20 = a[2, 0]
    l20 = w20 * i0
    w30 = a[3, 0]
    l30 = w30 * i0
    w40 = a[4, 0]
    l40 = w40 * i0
    w50 = a[5, 0]
    l50 = w50 * i0
    w60 = a[6, 0]
    l60 = w60 * i0
    w70 = a[7, 0]
    l70 = w70 * i0
    a11 = a[1, 1]
    if not (a11 > 0.0 and a11 < np.inf):
        return False, 0.0, 0.0, 0.0
    d1 = a11 - l10 * w10
    if not (d1 > _MIN_PIVOT * a11):
        return False, 0.0, 0.0, 0.0
    i1 = 1.0 / d1
    w21 = a[2, 1] - l20 * w10
    l21 = w21 * i1
    w31 = a[3, 1] - l30 * w10
    l31 = w31 * i1
    w41 = a[4, 1] - l40 * w10
    l41 = w41 * i1
    w51 = a[5, 1] - l50 * w10
    l51 = w51 * i1
    w61 = a[6, 1] - l60 * w10
    l61 = w61 * i1
    w71 = a[7, 1] - l70 * w10
    l71 = w71 * i1
    a22 = a[2, 2]
    if not (a22 > 0.0 and a22 < np.inf):
        return False, 0.0, 0.0, 0.0
    d2 = a22 - l20 * w20 - l21 * w21
    if not (d2 > _MIN_PIVOT * a22):
        return False, 0.0, 0.0, 0.0
    i2 = 1.0 / d2
    w32 = a[3, 2] - l30 * w20 - l31 * w21
    l32 = w32 * i2
    w42 = a[4, 2] - l40 * w20 - l41 * w21
    l42 = w42 * i2
    w52 = a[5, 2] - l50 * w20 - l51 * w21
    l52 = w52 * i2
    w62 = a[6, 2] - l60 * w20 - l61 * w21
    l62 = w62 * i2
    w72 = a[7, 2] - l70 * w20 - l71 * w21
    l72 = w72 * i2
    a33 = a[3, 3]
    if not (a33 > 0.0 and a33 < np.inf):
        return False, 0.0, 0.0, 0.0
    d3 = a33 - l30 * w30 - l31 * w31 - l32 * w32
    if not (d3 > _MIN_PIVOT * a33):
        return False, 0.0, 0.0, 0.0
    i3 = 1.0 / d3
    w43 = a[4, 3] - l40 * w30 - l41 * w31 - l42 * w32
    l43 = w43 * i3
    w53 = a[5, 3] - l50 * w30 - l51 * w31 - l52 * w32
    l53 = w53 * i3
    w63 = a[6, 3] - l60 * w30 - l61 * w31 - l62 * w32
    l63 = w63 * i3
    w73 = a[7, 3] - l70 * w30 - l71 * w31 - l72 * w32
    l73 = w73 * i3
    a44 = a[4, 4]
    if not (a44 > 0.0 and a44 < np.inf):
        return False, 0.0, 0.0, 0.0
    d4 = a44 - l40 * w40 - l41 * w41 - l42 * w42 - l43 * w43
    if not (d4 > _MIN_PIVOT * a44):
        return False, 0.0, 0.0, 0.0
    i4 = 1.0 / d4
    w54 = a[5, 4] - l50 * w40 - l51 * w41 - l52 * w42 - l53 * w43
    l54 = w54 * i4
    w64 = a[6, 4] - l60 * w40 - l61 * w41 - l62 * w42 - l63 * w43
    l64 = w64 * i4
    w74 = a[7, 4] - l70 * w40 - l71 * w41 - l72 * w42 - l73 * w43
    l74 = w74 * i4
    a55 = a[5, 5]
    if not (a55 > 0.0 and a55 < np.inf):
        return False, 0.0, 0.0, 0.0
    d5 = a55 - l50 * w50 - l51 * w51 - l52 * w52 - l53 * w53 - l54 * w54
    if not (d5 > _MIN_PIVOT * a55):
        return False, 0.0, 0.0, 0.0
    i5 = 1.0 / d5
    w65 = a[6, 5] - l60 * w50 - l61 * w51 - l62 * w52 - l63 * w53 - l64 * w54
    l65 = w65 * i5
    w75 = a[7, 5] - l70 * w50 - l71 * w51 - l72 * w52 - l73 * w53 - l74 * w54
    l75 = w75 * i5
    a66 = a[6, 6]
    if not (a66 > 0.0 and a66 < np.inf):
        return False, 0.0, 0.0, 0.0
    d6 = a66 - l60 * w60 - l61 * w61 - l62 * w62 - l63 * w63 - l64 * w64 - l65 * w65
    if not (d6 > _MIN_PIVOT * a66):
        return False, 0.0, 0.0, 0.0
    i6 = 1.0 / d6
    w76 = a[7, 6] - l70 * w60 - l71 * w61 - l72 * w62 - l73 * w63 - l74 * w64 - l75 * w65
    l76 = w76 * i6
    a77 = a[7, 7]
    if not (a77 > 0.0 and a77 < np.inf):
        return False, 0.0, 0.0, 0.0
    d7 = a77 - l70 * w70 - l71 * w71 - l72 * w72 - l73 * w73 - l74 * w74 - l75 * w75 - l76 * w76
    if not (d7 > _MIN_PIVOT * a77):
        return False, 0.0, 0.0, 0.0
    i7 = 1.0 / d7
    z0 = rhs[0]
    z1 = rhs[1] - l10 * z0
    z2 = rhs[2] - l20 * z0 - l21 * z1
    z3 = rhs[3] - l30 * z0 - l31 * z1 - l32 * z2
    z4 = rhs[4] - l40 * z0 - l41 * z1 - l42 * z2 - l43 * z3
    z5 = rhs[5] - l50 * z0 - l51 * z1 - l52 * z2 - l53 * z3 - l54 * z4
    z6 = rhs[6] - l60 * z0 - l61 * z1 - l62 * z2 - l63 * z3 - l64 * z4 - l65 * z5
    z7 = rhs[7] - l70 * z0 - l71 * z1 - l72 * z2 - l73 * z3 - l74 * z4 - l75 * z5 - l76 * z6
    x7 = z7 * i7
    sol[7] = x7
    x6 = z6 * i6 - (l76 * x7)
    sol[6] = x6
    x5 = z5 * i5 - (l65 * x6 + l75 * x7)
    sol[5] = x5
    x4 = z4 * i4 - (l54 * x5 + l64 * x6 + l74 * x7)
    sol[4] = x4
    if full:
        x3 = z3 * i3 - (l43 * x4 + l53 * x5 + l63 * x6 + l73 * x7)
        sol[3] = x3
        x2 = z2 * i2 - (l32 * x3 + l42 * x4 + l52 * x5 + l62 * x6 + l72 * x7)
        sol[2] = x2
        x1 = z1 * i1 - (l21 * x2 + l31 * x3 + l41 * x4 + l51 * x5 + l61 * x6 + l71 * x7)
        sol[1] = x1
        x0 = z0 * i0 - (l10 * x1 + l20 * x2 + l30 * x3 + l40 * x4 + l50 * x5 + l60 * x6 + l70 * x7)
        sol[0] = x0
    return True, d6, d7, l76


# row of each unknown (sx, sy, c11, c12, c21, c22, alpha, beta) in the normal equations: the shift last
_P0 = 6
_P1 = 7
_P2 = 0
_P3 = 1
_P4 = 2
_P5 = 3
_P6 = 4
_P7 = 5


@numba.njit(nogil=True, cache=True)
def _assemble(s, dx, dy, nmat, rhs):  # pragma: no cover - compiled
    """Normal equations of one template from its window sums ``s`` (layout in :func:`_centred_sums`).

    ``(dx, dy) = q(p) - q_ref`` moves the linearisation's reference to the template centre:
    ``y_p = y + g . (dx, dy)``. The unknowns ``sx, sy, c11, c12, c21, c22, alpha, beta``
    (index k) sit at row ``_Pk``: the shift last, so that its covariance block and its
    solution come from the last rows of the factor alone.
    """
    xx = 0
    xy = 6
    yy = 12
    xt = 18
    yt = 21
    gx = 24
    gy = 27
    xi = 30
    yi = 33
    sc = 36
    # geometry x geometry: sum g_i g_j m_i m_j
    nmat[_P0, _P0] = s[xx + 0]
    nmat[_P0, _P1] = nmat[_P1, _P0] = s[xy + 0]
    nmat[_P0, _P2] = nmat[_P2, _P0] = s[xx + 1]
    nmat[_P0, _P3] = nmat[_P3, _P0] = s[xx + 2]
    nmat[_P0, _P4] = nmat[_P4, _P0] = s[xy + 1]
    nmat[_P0, _P5] = nmat[_P5, _P0] = s[xy + 2]
    nmat[_P1, _P1] = s[yy + 0]
    nmat[_P1, _P2] = nmat[_P2, _P1] = s[xy + 1]
    nmat[_P1, _P3] = nmat[_P3, _P1] = s[xy + 2]
    nmat[_P1, _P4] = nmat[_P4, _P1] = s[yy + 1]
    nmat[_P1, _P5] = nmat[_P5, _P1] = s[yy + 2]
    nmat[_P2, _P2] = s[xx + 3]
    nmat[_P2, _P3] = nmat[_P3, _P2] = s[xx + 4]
    nmat[_P2, _P4] = nmat[_P4, _P2] = s[xy + 3]
    nmat[_P2, _P5] = nmat[_P5, _P2] = s[xy + 4]
    nmat[_P3, _P3] = s[xx + 5]
    nmat[_P3, _P4] = nmat[_P4, _P3] = s[xy + 4]
    nmat[_P3, _P5] = nmat[_P5, _P3] = s[xy + 5]
    nmat[_P4, _P4] = s[yy + 3]
    nmat[_P4, _P5] = nmat[_P5, _P4] = s[yy + 4]
    nmat[_P5, _P5] = s[yy + 5]
    # geometry x alpha: sum g m y_p = sum g m y + dx sum g gx m + dy sum g gy m  (m = 1, u, v)
    nmat[_P0, _P6] = nmat[_P6, _P0] = s[xi + 0] + dx * s[xx + 0] + dy * s[xy + 0]
    nmat[_P2, _P6] = nmat[_P6, _P2] = s[xi + 1] + dx * s[xx + 1] + dy * s[xy + 1]
    nmat[_P3, _P6] = nmat[_P6, _P3] = s[xi + 2] + dx * s[xx + 2] + dy * s[xy + 2]
    nmat[_P1, _P6] = nmat[_P6, _P1] = s[yi + 0] + dx * s[xy + 0] + dy * s[yy + 0]
    nmat[_P4, _P6] = nmat[_P6, _P4] = s[yi + 1] + dx * s[xy + 1] + dy * s[yy + 1]
    nmat[_P5, _P6] = nmat[_P6, _P5] = s[yi + 2] + dx * s[xy + 2] + dy * s[yy + 2]
    # geometry x beta: sum g m
    nmat[_P0, _P7] = nmat[_P7, _P0] = s[gx + 0]
    nmat[_P2, _P7] = nmat[_P7, _P2] = s[gx + 1]
    nmat[_P3, _P7] = nmat[_P7, _P3] = s[gx + 2]
    nmat[_P1, _P7] = nmat[_P7, _P1] = s[gy + 0]
    nmat[_P4, _P7] = nmat[_P7, _P4] = s[gy + 1]
    nmat[_P5, _P7] = nmat[_P7, _P5] = s[gy + 2]
    # radiometry
    syg = dx * s[xi + 0] + dy * s[yi + 0]
    gg = dx * dx * s[xx + 0] + 2.0 * dx * dy * s[xy + 0] + dy * dy * s[yy + 0]
    nmat[_P6, _P6] = s[sc + 4] + 2.0 * syg + gg
    nmat[_P6, _P7] = nmat[_P7, _P6] = s[sc + 3] + dx * s[gx + 0] + dy * s[gy + 0]
    nmat[_P7, _P7] = s[sc + 5]
    # right-hand side: sum column * T
    rhs[_P0] = s[xt + 0]
    rhs[_P2] = s[xt + 1]
    rhs[_P3] = s[xt + 2]
    rhs[_P1] = s[yt + 0]
    rhs[_P4] = s[yt + 1]
    rhs[_P5] = s[yt + 2]
    rhs[_P6] = s[sc + 2] + dx * s[xt + 0] + dy * s[yt + 0]
    rhs[_P7] = s[sc + 1]


_NSUMS = 36 + _NSCALARS
# vertical moments (powers of v) kept per horizontal plane: quadratic channels' a = 0 planes
# need v^0..v^2, their a = 1 planes and the linear channels' a = 0 planes v^0..v^1
_VPOW = np.array([3, 2, 1] * 3 + [2, 1] * 6 + [1] * _NSCALARS + [3, 2, 1] * 3 + [2, 1] * 4, dtype=np.int64)


@numba.njit(nogil=True, cache=True)
def _add_row(vsum, row, sign, rho, ncols, nplanes):  # pragma: no cover - compiled
    """Add (``sign`` = 1) or remove (-1) one row of horizontal sums, at relative row ``rho``."""
    w1 = sign * rho
    w2 = w1 * rho
    for k in range(nplanes):
        npow = _VPOW[k]
        for j in range(ncols):
            h = row[k, j]
            vsum[0, k, j] += sign * h
        if npow > 1:
            for j in range(ncols):
                vsum[1, k, j] += w1 * row[k, j]
        if npow > 2:
            for j in range(ncols):
                vsum[2, k, j] += w2 * row[k, j]


@numba.njit(nogil=True, cache=True)
def _centred_sums(vsum, rc, j, s):  # pragma: no cover - compiled
    """Window sums at column ``j`` about the centre row ``rc`` (relative) from the running sums."""
    for c in range(3):
        q = 3 * c  # _XX, _XY, _YY planes are 0, 3, 6
        o = 6 * c
        a0 = vsum[0, q, j]
        a1 = vsum[1, q, j]
        s[o + 0] = a0
        s[o + 1] = vsum[0, q + 1, j]
        s[o + 2] = a1 - rc * a0
        s[o + 3] = vsum[0, q + 2, j]
        s[o + 4] = vsum[1, q + 1, j] - rc * vsum[0, q + 1, j]
        s[o + 5] = vsum[2, q, j] - 2.0 * rc * a1 + rc * rc * a0
    for c in range(6):
        q = _XT + 2 * c
        o = 18 + 3 * c
        a0 = vsum[0, q, j]
        s[o + 0] = a0
        s[o + 1] = vsum[0, q + 1, j]
        s[o + 2] = vsum[1, q, j] - rc * a0
    for c in range(_NSCALARS):
        s[36 + c] = vsum[0, _TT + c, j]


@numba.njit(nogil=True, cache=True)
def _precision_sums(vsum, rc, j, s):  # pragma: no cover - compiled
    """The sums of :func:`_centred_sums` that the normal matrix needs, from the smooth gradients.

    The gain's column is the sampled image itself (``y_p`` at convergence), so the
    right-hand side's sums are left at zero.
    """
    for k in range(_NSUMS):
        s[k] = 0.0
    for c in range(3):
        q = _CXX + 3 * c
        o = 6 * c
        a0 = vsum[0, q, j]
        a1 = vsum[1, q, j]
        s[o + 0] = a0
        s[o + 1] = vsum[0, q + 1, j]
        s[o + 2] = a1 - rc * a0
        s[o + 3] = vsum[0, q + 2, j]
        s[o + 4] = vsum[1, q + 1, j] - rc * vsum[0, q + 1, j]
        s[o + 5] = vsum[2, q, j] - 2.0 * rc * a1 + rc * rc * a0
    for c, o in ((_CX, 24), (_CY, 27), (_CXR, 30), (_CYR, 33)):
        a0 = vsum[0, c, j]
        s[o + 0] = a0
        s[o + 1] = vsum[0, c + 1, j]
        s[o + 2] = vsum[1, c, j] - rc * a0
    s[36 + 3] = vsum[0, _R, j]
    s[36 + 4] = vsum[0, _RR, j]
    s[36 + 5] = vsum[0, _W, j]


@numba.njit(nogil=True, cache=True)
def _solve_window(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, region, rx, ry, min_count, final, template,
                  sol, stats):  # pragma: no cover - compiled
    """Solve the normal equations of every template centred in ``region``.

    ``sol`` (8, h, w) gets ``(dx, dy, b11, b12, b21, b22, gain, offset)``: the move of the
    position, the affine correction (both divided by the gain) and the radiometry in the
    normalised grey values; ``stats`` (5, h, w) gets ``sigma_x, sigma_y, cov_xy, rho, code``
    (code: 0 solved, OUTSIDE, SINGULAR). Only the move and the radiometry, and no
    statistics, unless ``final``.
    """
    h, w = t.shape
    r0, r1, c0, c1 = region
    a0 = max(c0 - rx, 0)
    a1 = min(c1 + rx, w)
    ncols = a1 - a0
    nring = 2 * ry + 1
    nplanes = _NPLANES if final and not template else _NPLANES_SOLVE
    ring = np.zeros((nring, nplanes, ncols))
    vsum = np.zeros((3, nplanes, ncols))
    pre = np.empty((nplanes, ncols + 1))
    s = np.empty(_NSUMS)
    s2 = np.empty(_NSUMS)
    rhs2 = np.empty(8)
    nmat = np.empty((8, 8))
    e = np.empty(8)
    rhs = np.empty(8)
    p = np.empty(8)
    npix = float((2 * rx + 1) * (2 * ry + 1))
    base_row = r0 - ry
    for r in range(r0 - ry, r1 + ry):
        slot = (r - base_row) % nring
        if r - base_row >= nring:  # the row leaving the window
            _add_row(vsum, ring[slot], -1.0, float(r - nring - base_row), ncols, nplanes)
        if 0 <= r < h:
            _row_planes(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, r, a0, a1, rx, nplanes, not template, pre,
                        ring[slot])
        else:
            ring[slot, :, :] = 0.0
        _add_row(vsum, ring[slot], 1.0, float(r - base_row), ncols, nplanes)
        rc = r - ry  # the row whose window is now complete
        if rc < r0:
            continue
        rrel = float(rc - base_row)
        for c in range(c0, c1):
            j = c - a0
            stats[4, rc, c] = _OUTSIDE
            if rc - ry < 0 or rc + ry >= h or j - rx < 0 or j + rx >= ncols:
                continue
            if not weight[rc, c]:
                continue
            _centred_sums(vsum, rrel, j, s)
            cnt = s[41]
            if cnt < min_count * npix or cnt <= 8.0:
                continue
            if template:
                _assemble(s, 0.0, 0.0, nmat, rhs)
            else:
                _assemble(s, px[rc, c] - c - qx, py[rc, c] - rc - qy, nmat, rhs)
            ok, d6, d7, lxy = _ldl_solve8(nmat, rhs, p, final)
            if not ok:
                stats[4, rc, c] = _SINGULAR
                continue
            alpha = p[_P6]
            if not (alpha > 0.0):
                stats[4, rc, c] = _SINGULAR
                continue
            # the geometric unknowns: the template's move (template gradients) or alpha times the image's
            scale = 1.0 if template else alpha
            sol[0, rc, c] = p[_P0] / scale
            sol[1, rc, c] = p[_P1] / scale
            sol[6, rc, c] = alpha
            sol[7, rc, c] = p[_P7]
            stats[4, rc, c] = _ACCEPTED
            if not final:
                continue
            sol[2, rc, c] = p[_P2] / scale
            sol[3, rc, c] = p[_P3] / scale
            sol[4, rc, c] = p[_P4] / scale
            sol[5, rc, c] = p[_P5] / scale
            ssr = s[36]
            for k in range(8):
                ssr -= p[k] * rhs[k]
            s02 = max(ssr, 0.0) / (cnt - 8.0) / (scale * scale)
            if template:
                # the template's smooth gradients are the design: the shift block of its own inverse
                stats[0, rc, c] = math.sqrt(max(s02 * (1.0 / d6 + lxy * lxy / d7), 0.0))
                stats[1, rc, c] = math.sqrt(max(s02 / d7, 0.0))
                stats[2, rc, c] = -s02 * lxy / d7
                st, stt, sti, si, sii = s[37], s[36], s[42], s[43], s[44]
                vt = stt - st * st / cnt
                vi = sii - si * si / cnt
                stats[3, rc, c] = (sti - st * si / cnt) / math.sqrt(vt * vi) if vt > 0.0 and vi > 0.0 else np.nan
                continue
            # the precision from the normal matrix of the smooth gradients, as in ALSC: the
            # slopes of the interpolant carry twice the noise and would make sigma optimistic
            _precision_sums(vsum, rrel, j, s2)
            _assemble(s2, 0.0, 0.0, nmat, rhs2)
            ok, d6, d7, lxy = _ldl_solve8(nmat, rhs2, e, False)
            if not ok:
                stats[4, rc, c] = _SINGULAR
                continue
            # shift block of N^-1 = (L22 D2 L22^T)^-1 for the last 2x2 blocks of the factor
            cxx = s02 * (1.0 / d6 + lxy * lxy / d7)
            cxy = -s02 * lxy / d7
            cyy = s02 / d7
            stats[0, rc, c] = math.sqrt(max(cxx, 0.0))
            stats[1, rc, c] = math.sqrt(max(cyy, 0.0))
            stats[2, rc, c] = cxy
            st, stt, sti, si, sii = s[37], s[36], s[42], s[43], s[44]
            vt = stt - st * st / cnt
            vi = sii - si * si / cnt
            stats[3, rc, c] = (sti - st * si / cnt) / math.sqrt(vt * vi) if vt > 0.0 and vi > 0.0 else np.nan


@dataclass(frozen=True)
class FieldLsqResult:
    """Per-pixel result of :func:`field_lsq` on the window grid.

    Attributes
    ----------
    x, y : float64 (h, w)
        Final positions in the distorted window's frame (the start where never updated).
    affine : float64 (4, h, w)
        ``b11, b12, b21, b22``, the Jacobian of the position minus the identity, of the last evaluation.
    gain, offset : float64 (h, w)
        Radiometry of the last evaluation, ``base ~ gain dist + offset`` as in ALSC.
    sigma_x, sigma_y, rho : float64 (h, w)
    step : float64 (h, w)
        Length of the last ``(x, y)`` update.
    code : int8 (h, w)
        :class:`~geocoder.kernels.alsc.Exit` code, -1 where not tried.
    """

    x: np.ndarray
    y: np.ndarray
    affine: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    rho: np.ndarray
    step: np.ndarray
    code: np.ndarray


@numba.njit(nogil=True, cache=True)
def _accept(sol, stats, px, py, x0, y0, step, eligible, region, tol, max_shift, min_rho, max_sigma, min_det,
            code):  # pragma: no cover - compiled
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            if not eligible[r, c]:
                code[r, c] = _NOT_TRIED
                continue
            k = int(stats[4, r, c])
            if k != _ACCEPTED:
                code[r, c] = k
                continue
            if not (step[r, c] < tol):
                code[r, c] = _NOT_CONVERGED
                continue
            dx = px[r, c] - x0[r, c]
            dy = py[r, c] - y0[r, c]
            if dx * dx + dy * dy > max_shift * max_shift:
                code[r, c] = _MOVED
                continue
            det = (1.0 + sol[2, r, c]) * (1.0 + sol[5, r, c]) - sol[3, r, c] * sol[4, r, c]  # I + Jacobian of q
            if not (det >= min_det and det * min_det <= 1.0):
                code[r, c] = _DEGENERATE
                continue
            if not (stats[3, r, c] >= min_rho):
                code[r, c] = _LOW_CORRELATION
                continue
            sx = stats[0, r, c]
            sy = stats[1, r, c]
            cxy = stats[2, r, c]
            half = 0.5 * (sx * sx - sy * sy)
            largest = 0.5 * (sx * sx + sy * sy) + math.sqrt(half * half + cxy * cxy)
            if not (largest <= max_sigma * max_sigma):
                code[r, c] = _IMPRECISE
                continue
            code[r, c] = _ACCEPTED


@numba.njit(nogil=True, cache=True)
def _update(sol, stats, px, py, step, region):  # pragma: no cover - compiled
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            if stats[4, r, c] == _ACCEPTED:
                tx = sol[0, r, c]
                ty = sol[1, r, c]
                px[r, c] += tx
                py[r, c] += ty
                step[r, c] = math.sqrt(tx * tx + ty * ty)
            else:
                step[r, c] = np.inf


def field_lsq(
    base: np.ndarray,
    dist: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    eligible: np.ndarray,
    region: tuple[int, int, int, int],
    *,
    radius: int = 25,
    radius_y: int = 3,
    iterations: int = 3,
    tol: float = 0.1,
    max_shift: float = 0.5,
    min_rho: float = 0.7,
    max_sigma: float = 0.1,
    min_det: float = 0.5,
    min_fill: float = 0.5,
    gradients: str = "template",
) -> FieldLsqResult:
    """Least-squares match of every eligible pixel of ``region``, starting from ``(x0, y0)``.

    Parameters
    ----------
    base : 2-D float array (h, w)
        Base window; templates are cut from it.
    dist : 2-D float array
        Distorted window.
    x0, y0 : float (h, w)
        Start positions in the distorted window's frame for every pixel of the base window
        (needed wherever a template of a pixel of ``region`` may reach after ``iterations``
        rounds, i.e. ``region`` grown by ``iterations`` template half-sizes).
    eligible : bool (h, w)
        Pixels whose start is trusted: only they take part in templates and are matched.
    region : (row0, row1, col0, col1)
        The pixels whose result is wanted (half open).
    radius, radius_y : int
        Template half-width (columns) and half-height (rows).
    iterations : int
        Resampling rounds; each moves every solved pixel of a region that shrinks by one
        template half-size per round, so the result inside ``region`` depends only on data
        within ``iterations`` half-sizes of it.
    tol : float
        Largest length (px) of the last move of an accepted pixel.
    max_shift, min_rho, max_sigma, min_det : float
        Acceptance tests as in :class:`geocoder.kernels.alsc.AlscOptions` (``max_shift``
        measured from the start, ``min_det`` on ``det(I + c / alpha)``, the affine correction).
    min_fill : float
        Smallest share of a template's pixels that must be eligible (with finite samples);
        the others are left out of its sums.
    gradients : {"template", "image"}
        The design's slopes. ``"template"``: the base template's central differences (the
        inverse-compositional form: free of the resampled image's noise, which biases the
        image's slopes on smooth texture); each round samples the image on the field
        smoothed over the template's box and moves a pixel to that mean plus its template's
        shift, so a round reaches two half-sizes, and sigma carries the fixed point's noise
        gain (:func:`_noise_gain`). ``"image"``: the slopes of the distorted image's
        interpolant at every template pixel's own position, each template linearised about
        its centre (one half-size per round).

    Returns
    -------
    FieldLsqResult
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    if gradients not in ("image", "template"):
        raise ValueError(f"gradients must be 'image' or 'template', got {gradients!r}")
    template = gradients == "template"
    h, w = base.shape
    t = np.asarray(base, dtype=np.float64)
    # grey values of O(1) keep the window sums well conditioned (gain and offset absorb the scale)
    tm, ts = _location_scale(t)
    t = (t - tm) / ts
    d = np.asarray(dist, dtype=np.float64)
    dm, ds = _location_scale(d)
    d = (d - dm) / ds
    px = np.array(x0, dtype=np.float64)
    py = np.array(y0, dtype=np.float64)
    weight = np.asarray(eligible, dtype=np.bool_) & np.isfinite(px) & np.isfinite(py)
    cols = np.arange(w)[None, :]
    rows = np.arange(h)[:, None]
    qx = float(np.median((px - cols)[weight])) if weight.any() else 0.0
    qy = float(np.median((py - rows)[weight])) if weight.any() else 0.0
    iw = np.full((h, w), np.nan)
    gxw = np.full((h, w), np.nan)
    gyw = np.full((h, w), np.nan)
    sol = np.full((8, h, w), np.nan)
    stats = np.full((5, h, w), np.nan)
    step = np.full((h, w), np.inf)
    r0, r1, c0, c1 = region
    if template:
        _template_rounds(t, d, px, py, weight, region, radius, radius_y, iterations, min_fill, iw, gxw, gyw, sol, stats,
                         step)
        stats[0:2] *= _noise_gain(radius, radius_y)
        stats[2] *= _noise_gain(radius, radius_y) ** 2
    else:
        cgy, cgx = np.gradient(d)  # the smooth gradients of the precision (NaN spreads to neighbours)
        cxw = np.full((h, w), np.nan)
        cyw = np.full((h, w), np.nan)
    for it in range(0 if template else iterations):
        grow = iterations - 1 - it
        reg = np.array([max(r0 - grow * radius_y, 0), min(r1 + grow * radius_y, h),
                        max(c0 - grow * radius, 0), min(c1 + grow * radius, w)], dtype=np.int64)
        warp = np.array([max(reg[0] - radius_y, 0), min(reg[1] + radius_y, h),
                         max(reg[2] - radius, 0), min(reg[3] + radius, w)], dtype=np.int64)
        final = it == iterations - 1
        _warp(d, px, py, warp, iw, gxw, gyw)
        if final:
            _sample(cgx, px, py, warp, cxw)
            _sample(cgy, px, py, warp, cyw)
        _solve_window(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, reg, radius, radius_y, min_fill, final,
                      False, sol, stats)
        _update(sol, stats, px, py, step, reg)
    code = np.full((h, w), _NOT_TRIED, dtype=np.int8)
    x0f = np.asarray(x0, dtype=np.float64)
    y0f = np.asarray(y0, dtype=np.float64)
    _accept(sol, stats, px, py, x0f, y0f, step, weight, np.array(region, dtype=np.int64), tol, max_shift, min_rho,
            max_sigma, min_det, code)
    sl = (slice(r0, r1), slice(c0, c1))
    gain = sol[6][sl] * ts / ds  # base ~ gain dist + offset, as in ALSC
    offset = tm + ts * sol[7][sl] - gain * dm
    return FieldLsqResult(
        px[sl], py[sl], sol[2:6, r0:r1, c0:c1], gain, offset, stats[0][sl], stats[1][sl], stats[3][sl], step[sl],
        code[sl],
    )


def _box_count(weight: np.ndarray, rx: int, ry: int) -> np.ndarray:
    """Share of the template's box around every pixel that is ``weight`` (the denominator of :func:`_box_mean`)."""
    return uniform_filter(weight.astype(np.float64), size=(2 * ry + 1, 2 * rx + 1), mode="constant")


def _box_mean(q: np.ndarray, weight: np.ndarray, den: np.ndarray, rx: int, ry: int) -> np.ndarray:
    """Mean of ``q`` over the ``weight`` pixels of the template's box around every pixel (NaN where none);
    ``den`` is :func:`_box_count` of ``weight``."""
    size = (2 * ry + 1, 2 * rx + 1)
    num = uniform_filter(np.where(weight, q, 0.0), size=size, mode="constant")
    # uniform_filter's running sums leave rounding of ~1e-16 where the box holds no weight
    return np.where(den > 0.5 / (size[0] * size[1]), num / np.maximum(den, 1e-300), np.nan)


def _template_rounds(t, d, px, py, weight, region, rx, ry, iterations, min_fill, iw, gxw, gyw, sol, stats, step):
    """The rounds of ``gradients="template"``: smooth the field over the template's box,
    resample the image there, and move every pixel to the smoothed field plus its template's shift.

    The smoothing is what keeps the templates independent of their neighbours' noise: the
    samples follow the box mean of the field (whose noise is that of many matches), and the
    new position of a pixel is that mean plus ITS template's own shift, so no pixel's noise
    is carried into the next round except through the mean. Round ``k`` of ``n`` solves the
    pixels within ``2 (n - 1 - k)`` half-sizes of ``region`` (the box, then the template).
    """
    h, w = t.shape
    r0, r1, c0, c1 = region
    tgy, tgx = np.gradient(t)
    cols = np.arange(w)[None, :]
    rows = np.arange(h)[:, None]
    den = _box_count(weight, rx, ry)  # the eligible pixels do not change between rounds
    for it in range(iterations):
        grow = 2 * (iterations - 1 - it)
        reg = np.array([max(r0 - grow * ry, 0), min(r1 + grow * ry, h),
                        max(c0 - grow * rx, 0), min(c1 + grow * rx, w)], dtype=np.int64)
        warp = np.array([max(reg[0] - ry, 0), min(reg[1] + ry, h), max(reg[2] - rx, 0), min(reg[3] + rx, w)],
                        dtype=np.int64)
        sx = cols + _box_mean(px - cols, weight, den, rx, ry)
        sy = rows + _box_mean(py - rows, weight, den, rx, ry)
        _warp(d, sx, sy, warp, iw, gxw, gyw)
        _solve_window(t, iw, tgx, tgy, iw, iw, sx, sy, 0.0, 0.0, weight, reg, rx, ry, min_fill, it == iterations - 1,
                      True, sol, stats)
        _move(sol, stats, sx, sy, px, py, step, reg)


@numba.njit(nogil=True, cache=True)
def _move(sol, stats, sx, sy, px, py, step, region):  # pragma: no cover - compiled
    """A solved pixel goes to the smoothed field plus its template's shift; ``step`` is how far it moved."""
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            if stats[4, r, c] == _ACCEPTED:
                nx = sx[r, c] + sol[0, r, c]
                ny = sy[r, c] + sol[1, r, c]
                ex = nx - px[r, c]
                ey = ny - py[r, c]
                px[r, c] = nx
                py[r, c] = ny
                step[r, c] = math.sqrt(ex * ex + ey * ey)
            else:
                step[r, c] = np.inf


_GAINS: dict[tuple[int, int], float] = {}


def _noise_gain(rx: int, ry: int) -> float:
    """Standard-deviation gain of the template rounds' fixed point over one template's noise.

    At the fixed point ``q = B q + B (t - B q)`` (``B`` the template's box mean) noise that
    enters as the box-smoothed noise of single matches leaves with the transfer
    ``1 / (1 - B + B^2)`` (at most 4/3); the gain is the ratio of the two spectra's powers,
    from the box's transfer function on a 512 x 512 grid.
    """
    key = (int(rx), int(ry))
    if key not in _GAINS:
        def box(n: int, size: int = 512) -> np.ndarray:
            k = np.zeros(size)
            k[:n] = 1.0 / n
            return np.real(np.fft.fft(np.roll(k, -(n // 2))))

        b = box(2 * key[1] + 1)[:, None] * box(2 * key[0] + 1)[None, :]
        p = b * b
        _GAINS[key] = float(np.sqrt((p / (1.0 - b + b * b) ** 2).sum() / p.sum()))
    return _GAINS[key]


def _location_scale(a: np.ndarray) -> tuple[float, float]:
    v = a[np.isfinite(a)]
    if v.size == 0:
        return 0.0, 1.0
    m = float(v.mean())
    s = float(v.std())
    return m, (s if s > 0 else 1.0)


def template_solution_reference(t, iw, gxw, gyw, px, py, row: int, col: int, radius: int, radius_y: int):
    """The least-squares solution of one template from its design matrix (numpy; for tests).

    Same model and inputs as the kernel (normalised grey values, warped image and slopes);
    returns ``(dx, dy, b11, b12, b21, b22, gain, offset)`` as the kernel's ``sol``.
    """
    sl = (slice(row - radius_y, row + radius_y + 1), slice(col - radius, col + radius + 1))
    v, u = np.mgrid[-radius_y : radius_y + 1, -radius : radius + 1]
    r, c = np.mgrid[sl]
    gx, gy, tt, i, x, y = (np.asarray(a, dtype=np.float64)[sl].ravel() for a in (gxw, gyw, t, iw, px, py))
    qx = x - c.ravel() - (px[row, col] - col)
    qy = y - r.ravel() - (py[row, col] - row)
    yp = i - gx * qx - gy * qy
    u, v = u.ravel().astype(float), v.ravel().astype(float)
    a = np.column_stack([gx, gy, u * gx, v * gx, u * gy, v * gy, yp, np.ones_like(tt)])
    theta = np.linalg.lstsq(a, tt, rcond=None)[0]
    alpha = theta[6]
    return np.r_[theta[:6] / alpha, alpha, theta[7]]
