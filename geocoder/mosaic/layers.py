"""Per-pixel layers of a mosaic: ``status`` (what a pixel's position rests on) and its precision.

For every output pixel the mosaic samples its ``source`` scene at a position from that scene's
adjusted model, or from its dense field where the field matched or filled the pixel
(:func:`geocoder.mosaic.output.scene_xy`). The layers say which, and how precise that position is:

* ``status`` uses :class:`geocoder.status.Status`: ``MATCHED`` and ``FILLED`` where the dense
  field gave the position, ``BLUNDER`` and ``NO_TEXTURE`` where the dense matcher rejected or
  could not match the pixel (its position is then the model's, as in ``register``), ``MODEL``
  where the scene has no field there, ``OUTSIDE`` where no scene covers the pixel.
* ``sigma_x``, ``sigma_y``: standard deviations of the pixel's position along the output's
  columns and rows, in output pixels. A model position's covariance is the adjustment's
  parameter covariance ``C`` propagated to the pixel, ``J C J^T`` (``J`` the model's
  parameter Jacobian, scene pixels), plus the scene's unmodelled variance (the mean square
  of its observations' residuals, per axis; :func:`scene_uncertainty`); a matched pixel's is
  the dense match's ``sigma_x``, ``sigma_y`` (the least-squares match's claim: optimistic
  where the field varies inside the template, as the README's error analysis shows); a
  filled pixel (a correction carried from matches along its row or column, whose error no
  match measured) gets the model's. Scene-pixel covariances are taken to output pixels
  through the inverse of the model's Jacobian ``d(scene pixel) / d(output pixel)``.

The model's covariance and Jacobian are evaluated on nodes every :data:`NODE_STEP` output
pixels of the whole grid (so a pixel's value does not depend on the tile that computes it)
and interpolated bilinearly: both are smooth over a scene. Pure numpy, one output window at a time.
"""

from __future__ import annotations

import numpy as np
from affine import Affine

from ..status import Status, positioned
from .outgrid import Reprojected, linear, to_map

__all__ = ["NODE_STEP", "field_layers", "model_layers", "pixel_sigma", "scene_uncertainty"]

#: Spacing (output pixels) of the grid nodes where a model's covariance is evaluated.
NODE_STEP = 8


