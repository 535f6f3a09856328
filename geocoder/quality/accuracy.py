"""Accuracy of a mosaic against known truth (synthetic blocks): per output pixel and along seams."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import xarray as xr
from affine import Affine

from ..geometry import world_to_pixel


def mosaic_errors(ds: xr.Dataset, truths: Sequence[Callable], shapes: Sequence[tuple[int, int]],
                  truth_transform: Affine) -> tuple[np.ndarray, np.ndarray]:
    """Geometric errors of a mosaic, in output pixels.

    Parameters
    ----------
    ds : xarray.Dataset
        A :func:`geocoder.mosaic.mosaic` result.
    truths : sequence of callables
        For every scene of ``ds.attrs["scenes"]``, its true mapping scene pixel -> pixel of
        the grid ``truth_transform`` describes (e.g. the reference's).
    shapes : sequence of (rows, cols)
        The scenes' sizes.
    truth_transform : Affine
        Transform of the grid the truths map into.

    Returns
    -------
    own : ndarray, shape (y, x)
        Error of every output pixel in the scene it comes from (NaN where none).
    seams : ndarray, shape (n,)
        For every output pixel seen by two scenes, the distance between where each puts it.
    """
    from ..mosaic import load_models

    models = load_models(ds)
    ex, ny = np.meshgrid(ds.x.values, ds.y.values)
    gx, gy = world_to_pixel(truth_transform, ex, ny)
    ground = np.column_stack([ex.ravel(), ny.ravel(), np.zeros(ex.size)])
    pos = []
    for (model, params), truth, (h, w) in zip(models, truths, shapes):
        xy = model.project(params, ground)
        x, y = xy[:, 0].reshape(ex.shape), xy[:, 1].reshape(ex.shape)
        inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        tx, ty = truth(x, y)
        pos.append(np.where(inside, tx, np.nan) + 1j * np.where(inside, ty, np.nan))
    src = ds.source.values
    own = np.full(src.shape, np.nan)
    for n, p in enumerate(pos):
        m = src == n
        own[m] = np.abs(p[m] - (gx[m] + 1j * gy[m]))
    seams = [np.abs(pos[i] - pos[j]) for i in range(len(pos)) for j in range(i + 1, len(pos))]
    return own, np.concatenate([s[np.isfinite(s)] for s in seams]) if seams else np.zeros(0)
