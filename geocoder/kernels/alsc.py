"""Adaptive least-squares correlation (ALSC) of a template against a distorted window.

A base template of ``(2 radius + 1)^2`` pixels centred on the integer base pixel
``(col, row)`` is matched against the distorted window under an affine geometry and a
linear radiometry (Gruen 1985; Otto & Chau 1989)::

    base(col + u, row + v) ~ gain * dist(x + a11 u + a12 v, y + a21 u + a22 v) + offset

for the template offsets ``u, v in [-radius, radius]``.  The eight parameters, in the order
``(x, y, a11, a12, a21, a22, offset, gain)``, are estimated by Gauss-Newton: every iteration
samples ``dist`` and its gradients ``gx, gy`` (central differences of the window, see
:func:`gradients`) bilinearly at the current positions, forms the 8x8 normal equations
with the design rows ::

    d/dx   = gain gx      d/da11 = gain gx u      d/da12 = gain gx v
    d/dy   = gain gy      d/da21 = gain gy u      d/da22 = gain gy v
    d/doffset = 1         d/dgain = dist

and adds the solution ``s_k`` to the parameters, relaxed as ``omega_k s_k`` (see below).  The
iteration has converged when the Gauss-Newton step of ``(x, y)`` is shorter than ``tol``; the
statistics are those of the normal equations, residuals ``e`` and resampled patch of the
evaluation that gave this last step (at parameters less than ``tol`` from the final ones; no
extra evaluation, which saved a fifth of the work): ``sigma0^2 = e.e / (n - 8)``, the covariance
``C = sigma0^2 N^-1`` (the shift block of the full inverse, not the inverse of the shift
block), ``sigma_x, sigma_y`` from its diagonal, and ``rho``, the correlation coefficient of
the template and the resampled distorted patch.

The design rows use the interpolated central-difference gradients, not the derivative of the
bilinear interpolant, so Gauss-Newton converges only linearly, at a rate that approaches -1
(the steps overshoot and alternate) on texture near the Nyquist frequency.  The update is
therefore relaxed by a secant (Aitken) estimate of that rate along the ``(x, y)`` step:
``q_k = s_k . s_{k-1} / |s_{k-1}|^2`` (the ``(x, y)`` parts of the raw steps) gives
``omega_k = clip(omega_{k-1} / (1 - q_k), 0.2, 1)`` (``omega_0 = 1``; ``omega_k = 1`` when
``q_k >= 1``).  Steps that keep their direction are taken in full; the relaxation changes the
path, not the fixed point, so the result does not depend on it (nor on the start within the
basin of convergence).

Coordinates follow ``CONVENTIONS.md``: ``x`` = column, ``y`` = row, pixel centres at integers,
NaN = nodata.  Bilinear sampling needs its 2x2 taps inside the window, i.e.
``0 <= x < width - 1`` and ``0 <= y < height - 1``; a sample that leaves the window or touches
a non-finite value (of ``dist`` or of its gradients), or a template that leaves ``base`` or
holds a non-finite value, ends the match with :attr:`Exit.OUTSIDE`.

Exit codes are decided in the order of :class:`Exit`: ``OUTSIDE`` (at any iteration),
``SINGULAR`` (the normal matrix is not numerically positive definite or not finite, at any
iteration or at the last evaluation), ``NOT_CONVERGED``, ``MOVED`` (the final ``(x, y)`` is
farther than ``max_shift`` from the start), ``DEGENERATE`` (``det([[a11, a12], [a21, a22]])``
divided by the determinant of the start affine is outside ``[min_det, 1 / min_det]``, or
``gain <= 0``), ``LOW_CORRELATION`` (``rho < min_rho``) and ``IMPRECISE`` (the largest
eigenvalue of the 2x2 shift covariance exceeds ``max_sigma^2``).

:func:`alsc_point` is the numba kernel for one point; it may be called from other numba
functions (it allocates only a few small work arrays per call).  Per evaluation it
accumulates the moments of the normal equations (sums of gradient products times
``1, u, v, u^2, u v, v^2``) row by row instead of building the design matrix.  :func:`alsc` runs it over
many points; :mod:`geocoder.kernels.alsc_reference` holds a vectorised numpy implementation of
the same algorithm for the tests.

The module is over 500 lines because its numba kernels are one algorithm: the moment loops
(bilinear and cubic, each written out branch-free so that LLVM vectorises it), the normal
equations, the factorisation and the two drivers share the moment vector's layout and the
exit codes as compile-time constants, and splitting them would only scatter that layout;
the public side (options, result, :func:`alsc`, :func:`gradients`, :func:`samples`) is the last
~200 lines.

References
----------
Gruen, A. W. (1985). Adaptive least squares correlation: a powerful image matching
technique. South African Journal of Photogrammetry, Remote Sensing and Cartography 14(3).

Otto, G. P. & Chau, T. K. W. (1989). 'Region-growing' algorithm for matching of terrain
images. Image and Vision Computing 7(2), 83-94.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numba
import numpy as np

__all__ = [
    "FIELDS",
    "F_A11",
    "F_A12",
    "F_A21",
    "F_A22",
    "F_GAIN",
    "F_ITERATIONS",
    "F_OFFSET",
    "F_RHO",
    "F_SIGMA_X",
    "F_SIGMA_Y",
    "F_X",
    "F_Y",
    "NFIELDS",
    "NPARAMS",
    "AlscOptions",
    "AlscResult",
    "Exit",
    "alsc",
    "alsc_point",
    "alsc_step",
    "gradients",
    "samples",
]

#: Fields of the ``out`` vector of :func:`alsc_point` (and of :class:`AlscResult`).
FIELDS = ("x", "y", "a11", "a12", "a21", "a22", "offset", "gain", "sigma_x", "sigma_y", "rho", "iterations")

NPARAMS = 8
NFIELDS = len(FIELDS)

# Positions in the ``out`` vector (and, for the first NPARAMS, in a parameter vector), as plain
# ints: numba freezes module-level ints as compile-time constants.
F_X = FIELDS.index("x")
F_Y = FIELDS.index("y")
F_A11 = FIELDS.index("a11")
F_A12 = FIELDS.index("a12")
F_A21 = FIELDS.index("a21")
F_A22 = FIELDS.index("a22")
F_OFFSET = FIELDS.index("offset")
F_GAIN = FIELDS.index("gain")
F_SIGMA_X = FIELDS.index("sigma_x")
F_SIGMA_Y = FIELDS.index("sigma_y")
F_RHO = FIELDS.index("rho")
F_ITERATIONS = FIELDS.index("iterations")


class Exit(IntEnum):
    """Exit codes of a match (checked in this order; 0 = accepted)."""

    ACCEPTED = 0
    OUTSIDE = 1
    SINGULAR = 2
    NOT_CONVERGED = 3
    MOVED = 4
    DEGENERATE = 5
    LOW_CORRELATION = 6
    IMPRECISE = 7


# Plain integer copies for the numba kernels (frozen as compile-time constants).
_ACCEPTED = int(Exit.ACCEPTED)
_OUTSIDE = int(Exit.OUTSIDE)
_SINGULAR = int(Exit.SINGULAR)
_NOT_CONVERGED = int(Exit.NOT_CONVERGED)
_MOVED = int(Exit.MOVED)
_DEGENERATE = int(Exit.DEGENERATE)
_LOW_CORRELATION = int(Exit.LOW_CORRELATION)
_IMPRECISE = int(Exit.IMPRECISE)

# Smallest relaxation factor of a Gauss-Newton step (see the module docstring).
_MIN_RELAX = 0.2

# Smallest pivot of the Cholesky factorisation of the normal matrix scaled to a unit
# diagonal: a pivot is 1 - R^2 of its column regressed on the earlier ones.
_MIN_PIVOT = 1e-12

# Layout of the moment vector accumulated by ``_moments`` (float64[_NMOM]).
#   [0, 18)  sums of q * m for q in (gx gx, gx gy, gy gy), m in (1, u, v, uu, uv, vv): 6 q + m
#   [18, 36) sums of f * w for f in (gx, gy, g gx, g gy, e gx, e gy), w in (1, u, v): 18 + 3 f + w
#   36..41   sums of g, g g, e, e g, e e, (t - mean t) g
# (g = sampled dist, gx/gy = sampled gradients, e = t - gain g - offset, t = template).
_LIN = 18
_SG = 36
_SGG = 37
_SE = 38
_SEG = 39
_SEE = 40
_STG = 41
_NMOM = 42

# Geometric parameter i (x, y, a11, a12, a21, a22): its gradient axis (0 = gx, 1 = gy) and
# weight (0 = 1, 1 = u, 2 = v); the moment index of the weight product w_i w_j.
_AXIS = (0, 1, 0, 0, 1, 1)
_WEIGHT = (0, 0, 1, 2, 1, 2)
_PAIR = ((0, 1, 2), (1, 3, 4), (2, 4, 5))


# --------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------


# Bilinear moments in two passes per template row: the samples (bilinear value and gradients,
# residual, template) into a small row buffer, then the sums over the buffer in three short
# loops. Split so, the sampling loop's gathers and the sums' accumulators no longer compete
# for registers (~20 % faster than one fused loop, bit for bit the same sums). Each tap is one
# 16-byte record (value, gx, gy, 0) of the table made by ``samples``: one load where three
# arrays needed three (~18 % per evaluation, the same sums). The bounds and finiteness tests
# are folded into flags checked once per row, indices are clamped so every load stays inside
# the window; only ``contract`` and ``reassoc`` fast-math flags, so NaN and infinity keep their
# IEEE meaning. The summation order is fixed at compile time: results are deterministic and do
# not depend on the tile.
@numba.njit(nogil=True, cache=True, fastmath={"contract", "reassoc"})
def _moments_bilinear(base, dist, col, row, p, rx, ry, tmean, mom):  # pragma: no cover - compiled
    """Bilinear case of :func:`_moments` (same contract)."""
    height, width = dist.shape[0], dist.shape[1]
    xmax = width - 1.0
    ymax = height - 1.0
    cmax = width - 2
    rmax = height - 2
    x, y = p[0], p[1]
    a11, a12, a21, a22 = p[2], p[3], p[4], p[5]
    offset, gain = p[6], p[7]
    n = 2 * rx + 1
    buf = np.empty((6, n))
    us, gs, gxs, gys, es, ts = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5]
    for i in range(n):
        us[i] = float(i - rx)
    for k in range(_NMOM):
        mom[k] = 0.0
    for v in range(-ry, ry + 1):
        fv = float(v)
        x0 = x + a12 * fv
        y0 = y + a22 * fv
        chk = 0.0
        outside = 0
        tr = row + v
        for i in range(n):
            fu = us[i]
            px = x0 + a11 * fu
            py = y0 + a21 * fu
            # False for NaN as well, so non-finite positions are rejected
            inside = px >= 0.0 and px < xmax and py >= 0.0 and py < ymax
            outside += 0 if inside else 1
            c = min(max(int(px) if inside else 0, 0), cmax)
            r = min(max(int(py) if inside else 0, 0), rmax)
            fx = px - c
            fy = py - r
            w00 = (1.0 - fx) * (1.0 - fy)
            w01 = fx * (1.0 - fy)
            w10 = (1.0 - fx) * fy
            w11 = fx * fy
            s00 = dist[r, c]
            s01 = dist[r, c + 1]
            s10 = dist[r + 1, c]
            s11 = dist[r + 1, c + 1]
            g = w00 * s00[0] + w01 * s01[0] + w10 * s10[0] + w11 * s11[0]
            gx = w00 * s00[1] + w01 * s01[1] + w10 * s10[1] + w11 * s11[1]
            gy = w00 * s00[2] + w01 * s01[2] + w10 * s10[2] + w11 * s11[2]
            chk += g + gx + gy
            t = float(base[tr, col - rx + i])
            gs[i] = g
            gxs[i] = gx
            gys[i] = gy
            es[i] = t - gain * g - offset
            ts[i] = t - tmean
        if outside != 0 or not (chk - chk == 0.0):  # a tap outside the window, or NaN/inf somewhere
            return False
        sxx0 = sxx1 = sxx2 = 0.0
        sxy0 = sxy1 = sxy2 = 0.0
        syy0 = syy1 = syy2 = 0.0
        for i in range(n):
            fu = us[i]
            gx = gxs[i]
            gy = gys[i]
            q = gx * gx
            sxx0 += q
            sxx1 += q * fu
            sxx2 += q * fu * fu
            q = gx * gy
            sxy0 += q
            sxy1 += q * fu
            sxy2 += q * fu * fu
            q = gy * gy
            syy0 += q
            syy1 += q * fu
            syy2 += q * fu * fu
        sx0 = sx1 = sy0 = sy1 = 0.0
        sgx0 = sgx1 = sgy0 = sgy1 = 0.0
        for i in range(n):
            fu = us[i]
            gx = gxs[i]
            gy = gys[i]
            g = gs[i]
            sx0 += gx
            sx1 += gx * fu
            sy0 += gy
            sy1 += gy * fu
            q = g * gx
            sgx0 += q
            sgx1 += q * fu
            q = g * gy
            sgy0 += q
            sgy1 += q * fu
        sex0 = sex1 = sey0 = sey1 = 0.0
        sg = sgg = se = seg = see = stg = 0.0
        for i in range(n):
            fu = us[i]
            e = es[i]
            g = gs[i]
            q = e * gxs[i]
            sex0 += q
            sex1 += q * fu
            q = e * gys[i]
            sey0 += q
            sey1 += q * fu
            sg += g
            sgg += g * g
            se += e
            seg += e * g
            see += e * e
            stg += ts[i] * g
        vv = fv * fv
        mom[0] += sxx0
        mom[1] += sxx1
        mom[2] += fv * sxx0
        mom[3] += sxx2
        mom[4] += fv * sxx1
        mom[5] += vv * sxx0
        mom[6] += sxy0
        mom[7] += sxy1
        mom[8] += fv * sxy0
        mom[9] += sxy2
        mom[10] += fv * sxy1
        mom[11] += vv * sxy0
        mom[12] += syy0
        mom[13] += syy1
        mom[14] += fv * syy0
        mom[15] += syy2
        mom[16] += fv * syy1
        mom[17] += vv * syy0
        mom[18] += sx0
        mom[19] += sx1
        mom[20] += fv * sx0
        mom[21] += sy0
        mom[22] += sy1
        mom[23] += fv * sy0
        mom[24] += sgx0
        mom[25] += sgx1
        mom[26] += fv * sgx0
        mom[27] += sgy0
        mom[28] += sgy1
        mom[29] += fv * sgy0
        mom[30] += sex0
        mom[31] += sex1
        mom[32] += fv * sex0
        mom[33] += sey0
        mom[34] += sey1
        mom[35] += fv * sey0
        mom[_SG] += sg
        mom[_SGG] += sgg
        mom[_SE] += se
        mom[_SEG] += seg
        mom[_SEE] += see
        mom[_STG] += stg
    return True


# The only hot loop: fusing its multiply-adds (``contract``; no other fast-math flag, so NaN
# and infinity keep their IEEE meaning) makes it ~20 % faster.
@numba.njit(nogil=True, cache=True, fastmath={"contract"})
def _moments(base, dist, col, row, p, rx, ry, cubic, tmean, mom):  # pragma: no cover - compiled
    """Accumulate the moments of the normal equations at the parameters ``p`` into ``mom``.

    Returns False (``mom`` then incomplete) when a sample needs a tap outside the window or
    touches a non-finite value.
    """
    if not cubic:
        return _moments_bilinear(base, dist, col, row, p, rx, ry, tmean, mom)
    height, width = dist.shape[0], dist.shape[1]
    xmax = width - 1.0
    ymax = height - 1.0
    x, y = p[0], p[1]
    a11, a12, a21, a22 = p[2], p[3], p[4], p[5]
    offset, gain = p[6], p[7]
    for k in range(_NMOM):
        mom[k] = 0.0
    for v in range(-ry, ry + 1):
        fv = float(v)
        # sums along the template row (v fixed): quadratic gradient terms times 1, u, u^2 ...
        sxx0 = sxx1 = sxx2 = 0.0
        sxy0 = sxy1 = sxy2 = 0.0
        syy0 = syy1 = syy2 = 0.0
        # ... and linear terms times 1, u
        sx0 = sx1 = sy0 = sy1 = 0.0
        sgx0 = sgx1 = sgy0 = sgy1 = 0.0
        sex0 = sex1 = sey0 = sey1 = 0.0
        sg = sgg = se = seg = see = stg = 0.0
        tr = row + v
        for u in range(-rx, rx + 1):
            fu = float(u)
            px = x + a11 * fu + a12 * fv
            py = y + a21 * fu + a22 * fv
            # Keys (a = -0.5) cubic convolution; value and the exact derivatives of the
            # interpolant, so the design rows are the true Jacobian (quadratic convergence)
            if not (px >= 1.0 and px < xmax - 1.0 and py >= 1.0 and py < ymax - 1.0):
                return False
            c = int(px)
            r = int(py)
            tx = px - c
            ty = py - r
            tx2 = tx * tx
            ty2 = ty * ty
            wx0 = (-0.5 * tx + 1.0) * tx2 - 0.5 * tx
            wx1 = (1.5 * tx - 2.5) * tx2 + 1.0
            wx2 = (-1.5 * tx + 2.0) * tx2 + 0.5 * tx
            wx3 = (0.5 * tx - 0.5) * tx2
            dx0 = -1.5 * tx2 + 2.0 * tx - 0.5
            dx1 = 4.5 * tx2 - 5.0 * tx
            dx2 = -4.5 * tx2 + 4.0 * tx + 0.5
            dx3 = 1.5 * tx2 - tx
            wy0 = (-0.5 * ty + 1.0) * ty2 - 0.5 * ty
            wy1 = (1.5 * ty - 2.5) * ty2 + 1.0
            wy2 = (-1.5 * ty + 2.0) * ty2 + 0.5 * ty
            wy3 = (0.5 * ty - 0.5) * ty2
            dy0 = -1.5 * ty2 + 2.0 * ty - 0.5
            dy1 = 4.5 * ty2 - 5.0 * ty
            dy2 = -4.5 * ty2 + 4.0 * ty + 0.5
            dy3 = 1.5 * ty2 - ty
            g = 0.0
            gx = 0.0
            gy = 0.0
            for i in range(4):
                rr = r - 1 + i
                d0 = dist[rr, c - 1, 0]
                d1 = dist[rr, c, 0]
                d2 = dist[rr, c + 1, 0]
                d3 = dist[rr, c + 2, 0]
                hv = wx0 * d0 + wx1 * d1 + wx2 * d2 + wx3 * d3
                hd = dx0 * d0 + dx1 * d1 + dx2 * d2 + dx3 * d3
                if i == 0:
                    wyi, dyi = wy0, dy0
                elif i == 1:
                    wyi, dyi = wy1, dy1
                elif i == 2:
                    wyi, dyi = wy2, dy2
                else:
                    wyi, dyi = wy3, dy3
                g += wyi * hv
                gx += wyi * hd
                gy += dyi * hv
            check = g + gx + gy
            if not (check - check == 0.0):  # NaN or infinite somewhere
                return False
            t = float(base[tr, col + u])
            e = t - gain * g - offset
            q = gx * gx
            sxx0 += q
            sxx1 += q * fu
            sxx2 += q * fu * fu
            q = gx * gy
            sxy0 += q
            sxy1 += q * fu
            sxy2 += q * fu * fu
            q = gy * gy
            syy0 += q
            syy1 += q * fu
            syy2 += q * fu * fu
            sx0 += gx
            sx1 += gx * fu
            sy0 += gy
            sy1 += gy * fu
            q = g * gx
            sgx0 += q
            sgx1 += q * fu
            q = g * gy
            sgy0 += q
            sgy1 += q * fu
            q = e * gx
            sex0 += q
            sex1 += q * fu
            q = e * gy
            sey0 += q
            sey1 += q * fu
            sg += g
            sgg += g * g
            se += e
            seg += e * g
            see += e * e
            stg += (t - tmean) * g
        # fold the row into the moments in (1, u, v, uu, uv, vv) / (1, u, v)
        vv = fv * fv
        mom[0] += sxx0
        mom[1] += sxx1
        mom[2] += fv * sxx0
        mom[3] += sxx2
        mom[4] += fv * sxx1
        mom[5] += vv * sxx0
        mom[6] += sxy0
        mom[7] += sxy1
        mom[8] += fv * sxy0
        mom[9] += sxy2
        mom[10] += fv * sxy1
        mom[11] += vv * sxy0
        mom[12] += syy0
        mom[13] += syy1
        mom[14] += fv * syy0
        mom[15] += syy2
        mom[16] += fv * syy1
        mom[17] += vv * syy0
        mom[18] += sx0
        mom[19] += sx1
        mom[20] += fv * sx0
        mom[21] += sy0
        mom[22] += sy1
        mom[23] += fv * sy0
        mom[24] += sgx0
        mom[25] += sgx1
        mom[26] += fv * sgx0
        mom[27] += sgy0
        mom[28] += sgy1
        mom[29] += fv * sgy0
        mom[30] += sex0
        mom[31] += sex1
        mom[32] += fv * sex0
        mom[33] += sey0
        mom[34] += sey1
        mom[35] += fv * sey0
        mom[_SG] += sg
        mom[_SGG] += sgg
        mom[_SE] += se
        mom[_SEG] += seg
        mom[_SEE] += see
        mom[_STG] += stg
    return True


@numba.njit(nogil=True, cache=True)
def _normal_equations(mom, gain, npix, nmat, rhs):  # pragma: no cover - compiled
    """Assemble the 8x8 normal matrix and right-hand side from the moments."""
    g2 = gain * gain
    for i in range(6):
        ai = _AXIS[i]
        wi = _WEIGHT[i]
        for j in range(i, 6):
            nmat[i, j] = g2 * mom[6 * (ai + _AXIS[j]) + _PAIR[wi][_WEIGHT[j]]]
        nmat[i, 6] = gain * mom[_LIN + 3 * ai + wi]
        nmat[i, 7] = gain * mom[_LIN + 3 * (2 + ai) + wi]
        rhs[i] = gain * mom[_LIN + 3 * (4 + ai) + wi]
    nmat[6, 6] = float(npix)
    nmat[6, 7] = mom[_SG]
    nmat[7, 7] = mom[_SGG]
    rhs[6] = mom[_SE]
    rhs[7] = mom[_SEG]
    for i in range(NPARAMS):
        for j in range(i):
            nmat[i, j] = nmat[j, i]


@numba.njit(nogil=True, cache=True)
def _factor(nmat, scale, chol):  # pragma: no cover - compiled
    """Cholesky factor of ``nmat`` scaled to a unit diagonal; False if not positive definite."""
    n = nmat.shape[0]
    for i in range(n):
        d = nmat[i, i]
        if not (d > 0.0 and d < np.inf):
            return False
        scale[i] = 1.0 / math.sqrt(d)
    for j in range(n):
        acc = nmat[j, j] * scale[j] * scale[j]
        for k in range(j):
            acc -= chol[j, k] * chol[j, k]
        if not (acc > _MIN_PIVOT):  # also False for NaN
            return False
        ljj = math.sqrt(acc)
        chol[j, j] = ljj
        for i in range(j + 1, n):
            acc = nmat[i, j] * scale[i] * scale[j]
            for k in range(j):
                acc -= chol[i, k] * chol[j, k]
            chol[i, j] = acc / ljj
    return True


@numba.njit(nogil=True, cache=True)
def _solve(chol, scale, rhs, sol):  # pragma: no cover - compiled
    """Solve ``nmat @ sol = rhs`` with the scaled factor from :func:`_factor`."""
    n = chol.shape[0]
    for i in range(n):
        acc = rhs[i] * scale[i]
        for k in range(i):
            acc -= chol[i, k] * sol[k]
        sol[i] = acc / chol[i, i]
    for i in range(n - 1, -1, -1):
        acc = sol[i]
        for k in range(i + 1, n):
            acc -= chol[k, i] * sol[k]
        sol[i] = acc / chol[i, i]
    for i in range(n):
        sol[i] *= scale[i]


@numba.njit(nogil=True, cache=True)
def _relaxation(omega, sx, sy, prev_x, prev_y):  # pragma: no cover - compiled
    """The next relaxation factor: the secant (Aitken) estimate ``q`` of the rate along the
    ``(x, y)`` steps, ``omega / (1 - q)`` within ``[_MIN_RELAX, 1]`` (1 when ``q >= 1``)."""
    den = prev_x * prev_x + prev_y * prev_y
    q = (sx * prev_x + sy * prev_y) / den if den > 0.0 else 0.0
    if q < 1.0:
        return min(1.0, max(_MIN_RELAX, omega / (1.0 - q)))
    return 1.0


@numba.njit(nogil=True, cache=True)
def _shift_covariance(chol, scale, s02, rhs, step):  # pragma: no cover - compiled
    """``(cxx, cxy, cyy)``: the shift block of ``s02 N^-1`` (the first two columns of the full
    inverse) from the scaled factor of ``N``; ``rhs`` and ``step`` are work arrays of its size."""
    for k in range(rhs.shape[0]):
        rhs[k] = 0.0
    rhs[0] = 1.0
    _solve(chol, scale, rhs, step)
    cxx = s02 * step[0]
    cxy = s02 * step[1]
    rhs[0] = 0.0
    rhs[1] = 1.0
    _solve(chol, scale, rhs, step)
    return cxx, cxy, s02 * step[1]


@numba.njit(nogil=True, cache=True)
def _verdict(p, x0, y0, det0, gain, rho, cxx, cxy, cyy, max_shift, min_rho, max_sigma, min_det):
    # pragma: no cover - compiled
    """The exit code of a converged match with parameters ``p`` (the tests after ``NOT_CONVERGED``,
    in the order of :class:`Exit`): moved from ``(x0, y0)``, affine determinant against ``det0``
    and ``gain``, correlation, the shift covariance's largest eigenvalue."""
    if math.sqrt((p[0] - x0) ** 2 + (p[1] - y0) ** 2) > max_shift:
        return _MOVED
    # det / det0 within [min_det, 1 / min_det], written without divisions
    det = p[2] * p[5] - p[3] * p[4]
    ratio = det * det0  # same sign as det / det0
    if not (det0 != 0.0 and ratio >= min_det * det0 * det0 and ratio * min_det <= det0 * det0 and gain > 0.0):
        return _DEGENERATE
    if not (rho >= min_rho):
        return _LOW_CORRELATION
    half = 0.5 * (cxx - cyy)
    largest = 0.5 * (cxx + cyy) + math.sqrt(half * half + cxy * cxy)
    if not (largest <= max_sigma * max_sigma):
        return _IMPRECISE
    return _ACCEPTED


