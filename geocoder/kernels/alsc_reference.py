"""Numpy references of the least-squares matching kernels of :mod:`geocoder.kernels.alsc` (for the tests).

:func:`alsc_reference` and :func:`alsc_step_reference` build the design matrix explicitly,
vectorised over the template, and take the covariance from the full inverse of the normal
matrix: the same algorithm as :func:`~geocoder.kernels.alsc.alsc_point` and
:func:`~geocoder.kernels.alsc.alsc_step`, written so that it can be read against the
equations, and slow. The tests compare the numba kernels with them point by point.
"""

from __future__ import annotations

import numpy as np

from .alsc import (
    _MIN_PIVOT,
    _MIN_RELAX,
    F_ITERATIONS,
    F_RHO,
    F_SIGMA_X,
    F_SIGMA_Y,
    NFIELDS,
    NPARAMS,
    AlscOptions,
    Exit,
    _window,
    gradients,
)

__all__ = ["alsc_reference", "alsc_step_reference"]


def _positive_definite(nmat: np.ndarray) -> bool:
    """The rule of ``_factor``: finite, positive diagonal, scaled Cholesky pivots > _MIN_PIVOT."""
    d = np.diag(nmat)
    if not (np.isfinite(nmat).all() and (d > 0).all()):
        return False
    s = 1.0 / np.sqrt(d)
    try:
        chol = np.linalg.cholesky(nmat * s[:, None] * s[None, :])
    except np.linalg.LinAlgError:
        return False
    return bool((np.diag(chol) ** 2 > _MIN_PIVOT).all())


def _cubic_reference(d: np.ndarray, px: np.ndarray, py: np.ndarray):
    """Keys cubic convolution (a = -0.5): value and derivatives at the points (numpy)."""

    def weights(t):
        t2 = t * t
        w = np.stack([(-0.5 * t + 1) * t2 - 0.5 * t, (1.5 * t - 2.5) * t2 + 1, (-1.5 * t + 2) * t2 + 0.5 * t, (0.5 * t - 0.5) * t2])
        dw = np.stack([-1.5 * t2 + 2 * t - 0.5, 4.5 * t2 - 5 * t, -4.5 * t2 + 4 * t + 0.5, 1.5 * t2 - t])
        return w, dw

    c0 = np.floor(px).astype(np.intp)
    r0 = np.floor(py).astype(np.intp)
    wx, dwx = weights(px - c0)
    wy, dwy = weights(py - r0)
    g = np.zeros(px.shape)
    gx = np.zeros(px.shape)
    gy = np.zeros(px.shape)
    for i in range(4):
        for j in range(4):
            v = d[r0 - 1 + i, c0 - 1 + j].astype(np.float64)
            g += wy[i] * wx[j] * v
            gx += wy[i] * dwx[j] * v
            gy += dwy[i] * wx[j] * v
    return g, gx, gy


