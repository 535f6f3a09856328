"""Map ground -> scene pixel for a whole window of output pixels, cheaply for rigorous models.

A line scanner solves every point's acquisition time iteratively and an RPC is a ratio of
cubics in geodetic coordinates: over an output tile both are smooth in map position and
linear in height to far below a pixel. So the window is projected exactly on a coarse grid of
nodes (every ``step`` output pixels, at the lowest and highest ground height of the window)
and every pixel is interpolated from its node cell (bilinear) and its height (linear).
Pixels whose cell has a node without a solution are projected exactly. A polynomial is
evaluated at every pixel (it is cheaper than the interpolation). Pure numpy.
"""

from __future__ import annotations

import numpy as np

from ..adjust.models import MapPolynomial

__all__ = ["project_window"]


def _nodes(n: int, step: int) -> np.ndarray:
    """Node positions ``0, step, ...`` and always the last pixel ``n - 1``."""
    return np.unique(np.r_[np.arange(0, n, step), n - 1]).astype(np.float64)


def project_window(model, params: np.ndarray, e: np.ndarray, n: np.ndarray, h: np.ndarray, *,
                   step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Scene pixels of a regular window of map points.

    Parameters
    ----------
    model : SensorModel
        Map ground ``(E, N, h)`` -> scene pixel.
    params : ndarray
    e, n : ndarray, shape (rows, cols)
        Map coordinates of the window's pixels (a regular, axis-aligned grid).
    h : ndarray, shape (rows, cols)
        Their ground heights.
    step : int
        Node spacing (output pixels) of a rigorous model's interpolation; 1 projects every pixel.

    Returns
    -------
    x, y : ndarray, shape (rows, cols)
        Scene column and row; NaN where the model has no solution.
    """
    shape = e.shape
    if isinstance(model, MapPolynomial) or step <= 1 or min(shape) < 2:
        xy = model.project(params, np.column_stack([e.ravel(), n.ravel(), h.ravel()]))
        return xy[:, 0].reshape(shape), xy[:, 1].reshape(shape)
    rows, cols = shape
    nr, nc = _nodes(rows, step), _nodes(cols, step)
    ri, ci = nr.astype(np.int64), nc.astype(np.int64)
    ne, nn = e[np.ix_(ri, ci)], n[np.ix_(ri, ci)]
    lo, hi = float(np.min(h)), float(np.max(h))
    layers = [lo] if hi - lo < 1e-6 else [lo, hi]
    grid = np.concatenate([np.column_stack([ne.ravel(), nn.ravel(), np.full(ne.size, z)]) for z in layers])
    xy = model.project(params, grid).reshape(len(layers), ri.size, ci.size, 2)
    # the pixels' cells and fractions along rows and columns
    pr, pc = np.arange(rows, dtype=np.float64), np.arange(cols, dtype=np.float64)
    a = np.clip(np.searchsorted(nr, pr, side="right") - 1, 0, nr.size - 2)
    b = np.clip(np.searchsorted(nc, pc, side="right") - 1, 0, nc.size - 2)
    fa = ((pr - nr[a]) / (nr[a + 1] - nr[a]))[:, None, None]
    fb = ((pc - nc[b]) / (nc[b + 1] - nc[b]))[None, :, None]
    A, B = a[:, None], b[None, :]
    out = []
    for g in xy:
        out.append((1 - fa) * ((1 - fb) * g[A, B] + fb * g[A, B + 1]) + fa * ((1 - fb) * g[A + 1, B] + fb * g[A + 1, B + 1]))
    if len(layers) == 2:
        t = ((h - lo) / (hi - lo))[..., None]
        res = (1 - t) * out[0] + t * out[1]
    else:
        res = out[0]
    bad = ~np.all(np.isfinite(res), axis=-1)
    if bad.any():
        exact = model.project(params, np.column_stack([e[bad], n[bad], h[bad]]))
        res[bad] = exact
    return res[..., 0], res[..., 1]