@numba.njit(nogil=True, cache=True)
def alsc_point(
    base, dist, col, row, init, out, radius, radius_y, cubic, max_iter, tol, max_shift, min_rho,
    max_sigma, min_det,
):  # pragma: no cover - compiled
    """Least-squares match of one template; returns the exit code (see :class:`Exit`).

    Parameters
    ----------
    base : ndarray of float32, shape (H, W)
        Base window; the template is ``base[row - radius : row + radius + 1,
        col - radius : col + radius + 1]``.
    dist : ndarray of float32, shape (H', W', 4)
        Distorted window with its gradients along x (columns) and y (rows), one record
        ``(value, gx, gy, 0)`` per pixel, as made by :func:`samples`.
    col, row : int
        Template centre in ``base``.
    init : ndarray of float64, shape (8,)
        Start parameters ``(x, y, a11, a12, a21, a22, offset, gain)``; ``x, y`` in the frame
        of ``dist``.
    out : ndarray of float64, shape (12,)
        Filled with :data:`FIELDS`: the final parameters (also when rejected; the start
        parameters if the template itself is unusable), ``sigma_x, sigma_y, rho`` where they
        could be computed (NaN otherwise) and the number of Gauss-Newton updates made.
    radius, radius_y : int
        Template half-width (columns) and half-height (rows): the template has
        ``(2 radius + 1) x (2 radius_y + 1)`` pixels.
    cubic : bool
        Sample ``dist`` by cubic convolution with the exact derivatives of the interpolant
        (the table's gradients are then not used); otherwise bilinear with interpolated
        central-difference gradients.
    max_iter : int
        Largest number of Gauss-Newton updates.
    tol : float
        Convergence threshold of the length of the (unrelaxed) Gauss-Newton step of
        ``(x, y)`` (px).
    max_shift : float
        Largest accepted distance of the final from the start ``(x, y)`` (px).
    min_rho : float
        Smallest accepted correlation coefficient.
    max_sigma : float
        Largest accepted standard deviation (px) along the worst direction of the shift.
    min_det : float
        Accepted range ``[min_det, 1 / min_det]`` of the affine determinant relative to the
        start affine.

    Returns
    -------
    int
        The exit code.
    """
    nan = np.nan
    p = np.empty(NPARAMS)
    for k in range(NPARAMS):
        p[k] = init[k]
        out[k] = p[k]
    for k in range(NPARAMS, NFIELDS):
        out[k] = nan
    out[F_ITERATIONS] = 0.0
    rx = radius
    ry = radius_y
    npix = (2 * rx + 1) * (2 * ry + 1)
    bh, bw = base.shape
    if col - rx < 0 or col + rx >= bw or row - ry < 0 or row + ry >= bh:
        return _OUTSIDE
    # template mean and sum of squares about it
    st = 0.0
    for r in range(row - ry, row + ry + 1):
        for c in range(col - rx, col + rx + 1):
            t = float(base[r, c])
            if not (t - t == 0.0):
                return _OUTSIDE
            st += t
    tmean = st / npix
    stt = 0.0
    for r in range(row - ry, row + ry + 1):
        for c in range(col - rx, col + rx + 1):
            t = float(base[r, c]) - tmean
            stt += t * t

    mom = np.empty(_NMOM)
    nmat = np.empty((NPARAMS, NPARAMS))
    chol = np.zeros((NPARAMS, NPARAMS))
    rhs = np.empty(NPARAMS)
    scale = np.empty(NPARAMS)
    step = np.empty(NPARAMS)
    x0 = p[0]
    y0 = p[1]
    det0 = p[2] * p[5] - p[3] * p[4]

    code = _ACCEPTED
    updates = 0
    omega = 1.0
    prev_x = 0.0
    prev_y = 0.0
    while True:
        if not _moments(base, dist, col, row, p, rx, ry, cubic, tmean, mom):
            code = _OUTSIDE
            break
        _normal_equations(mom, p[7], npix, nmat, rhs)
        if updates >= max_iter:
            code = _NOT_CONVERGED
            break
        if not _factor(nmat, scale, chol):
            code = _SINGULAR
            break
        _solve(chol, scale, rhs, step)
        sx = step[0]
        sy = step[1]
        if updates > 0:
            omega = _relaxation(omega, sx, sy, prev_x, prev_y)
        for k in range(NPARAMS):
            p[k] += omega * step[k]
        updates += 1
        prev_x = sx
        prev_y = sy
        if math.sqrt(sx * sx + sy * sy) < tol:
            break  # converged: the statistics are those of this evaluation

    for k in range(NPARAMS):
        out[k] = p[k]
    out[F_ITERATIONS] = float(updates)
    if code == _OUTSIDE:
        return code
    # correlation of the template and the resampled patch of the last evaluation
    sg = mom[_SG]
    vg = mom[_SGG] - sg * sg / npix
    if stt > 0.0 and vg > 0.0:
        rho = mom[_STG] / math.sqrt(stt * vg)
    else:
        rho = nan
    out[F_RHO] = rho
    if code == _SINGULAR:
        return code
    if not _factor(nmat, scale, chol):
        return _SINGULAR
    s02 = mom[_SEE] / (npix - NPARAMS) if npix > NPARAMS else nan
    cxx, cxy, cyy = _shift_covariance(chol, scale, s02, rhs, step)
    out[F_SIGMA_X] = math.sqrt(cxx)
    out[F_SIGMA_Y] = math.sqrt(cyy)
    if code == _NOT_CONVERGED:
        return code
    return _verdict(p, x0, y0, det0, p[7], rho, cxx, cxy, cyy, max_shift, min_rho, max_sigma, min_det)