def alsc_reference(
    base: np.ndarray,
    dist: np.ndarray,
    col: int,
    row: int,
    init: np.ndarray,
    *,
    options: AlscOptions = AlscOptions(),
) -> tuple[np.ndarray, int]:
    """Numpy implementation of :func:`alsc_point` for one point (for the tests).

    The design matrix is built explicitly (vectorised over the template) and the covariance
    is taken from the full inverse of the normal matrix.

    Parameters
    ----------
    base, dist : ndarray, shape (H, W) and (H', W')
        Base and distorted windows.
    col, row : int
        Template centre in ``base``.
    init : ndarray, shape (8,)
        Start parameters.
    options : AlscOptions
        As for :func:`alsc`.

    Returns
    -------
    out : ndarray of float64, shape (12,)
        The :data:`FIELDS`.
    code : Exit
        The exit code.
    """
    o = options
    b = _window(base, "base")
    d = _window(dist, "dist")
    gx, gy = gradients(d)
    rx, ry = int(o.radius), o.ry
    cubic = o.interpolation == "cubic"
    p = np.array(init, dtype=np.float64).reshape(NPARAMS)
    out = np.full(NFIELDS, np.nan)
    out[:NPARAMS] = p
    out[F_ITERATIONS] = 0.0
    bh, bw = b.shape
    if col - rx < 0 or col + rx >= bw or row - ry < 0 or row + ry >= bh:
        return out, Exit.OUTSIDE
    t = b[row - ry : row + ry + 1, col - rx : col + rx + 1].astype(np.float64).ravel()
    if not np.isfinite(t).all():
        return out, Exit.OUTSIDE
    vv, uu = np.mgrid[-ry : ry + 1, -rx : rx + 1].astype(np.float64)
    u, v = uu.ravel(), vv.ravel()
    npix = u.size
    dh, dw = d.shape

    def evaluate(p: np.ndarray):
        px = p[0] + p[2] * u + p[3] * v
        py = p[1] + p[4] * u + p[5] * v
        if cubic:
            if not ((px >= 1) & (px < dw - 2) & (py >= 1) & (py < dh - 2)).all():
                return None
            g, ix, iy = _cubic_reference(d, px, py)
            return _assemble(g, ix, iy)
        if not ((px >= 0) & (px < dw - 1) & (py >= 0) & (py < dh - 1)).all():
            return None
        c0 = np.floor(px).astype(np.intp)
        r0 = np.floor(py).astype(np.intp)
        fx, fy = px - c0, py - r0

        def bilinear(img: np.ndarray) -> np.ndarray:
            return (
                (1 - fx) * (1 - fy) * img[r0, c0]
                + fx * (1 - fy) * img[r0, c0 + 1]
                + (1 - fx) * fy * img[r0 + 1, c0]
                + fx * fy * img[r0 + 1, c0 + 1]
            )

        return _assemble(bilinear(d), bilinear(gx), bilinear(gy))

    def _assemble(g, ix, iy):
        if not (np.isfinite(g).all() and np.isfinite(ix).all() and np.isfinite(iy).all()):
            return None
        gain, offset = p[7], p[6]
        design = np.column_stack(
            [gain * ix, gain * iy, gain * ix * u, gain * ix * v, gain * iy * u, gain * iy * v, np.ones(npix), g]
        )
        e = t - gain * g - offset
        return design.T @ design, design.T @ e, e, g

    x0, y0 = p[0], p[1]
    det0 = p[2] * p[5] - p[3] * p[4]
    code = Exit.ACCEPTED
    updates = 0
    omega = 1.0
    prev = np.zeros(2)
    state = None
    while True:
        state = evaluate(p)
        if state is None:
            code = Exit.OUTSIDE
            break
        nmat, rhs, _, _ = state
        if updates >= o.max_iter:
            code = Exit.NOT_CONVERGED
            break
        if not _positive_definite(nmat):
            code = Exit.SINGULAR
            break
        step = np.linalg.solve(nmat, rhs)
        if updates > 0:
            den = prev @ prev
            q = (step[:2] @ prev) / den if den > 0 else 0.0
            omega = min(1.0, max(_MIN_RELAX, omega / (1.0 - q))) if q < 1 else 1.0
        p = p + omega * step
        updates += 1
        prev = step[:2].copy()
        if np.hypot(step[0], step[1]) < o.tol:
            break  # converged: the statistics are those of this evaluation

    out[:NPARAMS] = p
    out[F_ITERATIONS] = updates
    if code == Exit.OUTSIDE:
        return out, code
    nmat, _, e, g = state
    tc, gc = t - t.mean(), g - g.mean()
    den = np.sqrt((tc @ tc) * (gc @ gc))
    rho = float(tc @ gc / den) if den > 0 else np.nan
    out[F_RHO] = rho
    if code == Exit.SINGULAR:
        return out, code
    if not _positive_definite(nmat):
        return out, Exit.SINGULAR
    cov = (e @ e) / (npix - NPARAMS) * np.linalg.inv(nmat)[:2, :2]
    out[F_SIGMA_X], out[F_SIGMA_Y] = np.sqrt(cov[0, 0]), np.sqrt(cov[1, 1])
    if code == Exit.NOT_CONVERGED:
        return out, code
    if np.hypot(p[0] - x0, p[1] - y0) > o.max_shift:
        return out, Exit.MOVED
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (p[2] * p[5] - p[3] * p[4]) / det0
    if not (o.min_det <= ratio <= 1.0 / o.min_det and p[7] > 0):
        return out, Exit.DEGENERATE
    if not rho >= o.min_rho:
        return out, Exit.LOW_CORRELATION
    if not np.linalg.eigvalsh(cov)[-1] <= o.max_sigma**2:
        return out, Exit.IMPRECISE
    return out, Exit.ACCEPTED


