"""Figures of a mosaic's block adjustment and seams, for its summary and report.

Pure numpy: no dask, no I/O. All are small (a few numbers per scene or pair), so that the
summary of a block of thousands of scenes stays a few megabytes.
"""

from __future__ import annotations

import numpy as np

__all__ = ["footprint_outline", "pair_mismatch", "residual_bins", "scene_precision", "seam_errors", "seam_table"]


def scene_precision(model, params: np.ndarray, cov: np.ndarray | None, ground: np.ndarray) -> float:
    """RMS standard deviation of a scene's adjusted position over its footprint, in scene pixels.

    Parameters
    ----------
    model : SensorModel
        The scene's model (map -> scene pixel).
    params : ndarray
        Its adjusted parameters.
    cov : ndarray, shape (n, n) or None
        Their covariance (``sigma0**2`` times the block of the inverse normal matrix).
    ground : ndarray, shape (m, 3)
        Points of the footprint (map coordinates, height 0).

    Returns
    -------
    float
        ``sqrt(mean(trace(J C J^T) / 2))`` over the points; NaN without a covariance.
    """
    if cov is None or not np.all(np.isfinite(cov)):
        return float("nan")
    jp, _ = model.jacobians(params, ground)
    var = np.einsum("mai,ij,maj->m", jp, cov, jp) / 2.0
    return float(np.sqrt(np.mean(np.maximum(var, 0.0))))


def residual_bins(xy: np.ndarray, residuals: np.ndarray, shape: tuple[int, int], *, bins: int = 3) -> list[list[float]]:
    """Mean image residual of a scene's observations in ``bins x bins`` cells of the scene.

    Parameters
    ----------
    xy : ndarray, shape (m, 2)
        Observed scene pixels.
    residuals : ndarray, shape (m, 2)
        Their residuals (observed minus adjusted), in scene pixels.
    shape : (rows, cols)
        The scene's size.
    bins : int
        Cells per axis.

    Returns
    -------
    list of [x, y, rx, ry, n]
        Per non-empty cell: the mean position and residual of its observations and their number.
    """
    h, w = shape
    if len(xy) == 0:
        return []
    bx = np.clip((xy[:, 0] / max(w, 1) * bins).astype(int), 0, bins - 1)
    by = np.clip((xy[:, 1] / max(h, 1) * bins).astype(int), 0, bins - 1)
    cell = by * bins + bx
    n = np.bincount(cell, minlength=bins * bins)
    out = []
    for q in np.flatnonzero(n):
        sel = cell == q
        out.append([float(xy[sel, 0].mean()), float(xy[sel, 1].mean()), float(residuals[sel, 0].mean()),
                    float(residuals[sel, 1].mean()), int(n[q])])
    return out


def pair_mismatch(obs_frame: np.ndarray, obs_point: np.ndarray, residuals: np.ndarray, active: np.ndarray,
                  pairs: list[tuple[int, int]]) -> list[float]:
    """RMS disagreement of two scenes at their common ground points, from the adjustment's residuals.

    A ground point seen in scenes ``i`` and ``j`` has residuals ``v_i`` and ``v_j``; the two
    scenes put it ``|v_i - v_j|`` pixels apart (scenes of about the output's pixel). This is
    the adjustment's estimate of the geometric mismatch along their seam.

    Parameters
    ----------
    obs_frame, obs_point : ndarray of int, shape (M,)
        Scene and ground point of every observation.
    residuals : ndarray, shape (M, 2)
    active : ndarray of bool, shape (M,)
        Observations kept by the robust adjustment.
    pairs : list of (i, j)

    Returns
    -------
    list of float
        Per pair, the RMS of ``|v_i - v_j|`` (NaN if they share no point).
    """
    keep = np.flatnonzero(active)
    out = []
    for i, j in pairs:
        oi, oj = keep[obs_frame[keep] == i], keep[obs_frame[keep] == j]
        _, a, b = np.intersect1d(obs_point[oi], obs_point[oj], return_indices=True)
        if a.size == 0:
            out.append(float("nan"))
            continue
        d = residuals[oi[a]] - residuals[oj[b]]
        out.append(float(np.sqrt(np.mean(np.sum(d**2, axis=1)))))
    return out


