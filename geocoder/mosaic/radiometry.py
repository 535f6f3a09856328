"""Radiometric balance of a mosaic: a gain and an offset per scene and band, by least squares.

Equations (one per point and band): a control point says the scene's balanced value equals the
reference's, ``g_k v + o_k = r``; a tie point says two scenes agree, ``g_i v_i + o_i = g_j v_j + o_j``.
Without any control the mean gain is held at 1 and the mean offset at 0. Points whose residual
exceeds 3 robust sigmas (clouds, changes, occlusions) are dropped and the system solved again.
Pure numpy/scipy: no dask, no I/O.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import lsqr


def solve_balance(
    n_scenes: int,
    control: list[tuple[int, np.ndarray, np.ndarray]],
    ties: list[tuple[int, int, np.ndarray, np.ndarray]],
) -> np.ndarray:
    """Gain and offset of every scene for one band.

    Parameters
    ----------
    n_scenes : int
    control : list of (k, v, r)
        Scene ``k``'s values ``v`` at points where the reference has ``r``.
    ties : list of (i, j, v_i, v_j)
        Values of scenes ``i`` and ``j`` at their common points.

    Returns
    -------
    ndarray, shape (n_scenes, 2)
        ``(gain, offset)``; ``(1, 0)`` for a scene no equation reaches.
    """
    rows, cols, vals, rhs = [], [], [], []
    n = 0

    def add(entries: list[tuple[int, np.ndarray]], b: np.ndarray) -> None:
        nonlocal n
        m = b.size
        for col, v in entries:
            rows.append(n + np.arange(m))
            cols.append(np.full(m, col))
            vals.append(np.broadcast_to(v, (m,)).astype(np.float64))
        rhs.append(b.astype(np.float64))
        n += m

    for k, v, r in control:
        ok = np.isfinite(v) & np.isfinite(r)
        add([(2 * k, v[ok]), (2 * k + 1, np.ones(ok.sum()))], r[ok])
    for i, j, vi, vj in ties:
        ok = np.isfinite(vi) & np.isfinite(vj)
        m = int(ok.sum())
        add([(2 * i, vi[ok]), (2 * i + 1, np.ones(m)), (2 * j, -vj[ok]), (2 * j + 1, -np.ones(m))], np.zeros(m))
    if not control:
        add([(2 * k, np.ones(1) / n_scenes) for k in range(n_scenes)], np.ones(1))
        add([(2 * k + 1, np.ones(1) / n_scenes) for k in range(n_scenes)], np.zeros(1))
    if n == 0:
        return np.tile([1.0, 0.0], (n_scenes, 1))
    a = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, 2 * n_scenes))
    b = np.concatenate(rhs)
    # unknowns no equation touches stay at (1, 0): a tiny prior keeps the system full rank
    prior = sp.identity(2 * n_scenes, format="csr") * 1e-6
    start = np.tile([1.0, 0.0], n_scenes)
    weights = np.ones(n)
    for _ in range(2):
        sw = sp.diags(weights)
        x = lsqr(sp.vstack([sw @ a, prior]), np.concatenate([weights * b, 1e-6 * start]), atol=1e-12, btol=1e-12)[0]
        res = a @ x - b
        scale = 1.4826 * np.median(np.abs(res[weights > 0])) if np.any(weights > 0) else 0.0
        if scale <= 0:
            break
        weights = (np.abs(res) <= 3 * scale).astype(np.float64)
    return x.reshape(n_scenes, 2)


def seam_step(ties: list[tuple[int, int, np.ndarray, np.ndarray]], balance: np.ndarray | None = None) -> float:
    """RMS grey-value difference between scenes at their tie points (after ``balance`` if given)."""
    d = []
    for i, j, vi, vj in ties:
        if balance is not None:
            vi, vj = balance[i, 0] * vi + balance[i, 1], balance[j, 0] * vj + balance[j, 1]
        diff = vi - vj
        d.append(diff[np.isfinite(diff)])
    d = np.concatenate(d) if d else np.zeros(0)
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")