def _nodes(a: int, b: int, step: int) -> np.ndarray:
    """Nodes (multiples of ``step``) covering the pixels ``a .. b - 1``, at least two."""
    lo = (a // step) * step
    hi = max(-(-(b - 1) // step) * step, lo + step)
    return np.arange(lo, hi + 1, step)


def _bilinear(values: np.ndarray, nodes_r: np.ndarray, nodes_c: np.ndarray, rows: np.ndarray, cols: np.ndarray,
              step: int) -> np.ndarray:
    """``values (..., nr, nc)`` on uniform nodes, interpolated at every ``rows x cols`` pixel."""
    a = np.minimum((rows - nodes_r[0]) // step, nodes_r.size - 2)
    b = np.minimum((cols - nodes_c[0]) // step, nodes_c.size - 2)
    fa = ((rows - nodes_r[a]) / step)[:, None]
    fb = ((cols - nodes_c[b]) / step)[None, :]
    A, B = a[:, None], b[None, :]
    return ((1 - fa) * ((1 - fb) * values[..., A, B] + fb * values[..., A, B + 1])
            + fa * ((1 - fb) * values[..., A + 1, B] + fb * values[..., A + 1, B + 1]))


def model_layers(model, params: np.ndarray, cov: np.ndarray | None, transform: Affine | Reprojected,
                 window: tuple[int, int, int, int], dem=None, unmodelled: np.ndarray | None = None, *,
                 step: int = NODE_STEP) -> tuple[np.ndarray, np.ndarray]:
    """Covariance of a scene's model position, and the Jacobian's inverse, at every pixel of a window.

    Parameters
    ----------
    model : SensorModel
        The scene's adjusted model (map ``E, N, h`` -> scene pixel).
    params : ndarray
        Its adjusted parameters.
    cov : ndarray, shape (n, n) or None
        Their covariance (``sigma0**2`` times the block of the inverse normal matrix); None:
        unknown (NaN covariances).
    transform : affine.Affine or Reprojected
        The output grid (:mod:`geocoder.mosaic.outgrid`): its transform (pixel corners), or a
        grid in another CRS than the models'.
    window : tuple of int
        ``row0, row1, col0, col1`` in output pixels.
    dem : callable, optional
        ``dem(E, N) -> h``; heights 0 without it.
    unmodelled : ndarray, shape (2,), optional
        The scene's unmodelled variance along its columns and rows (scene pixels squared),
        added to the propagated one (:func:`scene_uncertainty`).
    step : int
        Node spacing in output pixels.

    Returns
    -------
    cov_out : ndarray, shape (3, rows, cols)
        ``var_x, cov_xy, var_y`` of the model's position in output pixels squared.
    inverse : ndarray, shape (2, 2, rows, cols)
        ``d(output pixel) / d(scene pixel)`` (over the DEM's slope, with one), to take a
        scene-pixel covariance to output pixels.
    """
    r0, r1, c0, c1 = window
    nr, nc = _nodes(r0, r1, step), _nodes(c0, c1, step)
    cols, rows = np.meshgrid(nc.astype(np.float64), nr.astype(np.float64))
    e, n = to_map(transform, cols.ravel(), rows.ravel())
    m = e.size
    slope = np.zeros((m, 2))
    if dem is None:
        h = np.zeros(m)
    else:  # the heights at the nodes and half a pixel either side along columns and rows
        dc, dr = np.array([0.0, -0.5, 0.5, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, -0.5, 0.5])
        ee, nn = to_map(transform, cols.ravel()[None] + dc[:, None], rows.ravel()[None] + dr[:, None])
        hh = np.asarray(dem(ee.ravel(), nn.ravel()), dtype=np.float64).reshape(5, m)
        h, slope = hh[0], np.column_stack([hh[2] - hh[1], hh[4] - hh[3]])
    jp, jg = model.jacobians(params, np.column_stack([e, n, h]))
    # d(scene) / d(output col, row) = d(scene) / d(E, N) . d(E, N) / d(col, row) + d(scene) / dh . dh / d(col, row)
    jac = jg[:, :, :2] @ linear(transform, cols.ravel(), rows.ravel())
    jac = jac + jg[:, :, 2:3] * slope[:, None, :]
    with np.errstate(invalid="ignore"):
        inv = np.linalg.inv(np.where(np.isfinite(jac), jac, np.nan))
    if cov is None or not np.all(np.isfinite(cov)):
        cs = np.full((e.size, 2, 2), np.nan)
    else:
        cs = jp @ cov @ jp.transpose(0, 2, 1)
    if unmodelled is not None:
        cs = cs + np.diag(np.asarray(unmodelled, dtype=np.float64))
    co = inv @ cs @ inv.transpose(0, 2, 1)
    stacked = np.concatenate([co[:, [0, 0, 1], [0, 1, 1]].T, inv.reshape(-1, 4).T]).reshape(7, nr.size, nc.size)
    out = _bilinear(stacked, nr, nc, np.arange(r0, r1), np.arange(c0, c1), step)
    return out[:3], out[3:].reshape(2, 2, r1 - r0, c1 - c0)


def scene_uncertainty(problem, result, scenes: int) -> tuple[list | None, np.ndarray]:
    """Every block scene's parameter covariance and unmodelled variance, for :func:`model_layers`.

    Parameters
    ----------
    problem : geocoder.adjust.solver.Problem
        The block (:func:`geocoder.mosaic.block.build_problem`).
    result : geocoder.adjust.solver.AdjustResult
        Its adjustment.
    scenes : int
        Number of block scenes (frames).

    Returns
    -------
    covs : list of ndarray or None
        Per scene, ``max(sigma0, 1)**2`` times its block of the inverse normal matrix: the
        a-posteriori covariance where the residuals exceed the matching precision, the
        a-priori one where they do not (a sigma0 below one would shrink the covariance
        below what correlated matching errors leave; measured on the simulated blocks).
        None when the adjustment gave no covariances.
    unmodelled : ndarray, shape (scenes, 2)
        Per scene and axis (scene columns, rows), the mean squared residual of its kept
        observations (scene pixels squared): what its model misses where it was observed
        (turbulence, a polynomial too low), matching noise included; 0 without observations.
    """
    covs = None
    if result.param_cov is not None:
        s0 = float(result.sigma0) if np.isfinite(result.sigma0) and result.sigma0 > 0 else 1.0
        covs = [np.asarray(c) * max(1.0, 1.0 / s0**2) for c in result.param_cov]
    unmodelled = np.zeros((scenes, 2))
    for n in range(scenes):
        kept = (problem.obs_frame == n) & result.obs_active
        if kept.any():
            unmodelled[n] = np.mean(np.square(result.residuals[kept]), axis=0)
    return covs, unmodelled


def sample_field(located: dict, rx: np.ndarray, ry: np.ndarray) -> tuple[np.ndarray, ...]:
    """A scene's dense field at fractional reference pixels (an output grid of another pixel or CRS).

    ``dx, dy`` are interpolated bilinearly where the four samples around a point are usable
    (matched, filled or estimated), taken from the nearest sample where only it is; the
    status and the sigmas are the nearest sample's. Only the window of the field the points
    span is read.

    Parameters
    ----------
    located : dict
        Where the field is (:func:`geocoder.mosaic.refine.refine_scene`).
    rx, ry : ndarray
        Reference pixel coordinates (column, row; pixel centres at integers).

    Returns
    -------
    dx, dy : ndarray
        Displacement reference pixel -> scene pixel (0 where not ``good``).
    good : ndarray of bool
        Where the field gives the position.
    status : ndarray of uint8
        The nearest sample's status (``OUTSIDE`` beyond the field).
    sigma_x, sigma_y : ndarray of float32
        The nearest sample's (NaN beyond the field).
    """
    import zarr

    fx = np.asarray(rx, dtype=np.float64) - located["col0"]
    fy = np.asarray(ry, dtype=np.float64) - located["row0"]
    h, w = located["shape"]
    dx, dy = np.zeros(fx.shape), np.zeros(fx.shape)
    good = np.zeros(fx.shape, dtype=bool)
    status = np.full(fx.shape, Status.OUTSIDE, dtype=np.uint8)
    sx = np.full(fx.shape, np.nan, dtype=np.float32)
    sy = sx.copy()
    finite = np.isfinite(fx) & np.isfinite(fy)
    if not finite.any():
        return dx, dy, good, status, sx, sy
    a0 = int(np.clip(np.floor(fy[finite].min()), 0, h))
    a1 = int(np.clip(np.floor(fy[finite].max()) + 2, 0, h))
    b0 = int(np.clip(np.floor(fx[finite].min()), 0, w))
    b1 = int(np.clip(np.floor(fx[finite].max()) + 2, 0, w))
    if a0 >= a1 or b0 >= b1:
        return dx, dy, good, status, sx, sy
    g = zarr.open_group(located["store"], mode="r")
    wdx, wdy, wst, wsx, wsy = (np.asarray(g[n][a0:a1, b0:b1]) for n in ("dx", "dy", "status", "sigma_x", "sigma_y"))
    usable = positioned(wst)
    hh, ww = wst.shape

    def at(i, j):
        inside = finite & (i >= 0) & (i < hh) & (j >= 0) & (j < ww)
        return inside, np.where(inside, i, 0), np.where(inside, j, 0)

    fy0, fx0 = np.floor(np.nan_to_num(fy)), np.floor(np.nan_to_num(fx))
    ty, tx = np.nan_to_num(fy) - fy0, np.nan_to_num(fx) - fx0
    i0, j0 = fy0.astype(np.int64) - a0, fx0.astype(np.int64) - b0
    near, ni, nj = at(np.rint(np.nan_to_num(fy)).astype(np.int64) - a0, np.rint(np.nan_to_num(fx)).astype(np.int64) - b0)
    status = np.where(near, wst[ni, nj], status).astype(np.uint8)
    sx = np.where(near, wsx[ni, nj], sx).astype(np.float32)
    sy = np.where(near, wsy[ni, nj], sy).astype(np.float32)
    near_ok = near & usable[ni, nj]
    ok4 = np.ones(fx.shape, dtype=bool)
    vx, vy = np.zeros(fx.shape), np.zeros(fx.shape)
    for di, dj, wt in ((0, 0, (1 - ty) * (1 - tx)), (0, 1, (1 - ty) * tx), (1, 0, ty * (1 - tx)), (1, 1, ty * tx)):
        inside, ii, jj = at(i0 + di, j0 + dj)
        ok4 &= inside & usable[ii, jj]
        vx += wt * np.where(inside, wdx[ii, jj], 0.0)
        vy += wt * np.where(inside, wdy[ii, jj], 0.0)
    dx = np.where(ok4, vx, np.where(near_ok, wdx[ni, nj], 0.0))
    dy = np.where(ok4, vy, np.where(near_ok, wdy[ni, nj], 0.0))
    return dx, dy, ok4 | near_ok, status, sx, sy


def field_layers(located: dict | None, window: tuple[int, int, int, int], origin: tuple[int, int] | Affine,
                 grid: Affine | Reprojected | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Status and matching sigmas of a scene's dense field over an output window.

    Parameters
    ----------
    located : dict or None
        Where the field is (:func:`geocoder.mosaic.refine.refine_scene`: ``store``, ``row0``,
        ``col0``, ``shape``); None: the scene has no field.
    window : tuple of int
        ``row0, row1, col0, col1`` in output pixels.
    origin : tuple of int or Affine
        The output grid's pixel ``(0, 0)`` in reference pixels (``col, row``); or, for an
        output grid of another pixel size or CRS, the reference's transform (every output
        pixel is then mapped through the map to the reference's pixels, :func:`sample_field`).
    grid : Affine or Reprojected, optional
        The output grid (needed with a transform as ``origin``).

    Returns
    -------
    status : ndarray of uint8, shape (rows, cols)
        The field's status; ``MODEL`` where it has none (outside the field, or ``OUTSIDE`` in it).
    sigma_x, sigma_y : ndarray of float32, shape (rows, cols)
        The dense match's standard deviations (scene pixels) where matched, NaN elsewhere.
    """
    import zarr

    r0, r1, c0, c1 = window
    status = np.full((r1 - r0, c1 - c0), Status.MODEL, dtype=np.uint8)
    sx = np.full((r1 - r0, c1 - c0), np.nan, dtype=np.float32)
    sy = sx.copy()
    if located is None:
        return status, sx, sy
    if isinstance(origin, Affine):
        from ..geometry import world_to_pixel

        ys, xs = np.mgrid[r0:r1, c0:c1].astype(np.float64)
        rx, ry = world_to_pixel(origin, *to_map(grid, xs, ys))
        _, _, _, st, sx, sy = sample_field(located, rx, ry)
        return np.where(st == Status.OUTSIDE, Status.MODEL, st).astype(np.uint8), sx, sy
    fr0, fc0 = r0 + origin[1] - located["row0"], c0 + origin[0] - located["col0"]
    a0, a1 = max(fr0, 0), min(fr0 + (r1 - r0), located["shape"][0])
    b0, b1 = max(fc0, 0), min(fc0 + (c1 - c0), located["shape"][1])
    if a0 >= a1 or b0 >= b1:
        return status, sx, sy
    g = zarr.open_group(located["store"], mode="r")
    sl = (slice(a0 - fr0, a1 - fr0), slice(b0 - fc0, b1 - fc0))
    st = np.asarray(g["status"][a0:a1, b0:b1])
    status[sl] = np.where(st == Status.OUTSIDE, Status.MODEL, st)
    sx[sl] = g["sigma_x"][a0:a1, b0:b1]
    sy[sl] = g["sigma_y"][a0:a1, b0:b1]
    return status, sx, sy


def pixel_sigma(status: np.ndarray, cov_model: np.ndarray, inverse: np.ndarray, sigma_x: np.ndarray,
                sigma_y: np.ndarray) -> np.ndarray:
    """Standard deviations ``(2, rows, cols)`` of a scene's positions along the output's columns and rows.

    Parameters
    ----------
    status : ndarray, shape (rows, cols)
        :func:`field_layers`' status.
    cov_model : ndarray, shape (3, rows, cols)
        :func:`model_layers`' covariance (output pixels squared).
    inverse : ndarray, shape (2, 2, rows, cols)
        :func:`model_layers`' ``d(output pixel) / d(scene pixel)``.
    sigma_x, sigma_y : ndarray, shape (rows, cols)
        The dense match's standard deviations (scene pixels), NaN where none.

    Returns
    -------
    ndarray of float32, shape (2, rows, cols)
        The match's at ``MATCHED`` pixels, the model's elsewhere (see the module).
    """
    sx2, sy2 = np.square(sigma_x, dtype=np.float64), np.square(sigma_y, dtype=np.float64)
    dense = np.stack([inverse[0, 0] ** 2 * sx2 + inverse[0, 1] ** 2 * sy2,
                      inverse[1, 0] ** 2 * sx2 + inverse[1, 1] ** 2 * sy2])
    var = np.where(status == Status.MATCHED, dense, cov_model[[0, 2]])
    return np.sqrt(var).astype(np.float32)