@numba.njit(nogil=True, cache=True)
def alsc_step(
    base, dist, col, row, init, out, radius, radius_y, cubic, step_tol, max_shift, min_rho,
    max_sigma, min_det,
):  # pragma: no cover - compiled
    """One verified Gauss-Newton step from a close start; returns the exit code.

    For a start that is already close to the solution (the interpolation of two converged
    neighbours on the same scan line): the normal equations are evaluated once, at
    ``init``; the full step ``s`` is added to the parameters, and ``sigma_x, sigma_y``
    (from the full 8x8 inverse, ``sigma0^2 N^-1``) and ``rho`` are those of that evaluation.
    The step counts as converged when its ``(x, y)`` part is shorter than ``step_tol``
    (otherwise :attr:`Exit.NOT_CONVERGED`, and the caller iterates with :func:`alsc_point`);
    the other tests and exit codes are those of :func:`alsc_point`, the shift measured from
    ``init``. Arguments as for :func:`alsc_point` (``step_tol`` replaces ``max_iter`` and ``tol``).
    """
    nan = np.nan
    for k in range(NPARAMS):
        out[k] = init[k]
    for k in range(NPARAMS, NFIELDS):
        out[k] = nan
    out[F_ITERATIONS] = 0.0
    rx = radius
    ry = radius_y
    npix = (2 * rx + 1) * (2 * ry + 1)
    bh, bw = base.shape
    if col - rx < 0 or col + rx >= bw or row - ry < 0 or row + ry >= bh:
        return _OUTSIDE
    st = 0.0
    for r in range(row - ry, row + ry + 1):
        for c in range(col - rx, col + rx + 1):
            t = float(base[r, c])
            if not (t - t == 0.0):
                return _OUTSIDE
            st += t
    tmean = st / npix
    stt = 0.0
    for r in range(row - ry, row + ry + 1):
        for c in range(col - rx, col + rx + 1):
            t = float(base[r, c]) - tmean
            stt += t * t
    mom = np.empty(_NMOM)
    nmat = np.empty((NPARAMS, NPARAMS))
    chol = np.zeros((NPARAMS, NPARAMS))
    rhs = np.empty(NPARAMS)
    scale = np.empty(NPARAMS)
    step = np.empty(NPARAMS)
    if not _moments(base, dist, col, row, init, rx, ry, cubic, tmean, mom):
        return _OUTSIDE
    _normal_equations(mom, init[7], npix, nmat, rhs)
    sg = mom[_SG]
    vg = mom[_SGG] - sg * sg / npix
    if stt > 0.0 and vg > 0.0:
        rho = mom[_STG] / math.sqrt(stt * vg)
    else:
        rho = nan
    out[F_RHO] = rho
    if not _factor(nmat, scale, chol):
        return _SINGULAR
    _solve(chol, scale, rhs, step)
    for k in range(NPARAMS):
        out[k] = init[k] + step[k]
    out[F_ITERATIONS] = 1.0
    s02 = mom[_SEE] / (npix - NPARAMS) if npix > NPARAMS else nan
    cxx, cxy, cyy = _shift_covariance(chol, scale, s02, rhs, step)
    out[F_SIGMA_X] = math.sqrt(cxx)
    out[F_SIGMA_Y] = math.sqrt(cyy)
    sx = out[0] - init[0]
    sy = out[1] - init[1]
    if not (math.sqrt(sx * sx + sy * sy) < step_tol):
        return _NOT_CONVERGED
    det0 = init[2] * init[5] - init[3] * init[4]
    return _verdict(out, init[0], init[1], det0, out[7], rho, cxx, cxy, cyy, max_shift, min_rho, max_sigma, min_det)


