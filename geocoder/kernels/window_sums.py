"""Window sums of :func:`geocoder.kernels.fieldlsq.field_lsq`: the resampled planes, their sliding sums, the normal equations.

Every template's normal equations are sums over its window of products of per-pixel images
(the resampled image ``i``, its slopes, the template ``t``, their products with the powers
of the column offset ``u``). A row's products go into horizontal prefix sums, one plane per
channel and power of ``u`` (the ``_XX`` ... ``_CY`` planes); a ring buffer of ``2 ry + 1``
such rows gives, per column, the vertical sums with powers of the row offset ``v``
(:func:`_add_row`); :func:`_centred_sums` turns those into the window sums about a
template's centre, laid out as ``S_*`` say; :func:`_assemble` makes the 8x8 normal equations
of one template from them and :func:`_ldl_solve8` solves them (the shift last, so that its
covariance block comes from the last rows of the factor alone).

The sampling of the distorted image at the field (:func:`_warp`, :func:`_sample`,
:func:`_sample_lanczos`) is here too: it makes the images the planes are built from.
"""

from __future__ import annotations

import numba
import numpy as np

from .resample import lanczos_weights

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


@numba.njit(nogil=True, cache=True)
def _sample_lanczos(image, px, py, region, table, out):  # pragma: no cover - compiled
    """Lanczos-3 samples of ``image`` at ``(px, py)`` inside ``region``.

    NaN where a tap (``floor - 2 .. floor + 3`` on either axis) is outside the image or NaN.
    Bilinear samples average the image's noise over their taps (by a factor that changes with
    the fraction of the position) and cut its fine detail; this kernel keeps both, so that a
    template's residuals tell its noise and its shift follows the detail.
    """
    hd, wd = image.shape
    r0, r1, c0, c1 = region
    wx = np.empty(6)
    wy = np.empty(6)
    for r in range(r0, r1):
        for c in range(c0, c1):
            x = px[r, c]
            y = py[r, c]
            if not (x >= 2.0 and x < wd - 3 and y >= 2.0 and y < hd - 3):
                out[r, c] = np.nan
                continue
            ix = int(x)
            iy = int(y)
            lanczos_weights(x - ix, table, wx)
            lanczos_weights(y - iy, table, wy)
            acc = 0.0
            for j in range(6):
                row = 0.0
                for i in range(6):
                    row += wx[i] * image[iy - 2 + j, ix - 2 + i]
                acc += wy[j] * row
            out[r, c] = acc


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

# Positions in the window sums ``s`` (float64[_NSUMS]) of :func:`_centred_sums`:
#   [0, 18)  quadratic channels gx gx, gx gy, gy gy, each with 1, u, v, u u, u v, v v
#   [18, 36) linear channels gx t, gy t, gx, gy, gx i, gy i, each with 1, u, v
#   [36, 45) scalars, in the order of the scalar planes from _TT:
S_TT, S_T, S_TI, S_I, S_II, S_W, S_TR, S_R, S_RR = range(36, 45)
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
        s[S_TT + c] = vsum[0, _TT + c, j]


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
    s[S_I] = vsum[0, _R, j]
    s[S_II] = vsum[0, _RR, j]
    s[S_W] = vsum[0, _W, j]
