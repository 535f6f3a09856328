"""Accuracy of a mosaic against known truth (synthetic blocks): per output pixel and along seams."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import xarray as xr
from affine import Affine

from ..geometry import world_to_pixel


def mosaic_errors(ds: xr.Dataset, truths: Sequence[Callable], shapes: Sequence[tuple[int, int]],
                  truth_transform: Affine, positions: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
                  ) -> tuple[np.ndarray, np.ndarray]:
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
    positions : sequence of (x, y) arrays, optional
        Where the mosaic sampled every output pixel in each scene
        (:func:`geocoder.mosaic.scene_positions`, needed for a densely refined mosaic);
        default: the scenes' adjusted models.

    Returns
    -------
    own : ndarray, shape (y, x)
        Error of every output pixel in the scene it comes from (NaN where none).
    seams : ndarray, shape (n,)
        For every output pixel seen by two scenes, the distance between where each puts it.

    Raises
    ------
    ValueError
        If the mosaic's grid is in another CRS than its models (``crs=``): its coordinates
        are not those the truths and models map.
    """
    from ..mosaic import load_models

    if ds.attrs.get("models_crs"):
        raise ValueError("the mosaic's grid is in another CRS than its models (mosaic(crs=...)); "
                         "mosaic_errors needs a mosaic on the models' CRS")

    models = load_models(ds)
    ex, ny = np.meshgrid(ds.x.values, ds.y.values)
    gx, gy = world_to_pixel(truth_transform, ex, ny)
    ground = np.column_stack([ex.ravel(), ny.ravel(), np.zeros(ex.size)])
    # per scene, only the pixels it sees (flat indices, true positions): memory grows with the
    # scenes' areas, not with their number times the mosaic's
    seen = []
    for n, ((model, params), truth, (h, w)) in enumerate(zip(models, truths, shapes)):
        if positions is not None:
            x, y = positions[n]
        else:
            xy = model.project(params, ground)
            x, y = xy[:, 0].reshape(ex.shape), xy[:, 1].reshape(ex.shape)
        idx = np.flatnonzero((x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1))
        tx, ty = truth(x.ravel()[idx], y.ravel()[idx])
        seen.append((idx, tx + 1j * ty))
    src = ds.source.values.ravel()
    own = np.full(src.shape, np.nan)
    target = gx.ravel() + 1j * gy.ravel()
    for n, (idx, p) in enumerate(seen):
        m = src[idx] == n
        own[idx[m]] = np.abs(p[m] - target[idx[m]])
    own = own.reshape(ex.shape)
    seams = []
    for i in range(len(seen)):
        for j in range(i + 1, len(seen)):
            _, a, b = np.intersect1d(seen[i][0], seen[j][0], assume_unique=True, return_indices=True)
            if a.size:
                seams.append(np.abs(seen[i][1][a] - seen[j][1][b]))
    return own, np.concatenate(seams) if seams else np.zeros(0)