@numba.njit(nogil=True, cache=True)
def _alsc_many(
    base, dist, cols, rows, init, out, codes, radius, radius_y, cubic, max_iter, tol, max_shift,
    min_rho, max_sigma, min_det,
):  # pragma: no cover - compiled
    for i in range(cols.shape[0]):
        codes[i] = alsc_point(
            base, dist, cols[i], rows[i], init[i], out[i], radius, radius_y, cubic, max_iter, tol,
            max_shift, min_rho, max_sigma, min_det,
        )


# --------------------------------------------------------------------------
# Python API
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class AlscOptions:
    """Options of the least-squares matching (see :func:`alsc_point` for their meaning).

    Attributes
    ----------
    radius : int
        Template half-width; the template has ``(2 radius + 1) x (2 radius_y + 1)`` pixels.
    radius_y : int, optional
        Template half-height (rows); default ``radius`` (square). A short, wide template suits
        line scanners, whose distortion changes from scan line to scan line.
    interpolation : {"cubic", "bilinear"}
        Sampling of the distorted image (cubic: exact derivatives of the interpolant).
    max_iter : int
        Largest number of Gauss-Newton updates.
    tol : float
        Convergence threshold of the ``(x, y)`` update (px).
    max_shift : float
        Largest distance of the result from the start position (px).
    min_rho : float
        Smallest correlation coefficient.
    max_sigma : float
        Largest standard deviation of the shift along its worst direction (px).
    min_det : float
        The affine determinant must stay within ``[min_det, 1 / min_det]`` of the start's.
    """

    radius: int = 7
    radius_y: int | None = None
    interpolation: str = "bilinear"
    max_iter: int = 20
    tol: float = 1e-3
    max_shift: float = 1.5
    min_rho: float = 0.7
    max_sigma: float = 0.2
    min_det: float = 0.5

    def __post_init__(self) -> None:
        if int(self.radius) != self.radius or self.radius < 1:
            raise ValueError(f"radius must be a positive integer, got {self.radius!r}")
        if self.radius_y is not None and (int(self.radius_y) != self.radius_y or self.radius_y < 1):
            raise ValueError(f"radius_y must be a positive integer, got {self.radius_y!r}")
        if self.interpolation not in ("cubic", "bilinear"):
            raise ValueError(f"interpolation must be 'cubic' or 'bilinear', got {self.interpolation!r}")
        if int(self.max_iter) != self.max_iter or self.max_iter < 0:
            raise ValueError(f"max_iter must be a non-negative integer, got {self.max_iter!r}")
        if not self.tol > 0:
            raise ValueError(f"tol must be positive, got {self.tol!r}")
        if not self.max_shift >= 0:
            raise ValueError(f"max_shift must be non-negative, got {self.max_shift!r}")
        if not self.max_sigma > 0:
            raise ValueError(f"max_sigma must be positive, got {self.max_sigma!r}")
        if not 0 < self.min_det <= 1:
            raise ValueError(f"min_det must be in (0, 1], got {self.min_det!r}")
        if not -1 <= self.min_rho <= 1:
            raise ValueError(f"min_rho must be in [-1, 1], got {self.min_rho!r}")

    @property
    def ry(self) -> int:
        """Template half-height."""
        return int(self.radius if self.radius_y is None else self.radius_y)

    def kernel_args(self) -> tuple:
        """The options in the order of the trailing arguments of :func:`alsc_point`."""
        return (
            int(self.radius), self.ry, self.interpolation == "cubic", int(self.max_iter), float(self.tol), float(self.max_shift), float(self.min_rho),
            float(self.max_sigma), float(self.min_det),
        )


