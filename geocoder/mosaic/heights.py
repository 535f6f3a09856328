"""Ground heights of a mosaic: a DEM in the reference's CRS, sampled bilinearly from Zarr windows.

The DEM is ingested once into the job (reprojected to the reference's CRS when it has
another), and every caller reads only the windows its points need: an output tile its
window, the block adjustment its points grouped by DEM tile.
"""

from __future__ import annotations

import numpy as np
from affine import Affine

from ..geometry import world_to_pixel
from ..scene import WindowReader

__all__ = ["MapDEM", "ref_to_scene_prior"]


class MapDEM:
    """Heights of map points from an ingested DEM (pickleable; reads windows on demand).

    Parameters
    ----------
    store : str
        Zarr store of the DEM (``geocoder ingest`` layout), in the mosaic's CRS.
    transform : Affine
        The DEM's transform.
    tile : int
        Points are read one DEM tile at a time.

    Notes
    -----
    Points outside the DEM take the height of its nearest edge pixel; nodata counts as 0.
    """

    def __init__(self, store: str, transform: Affine, tile: int = 512) -> None:
        self.reader = WindowReader(store)
        self.transform = transform
        self.tile = int(tile)

    def __call__(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Bilinear heights (m) at map points ``(e, n)``, shaped like ``e``.

        Parameters
        ----------
        e, n : ndarray
            Map coordinates in the mosaic's CRS.

        Returns
        -------
        ndarray
        """
        e, n = np.broadcast_arrays(np.asarray(e, dtype=np.float64), np.asarray(n, dtype=np.float64))
        h, w = self.reader.shape[1:]
        px, py = world_to_pixel(self.transform, e.ravel(), n.ravel())
        px = np.clip(np.nan_to_num(px, nan=0.0), 0, w - 1)
        py = np.clip(np.nan_to_num(py, nan=0.0), 0, h - 1)
        out = np.empty(px.size)
        key = np.floor(py / self.tile) * (w // self.tile + 1) + np.floor(px / self.tile)
        for k in np.unique(key):
            sel = key == k
            out[sel] = self.reader.sample(px[sel], py[sel], method="bilinear")[0]
        return np.nan_to_num(out, nan=0.0).reshape(e.shape)


def ref_to_scene_prior(model, params: np.ndarray, transform: Affine, ref_shape: tuple[int, int],
                       scene_shape: tuple[int, int], height=None, *, samples: int = 64) -> np.ndarray | None:
    """Affine reference pixel -> scene pixel (2x3) from a scene's sensor model as delivered.

    A grid of ``samples x samples`` reference pixels (at the DEM's heights) is projected into
    the scene; the affine is fitted to those that land inside it. The start of the scene's
    coarse alignment on the reference (its footprint from its RPC or line scanner).

    Parameters
    ----------
    model : SensorModel
        Map ground -> scene pixel.
    params : ndarray
    transform : Affine
        The reference's transform.
    ref_shape, scene_shape : (rows, cols)
    height : callable, optional
        ``height(E, N)``; 0 without it.
    samples : int

    Returns
    -------
    ndarray, shape (2, 3), or None
        None when fewer than 10 samples land in the scene (it is then searched blind).
    """
    from ..geometry import pixel_to_world

    rh, rw = ref_shape
    ry, rx = np.meshgrid(np.linspace(0, rh - 1, samples), np.linspace(0, rw - 1, samples), indexing="ij")
    ex, ny = pixel_to_world(transform, rx.ravel(), ry.ravel())
    hz = np.zeros(ex.size) if height is None else height(ex, ny)
    xy = model.project(params, np.column_stack([ex, ny, hz]))
    h, w = scene_shape
    inside = np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
    if inside.sum() < 10:
        return None
    design = np.column_stack([rx.ravel()[inside], ry.ravel()[inside], np.ones(int(inside.sum()))])
    return np.linalg.lstsq(design, xy[inside], rcond=None)[0].T