def alsc_step_reference(
    base: np.ndarray,
    dist: np.ndarray,
    col: int,
    row: int,
    init: np.ndarray,
    *,
    step_tol: float,
    options: AlscOptions = AlscOptions(),
) -> tuple[np.ndarray, int]:
    """Numpy implementation of :func:`alsc_step` for one point (for the tests).

    The design matrix is built explicitly at ``init``; the covariance is taken from the
    full inverse of the normal matrix. Arguments and result as for :func:`alsc_reference`
    (``options.max_iter`` and ``options.tol`` are not used).
    """
    o = options
    b = _window(base, "base")
    d = _window(dist, "dist")
    gx, gy = gradients(d)
    rx, ry = int(o.radius), o.ry
    p = np.array(init, dtype=np.float64).reshape(NPARAMS)
    out = np.full(NFIELDS, np.nan)
    out[:NPARAMS] = p
    out[F_ITERATIONS] = 0.0
    bh, bw = b.shape
    if col - rx < 0 or col + rx >= bw or row - ry < 0 or row + ry >= bh:
        return out, Exit.OUTSIDE
    t = b[row - ry : row + ry + 1, col - rx : col + rx + 1].astype(np.float64).ravel()
    if not np.isfinite(t).all():
        return out, Exit.OUTSIDE
    vv, uu = np.mgrid[-ry : ry + 1, -rx : rx + 1].astype(np.float64)
    u, v = uu.ravel(), vv.ravel()
    npix = u.size
    dh, dw = d.shape
    px = p[0] + p[2] * u + p[3] * v
    py = p[1] + p[4] * u + p[5] * v
    if o.interpolation == "cubic":
        if not ((px >= 1) & (px < dw - 2) & (py >= 1) & (py < dh - 2)).all():
            return out, Exit.OUTSIDE
        g, ix, iy = _cubic_reference(d, px, py)
    else:
        if not ((px >= 0) & (px < dw - 1) & (py >= 0) & (py < dh - 1)).all():
            return out, Exit.OUTSIDE
        c0 = np.floor(px).astype(np.intp)
        r0 = np.floor(py).astype(np.intp)
        fx, fy = px - c0, py - r0

        def bilinear(img: np.ndarray) -> np.ndarray:
            return (
                (1 - fx) * (1 - fy) * img[r0, c0]
                + fx * (1 - fy) * img[r0, c0 + 1]
                + (1 - fx) * fy * img[r0 + 1, c0]
                + fx * fy * img[r0 + 1, c0 + 1]
            )

        g, ix, iy = bilinear(d), bilinear(gx), bilinear(gy)
    if not (np.isfinite(g).all() and np.isfinite(ix).all() and np.isfinite(iy).all()):
        return out, Exit.OUTSIDE
    gain, offset = p[7], p[6]
    design = np.column_stack([gain * ix, gain * iy, gain * ix * u, gain * ix * v, gain * iy * u, gain * iy * v, np.ones(npix), g])
    e = t - gain * g - offset
    nmat = design.T @ design
    tc, gc = t - t.mean(), g - g.mean()
    den = np.sqrt((tc @ tc) * (gc @ gc))
    rho = float(tc @ gc / den) if den > 0 else np.nan
    out[F_RHO] = rho
    if not _positive_definite(nmat):
        return out, Exit.SINGULAR
    step = np.linalg.solve(nmat, design.T @ e)
    q = p + step
    out[:NPARAMS] = q
    out[F_ITERATIONS] = 1.0
    cov = (e @ e) / (npix - NPARAMS) * np.linalg.inv(nmat)[:2, :2]
    out[F_SIGMA_X], out[F_SIGMA_Y] = np.sqrt(cov[0, 0]), np.sqrt(cov[1, 1])
    shift = np.hypot(step[0], step[1])
    if not shift < step_tol:
        return out, Exit.NOT_CONVERGED
    if shift > o.max_shift:
        return out, Exit.MOVED
    det0 = p[2] * p[5] - p[3] * p[4]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (q[2] * q[5] - q[3] * q[4]) / det0
    if not (o.min_det <= ratio <= 1.0 / o.min_det and q[7] > 0):
        return out, Exit.DEGENERATE
    if not rho >= o.min_rho:
        return out, Exit.LOW_CORRELATION
    if not np.linalg.eigvalsh(cov)[-1] <= o.max_sigma**2:
        return out, Exit.IMPRECISE
    return out, Exit.ACCEPTED
