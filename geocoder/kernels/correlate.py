"""Patch correlation and least-squares refinement of point pairs.

Patches are sampled through a local affine so that rotation and scale between the images
do not defeat the correlation (DESIGN.md, data flow step 4): the distorted patch of a point
pair is the distorted image at ``p'' + J @ (u, v)`` for the template offsets ``(u, v)``.

References
----------
Paderes, Mikhail & Foerstner (1984), eqs 23-29 and 34 (weights and correlation);
Foerstner (1982) / Gruen (1985) for least-squares matching.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .alsc import _relaxation
from .resample import bilinear_taps, sample, sample_affine_patches


def patch_offsets(radius: int) -> np.ndarray:
    """Offsets ``(u, v)`` of a square ``(2 radius + 1)^2`` template, shape (P, 2), row-major."""
    r = np.arange(-radius, radius + 1, dtype=np.float64)
    v, u = np.meshgrid(r, r, indexing="ij")
    return np.stack([u.ravel(), v.ravel()], axis=1)


def extract_patches(image: np.ndarray, x: np.ndarray, y: np.ndarray, radius: int) -> np.ndarray:
    """Patches around integral positions, shape (n, P); rows with any pixel outside are NaN."""
    offs = patch_offsets(radius).astype(np.int64)
    xi = np.rint(np.asarray(x)).astype(np.int64)[:, None] + offs[None, :, 0]
    yi = np.rint(np.asarray(y)).astype(np.int64)[:, None] + offs[None, :, 1]
    h, w = image.shape
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    out = image[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)].astype(np.float64)
    out[~inside.all(axis=1)] = np.nan
    return out


def warped_patches(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, jac: np.ndarray, radius: int
) -> np.ndarray:
    """Bilinear patches at ``(x, y) + jac @ (u, v)``, shape (n, P); NaN where undefined.

    ``jac`` has shape (n, 2, 2), rows ``d(x'', y'') / d(x, y)``.
    """
    return sample_affine_patches(image, x, y, jac, patch_offsets(radius)).astype(np.float64)


def correlation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Correlation coefficient of matching rows of ``a`` and ``b`` (eq 34); NaN rows give NaN."""
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    num = (a * b).sum(axis=1)
    den = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def pair_weight(rho: np.ndarray, sd1: np.ndarray, sd2: np.ndarray, w1: np.ndarray, w2: np.ndarray) -> np.ndarray:
    """A-priori weight of a point pair (eq 29).

    ``w = rho / (2 (1 - rho)) / (sigma_g' sigma_g'' sqrt(tr Q' tr Q''))`` with
    ``tr Q = 1 / w_interest`` (eq 32-33).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        snr2 = rho / (2.0 * (1.0 - rho))
        return np.where(rho < 1.0, snr2 * np.sqrt(w1 * w2) / (sd1 * sd2), np.inf)


@dataclass(frozen=True)
class ShiftMatch:
    """Least-squares refined positions of point pairs (all arrays of shape (n,)).

    ``x, y`` are the refined positions in the searched image; ``sigma_x, sigma_y`` their
    standard deviations from the normal matrix and sigma_0; ``rho`` the final correlation;
    ``ok`` whether the iteration converged within ``max_move`` of the start.
    """

    x: np.ndarray
    y: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    rho: np.ndarray
    ok: np.ndarray


def refine_shift(
    template: np.ndarray,
    image: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    jac: np.ndarray,
    radius: int,
    *,
    iterations: int = 12,
    tol: float = 0.005,
    max_move: float = 2.0,
) -> ShiftMatch:
    """Least-squares matching of templates with shift and gain/offset, geometry ``jac`` fixed.

    Minimises ``sum (T(u) - a I(p + J u) - b)^2`` over the shift ``p`` and the radiometric
    ``a, b`` by Gauss-Newton, all points at once (no Python loop over points). The design's
    gradients are central differences, so the steps overshoot on fine texture; they are
    relaxed by the secant estimate of the rate as in :mod:`geocoder.kernels.alsc` (the path
    changes, not the fixed point). A point has converged when its unrelaxed step is shorter
    than ``tol``; its covariance is that of the evaluation that gave this step.

    Parameters
    ----------
    template : ndarray, shape (n, P)
        Base patches (see :func:`extract_patches`).
    image : ndarray, shape (H, W)
        The image searched (NaN = nodata).
    x0, y0 : ndarray, shape (n,)
        Start positions in ``image``.
    jac : ndarray, shape (n, 2, 2)
        Local affine of the template frame into the image frame.
    radius : int
        Template radius (``P = (2 radius + 1)^2``).
    """
    img = np.asarray(image, dtype=np.float32)
    gy, gx = np.gradient(img)
    gx = np.ascontiguousarray(gx, dtype=np.float32)
    gy = np.ascontiguousarray(gy, dtype=np.float32)
    img = np.ascontiguousarray(img)
    offs = patch_offsets(radius)
    du = np.ascontiguousarray(jac[:, 0, 0, None] * offs[:, 0] + jac[:, 0, 1, None] * offs[:, 1])
    dv = np.ascontiguousarray(jac[:, 1, 0, None] * offs[:, 0] + jac[:, 1, 1, None] * offs[:, 1])
    x = np.asarray(x0, dtype=np.float64).copy()
    y = np.asarray(y0, dtype=np.float64).copy()
    n, p = template.shape
    t = np.ascontiguousarray(template, dtype=np.float64)
    converged = np.zeros(n, dtype=bool)
    nmat = np.zeros((n, 4, 4))
    rhs = np.zeros((n, 4))
    res = np.full((n, p), np.nan)
    g = np.empty((n, p))
    omega = np.ones(n)
    prev = np.zeros((n, 2))
    for k in range(iterations):
        # A converged point no longer moves and keeps the normals and residuals of the
        # evaluation that gave its last step (less than ``tol`` from its final position).
        active = ~converged
        _shift_normals(img, gx, gy, t, x, y, du, dv, nmat, rhs, res, g, active)
        bad = ~np.isfinite(nmat).all(axis=(1, 2)) | ~np.isfinite(rhs).all(axis=1)
        nmat[bad] = np.eye(4)
        rhs[bad] = 0.0
        step = np.linalg.solve(nmat + 1e-9 * np.eye(4), rhs[..., None])[..., 0]
        step[bad] = np.nan
        if k > 0:
            _relax_all(omega, step, prev)
        x[active] += omega[active] * step[active, 0]
        y[active] += omega[active] * step[active, 1]
        prev[active] = step[active, :2]
        converged |= np.hypot(step[:, 0], step[:, 1]) < tol
        if converged.all():
            break
    vals = sample(img, x[:, None] + du, y[:, None] + dv, method="bilinear").astype(np.float64)
    rho = correlation(t, vals)
    dof = max(p - 4, 1)
    sigma2 = np.nansum(res**2, axis=1) / dof
    with np.errstate(invalid="ignore"):
        cov = np.linalg.pinv(nmat) * sigma2[:, None, None]
    moved = np.hypot(x - x0, y - y0)
    ok = converged & np.isfinite(rho) & (moved <= max_move) & np.isfinite(x) & np.isfinite(y)
    return ShiftMatch(
        x=x,
        y=y,
        sigma_x=np.sqrt(np.abs(cov[:, 0, 0])),
        sigma_y=np.sqrt(np.abs(cov[:, 1, 1])),
        rho=rho,
        ok=ok,
    )


@numba.njit(nogil=True, cache=True)
def _relax_all(omega, step, prev):  # pragma: no cover - compiled
    """ALSC's relaxation factor (:func:`geocoder.kernels.alsc._relaxation`) of every point's next
    ``(x, y)`` step, in place in ``omega``."""
    for i in range(omega.shape[0]):
        omega[i] = _relaxation(omega[i], step[i, 0], step[i, 1], prev[i, 0], prev[i, 1])


@numba.njit(nogil=True, cache=True, inline="always")
def _bilinear3(img, gx, gy, xp, yp):  # pragma: no cover - compiled
    """Bilinear values of ``img``, ``gx``, ``gy`` at one point, as :func:`sample` computes them.

    Same tap rules (NaN outside, taps of zero weight never read) and the same float64
    arithmetic, rounded to float32 like :func:`sample`'s output.
    """
    height, width = img.shape
    if not (xp > -3.0 and xp < width + 2.0 and yp > -3.0 and yp < height + 2.0):
        return np.nan, np.nan, np.nan
    x0 = math.floor(xp)
    y0 = math.floor(yp)
    fx = xp - x0
    fy = yp - y0
    c = int(x0)
    r = int(y0)
    wx0, wx1, wy0, wy1 = 1.0 - fx, fx, 1.0 - fy, fy
    if (wy0 != 0.0 and (r < 0 or r >= height)) or (wy1 != 0.0 and (r + 1 < 0 or r + 1 >= height)) \
            or (wx0 != 0.0 and (c < 0 or c >= width)) or (wx1 != 0.0 and (c + 1 < 0 or c + 1 >= width)):
        return np.nan, np.nan, np.nan
    return (
        np.float64(np.float32(bilinear_taps(img, r, c, wy0, wy1, wx0, wx1))),
        np.float64(np.float32(bilinear_taps(gx, r, c, wy0, wy1, wx0, wx1))),
        np.float64(np.float32(bilinear_taps(gy, r, c, wy0, wy1, wx0, wx1))),
    )


@numba.njit(nogil=True, cache=True)
def _sample_patch_fast(img, gx, gy, x, y, du, dv, g, ix, iy):  # pragma: no cover - compiled
    """Image and gradients at ``(x + du, y + dv)`` when every tap of every sample is inside
    and weighs (the usual case); False, and partial output, as soon as one is not.

    The sums are :func:`sample`'s for four weighing taps, in its order; kept apart from the
    general case so that this loop compiles tight.
    """
    height, width = img.shape
    for k in range(du.shape[0]):
        xp = x + du[k]
        yp = y + dv[k]
        if not (xp > 0.0 and xp < width - 1 and yp > 0.0 and yp < height - 1):
            return False
        x0 = math.floor(xp)
        y0 = math.floor(yp)
        fx = xp - x0
        fy = yp - y0
        if fx == 0.0 or fy == 0.0:
            return False
        c = int(x0)
        r = int(y0)
        wx0, wx1, wy0, wy1 = 1.0 - fx, fx, 1.0 - fy, fy
        if wx0 == 0.0 or wy0 == 0.0:
            return False
        g[k] = np.float32(wy0 * (wx0 * img[r, c] + wx1 * img[r, c + 1]) + wy1 * (wx0 * img[r + 1, c] + wx1 * img[r + 1, c + 1]))
        ix[k] = np.float32(wy0 * (wx0 * gx[r, c] + wx1 * gx[r, c + 1]) + wy1 * (wx0 * gx[r + 1, c] + wx1 * gx[r + 1, c + 1]))
        iy[k] = np.float32(wy0 * (wx0 * gy[r, c] + wx1 * gy[r, c + 1]) + wy1 * (wx0 * gy[r + 1, c] + wx1 * gy[r + 1, c + 1]))
    return True


@numba.njit(nogil=True, cache=True)
def _sample_patch(img, gx, gy, x, y, du, dv, g, ix, iy):  # pragma: no cover - compiled
    """Image and gradients at ``(x + du, y + dv)``, any position (NaN as :func:`sample`)."""
    for k in range(du.shape[0]):
        v0, v1, v2 = _bilinear3(img, gx, gy, x + du[k], y + dv[k])
        g[k] = v0
        ix[k] = v1
        iy[k] = v2


@numba.njit(nogil=True, cache=True)
def _shift_normals(img, gx, gy, t, x, y, du, dv, nmat, rhs, res, g, todo):  # pragma: no cover - compiled
    """Normal equations of one Gauss-Newton step of :func:`refine_shift`, points with ``todo``.

    For point ``i`` the image and its gradients are sampled (bilinear) at
    ``(x_i + du_i, y_i + dv_i)``; gain and offset come in closed form, then the design
    rows ``(a I_x, a I_y, g, 1)`` and the residuals ``t - (a g + b)`` give ``nmat[i]``
    (4 x 4), ``rhs[i]`` (4) and ``res[i]`` (P). NaN samples make the point's arrays NaN,
    as in :func:`_shift_normals_reference`.
    """
    n, p = t.shape
    ix = np.empty(p)
    iy = np.empty(p)
    for i in range(n):
        if not todo[i]:
            continue
        if not _sample_patch_fast(img, gx, gy, x[i], y[i], du[i], dv[i], g[i], ix, iy):
            _sample_patch(img, gx, gy, x[i], y[i], du[i], dv[i], g[i], ix, iy)
        gs = 0.0
        ts = 0.0
        for k in range(p):
            gs += g[i, k]
            ts += t[i, k]
        gm = gs / p
        tm = ts / p
        var = 0.0
        cov = 0.0
        for k in range(p):
            var += (g[i, k] - gm) ** 2
            cov += (g[i, k] - gm) * (t[i, k] - tm)
        a = cov / var if var > 0 else np.nan
        b = tm - a * gm
        # design row (a I_x, a I_y, g, 1); the 10 distinct entries of the normals as scalars
        n00 = n01 = n02 = n03 = n11 = n12 = n13 = n22 = n23 = n33 = 0.0
        r0 = r1 = r2 = r3 = 0.0
        for k in range(p):
            gk = g[i, k]
            e = t[i, k] - (a * gk + b)
            res[i, k] = e
            d0 = a * ix[k]
            d1 = a * iy[k]
            r0 += d0 * e
            r1 += d1 * e
            r2 += gk * e
            r3 += e
            n00 += d0 * d0
            n01 += d0 * d1
            n02 += d0 * gk
            n03 += d0
            n11 += d1 * d1
            n12 += d1 * gk
            n13 += d1
            n22 += gk * gk
            n23 += gk
            n33 += 1.0
        rhs[i, 0] = r0
        rhs[i, 1] = r1
        rhs[i, 2] = r2
        rhs[i, 3] = r3
        nm = nmat[i]
        nm[0, 0] = n00
        nm[0, 1] = nm[1, 0] = n01
        nm[0, 2] = nm[2, 0] = n02
        nm[0, 3] = nm[3, 0] = n03
        nm[1, 1] = n11
        nm[1, 2] = nm[2, 1] = n12
        nm[1, 3] = nm[3, 1] = n13
        nm[2, 2] = n22
        nm[2, 3] = nm[3, 2] = n23
        nm[3, 3] = n33


def _shift_normals_reference(img, gx, gy, t, x, y, du, dv):
    """Numpy reference of :func:`_shift_normals`: returns ``nmat, rhs, res, g``."""
    stack = np.stack([img, gx, gy])
    g, ix, iy = sample(stack, x[:, None] + du, y[:, None] + dv, method="bilinear").astype(np.float64)
    gm, tm = g.mean(1, keepdims=True), t.mean(1, keepdims=True)
    var = ((g - gm) ** 2).sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(var > 0, ((g - gm) * (t - tm)).sum(1) / var, np.nan)
    b = tm[:, 0] - a * gm[:, 0]
    res = t - (a[:, None] * g + b[:, None])
    design = np.stack([a[:, None] * ix, a[:, None] * iy, g, np.ones_like(g)], axis=2)
    nmat = np.einsum("npi,npj->nij", design, design)
    rhs = np.einsum("npi,np->ni", design, res)
    return nmat, rhs, res, g