@dataclass(frozen=True)
class AlscResult:
    """Matches of many points (every array has shape (n,)).

    Attributes
    ----------
    x, y : ndarray of float64
        Position in the distorted window conjugate to the template centre.
    a11, a12, a21, a22 : ndarray of float64
        Affine of the template offsets into the distorted window.
    offset, gain : ndarray of float64
        Radiometry: ``base ~ gain * dist + offset``.
    sigma_x, sigma_y : ndarray of float64
        Standard deviations of ``x, y`` (NaN where not computed).
    rho : ndarray of float64
        Correlation coefficient of template and resampled patch (NaN where not computed).
    iterations : ndarray of int32
        Gauss-Newton updates made.
    exit : ndarray of int8
        Exit codes (:class:`Exit`).
    """

    x: np.ndarray
    y: np.ndarray
    a11: np.ndarray
    a12: np.ndarray
    a21: np.ndarray
    a22: np.ndarray
    offset: np.ndarray
    gain: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    rho: np.ndarray
    iterations: np.ndarray
    exit: np.ndarray

    @property
    def accepted(self) -> np.ndarray:
        """Boolean mask of the accepted matches."""
        return self.exit == Exit.ACCEPTED


def gradients(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of a distorted window along x (columns) and y (rows).

    Central differences (one-sided at the border), i.e. :func:`numpy.gradient`, computed in
    float64; NaN propagates to the neighbours of a NaN pixel.

    Parameters
    ----------
    dist : ndarray, shape (H, W)
        The window, at least 2x2.

    Returns
    -------
    grad_x, grad_y : ndarray of float32, shape (H, W)
    """
    a = np.asarray(dist, dtype=np.float64)
    if a.ndim != 2 or min(a.shape) < 2:
        raise ValueError(f"dist must be a 2-D array of at least 2x2 pixels, got shape {a.shape}")
    gy, gx = np.gradient(a)
    return gx.astype(np.float32), gy.astype(np.float32)


def samples(dist: np.ndarray) -> np.ndarray:
    """The distorted window as the matching kernels read it: value and gradients per pixel.

    Parameters
    ----------
    dist : ndarray, shape (..., H, W)
        One window, or several bands of it (leading axes), at least 2x2 pixels.

    Returns
    -------
    ndarray of float32, shape (..., H, W, 4)
        ``(value, gx, gy, 0)`` per pixel, the gradients as made by :func:`gradients`; a bilinear
        tap is one 16-byte record instead of a load from each of three arrays.
    """
    a = np.asarray(dist, dtype=np.float32).astype(np.float64)  # the gradients of the float32 values
    if a.ndim < 2 or min(a.shape[-2:]) < 2:
        raise ValueError(f"dist must have at least 2x2 pixels in its last two axes, got shape {a.shape}")
    out = np.zeros((*a.shape, 4), dtype=np.float32)
    out[..., 0] = a
    gy, gx = np.gradient(a, axis=(-2, -1))
    out[..., 1] = gx
    out[..., 2] = gy
    return out


def _window(image: np.ndarray, name: str) -> np.ndarray:
    a = np.ascontiguousarray(image, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"{name} must be 2-D, got shape {a.shape}")
    return a


def _integers(values: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(values)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.integer):
        if not (np.isfinite(a).all() and (a == np.round(a)).all()):
            raise ValueError(f"{name} must hold integers")
    return np.ascontiguousarray(a, dtype=np.int64)


def alsc(
    base: np.ndarray,
    dist: np.ndarray,
    cols: np.ndarray,
    rows: np.ndarray,
    init: np.ndarray,
    *,
    options: AlscOptions = AlscOptions(),
) -> AlscResult:
    """Least-squares matching of many templates of ``base`` in ``dist``.

    Parameters
    ----------
    base : ndarray, shape (H, W)
        Base window (NaN = nodata).
    dist : ndarray, shape (H', W')
        Distorted window (NaN = nodata); its gradients are made with :func:`gradients`
        (in the table of :func:`samples`).
    cols, rows : ndarray of int, shape (n,)
        Template centres in ``base``.
    init : ndarray, shape (n, 8) or (8,)
        Start parameters ``(x, y, a11, a12, a21, a22, offset, gain)`` per point (a single
        vector is used for every point); ``x, y`` in the frame of ``dist``.
    options : AlscOptions
        Template size, iteration and acceptance settings.

    Returns
    -------
    AlscResult
        Parameters, precision, correlation and exit code per point.
    """
    b = _window(base, "base")
    d = samples(_window(dist, "dist"))
    c = _integers(cols, "cols")
    r = _integers(rows, "rows")
    if c.shape != r.shape:
        raise ValueError(f"cols and rows differ in shape: {c.shape} != {r.shape}")
    n = c.shape[0]
    start = np.asarray(init, dtype=np.float64)
    if start.shape == (NPARAMS,):
        start = np.broadcast_to(start, (n, NPARAMS))
    if start.shape != (n, NPARAMS):
        raise ValueError(f"init must have shape ({n}, {NPARAMS}), got {start.shape}")
    start = np.ascontiguousarray(start)
    out = np.empty((n, NFIELDS))
    codes = np.empty(n, dtype=np.int8)
    _alsc_many(b, d, c, r, start, out, codes, *options.kernel_args())
    cols_ = {name: out[:, k].copy() for k, name in enumerate(FIELDS)}
    cols_["iterations"] = out[:, F_ITERATIONS].astype(np.int32)
    return AlscResult(**cols_, exit=codes)