def footprint_outline(to_out, shape: tuple[int, int], *, per_side: int = 4) -> list[list[float]]:
    """A scene's outline in output pixels: ``per_side`` points along each edge, clockwise.

    Parameters
    ----------
    to_out : callable
        Scene pixel ``(x, y)`` -> output pixel ``(col, row)``.
    shape : (rows, cols)

    Returns
    -------
    list of [col, row]
    """
    h, w = shape
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)
    xs = np.concatenate([t * (w - 1), np.full(per_side, w - 1.0), (1 - t) * (w - 1), np.zeros(per_side)])
    ys = np.concatenate([np.zeros(per_side), t * (h - 1), np.full(per_side, h - 1.0), (1 - t) * (h - 1)])
    cx, cy = to_out(xs, ys)
    return [[round(float(a), 2), round(float(b), 2)] for a, b in zip(cx, cy)]


def seam_table(stats: list[dict], scenes: list[int]) -> list[dict]:
    """Per pair of scenes, the seam's length and grey-value step from the output tiles' statistics.

    Parameters
    ----------
    stats : list of dict
        Every tile's ``seams``: ``(a, b) -> [n, sum d, sum d^2]`` (block indices).
    scenes : list of int
        Block index -> scene index.

    Returns
    -------
    list of dict
        ``i``, ``j`` (scene indices), ``pixels`` (seam length in pixel edges), ``grey_step``
        (RMS of the difference of the two balanced scenes along the seam), ``grey_bias``.
    """
    total: dict[tuple[int, int], np.ndarray] = {}
    for s in stats:
        for key, v in s.items():
            total[key] = total.get(key, np.zeros(3)) + np.asarray(v, dtype=np.float64)
    rows = []
    for (a, b), (n, s1, s2) in sorted(total.items()):
        rows.append({"i": scenes[a], "j": scenes[b], "pixels": int(n), "grey_step": float(np.sqrt(s2 / n)) if n else float("nan"),
                     "grey_bias": float(s1 / n) if n else float("nan")})
    return rows


def seam_errors(source: np.ndarray, transform, models: list, truths: list, shapes: list,
                heights: np.ndarray | None = None) -> np.ndarray:
    """Geometric mismatch of two scenes along the seams, against known truth (tests, benchmarks).

    At every pixel ``p`` whose right or lower neighbour comes from another scene (``a`` and
    ``b``, :func:`~geocoder.mosaic.seams.seam_pairs`), the distance between where the two
    scenes put it: ``|T_a(model_a(p)) - T_b(model_b(p))|``, ``T`` the scenes' true mappings
    scene pixel -> truth-grid pixel.

    Parameters
    ----------
    source : ndarray, shape (h, w), uint16
        The mosaic's ``source`` layer.
    transform : Affine
        The mosaic's transform.
    models : list of (model, params)
        The adjusted models (:func:`geocoder.mosaic.load_models`).
    truths : list of callables
        Per block scene, its true mapping scene pixel -> truth-grid pixel.
    shapes : list of (rows, cols)
    heights : ndarray, shape (h, w), optional
        The mosaic's ``height`` layer (a mosaic made with a DEM); 0 without.

    Returns
    -------
    ndarray, shape (n,)
        The mismatch at every seam pixel (truth-grid pixels).
    """
    from ..geometry import pixel_to_world
    from .seams import seam_pairs

    r, c, a, b = seam_pairs(source)
    if r.size == 0:
        return np.zeros(0)
    ex, ny = pixel_to_world(transform, c.astype(np.float64), r.astype(np.float64))
    ground = np.column_stack([ex, ny, np.zeros(ex.size) if heights is None else heights[r, c]])
    where = np.full((2, r.size, 2), np.nan)
    for n, ((model, params), truth) in enumerate(zip(models, truths)):
        for side, lab in enumerate((a, b)):
            sel = lab == n
            if sel.any():
                xy = model.project(params, ground[sel])
                tx, ty = truth(xy[:, 0], xy[:, 1])
                where[side, sel] = np.column_stack([tx, ty])
    return np.hypot(*(where[0] - where[1]).T)
