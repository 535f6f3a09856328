"""A mosaic without a reference orthoimage: the block's frame and datum from the scenes' georeferences.

Without ``reference``, the scenes that carry a georeference (CRS and north-up transform, e.g.
a GeoTIFF's, all in one CRS; at least one) set the frame: a *virtual reference*, a north-up
pixel grid in that CRS (the finest scene pixel, bounds = the union of their footprints) that
has no image, only the frame the rest of the mosaic works in (its pixels are what the
adjustment, the output grid and the summary call reference pixels). Each such scene is placed
by its georeference (scene pixel -> virtual reference pixel, exactly); a scene without one is
placed by matching it against the placed scenes it overlaps
(:func:`geocoder.mosaic.placement.place_by_neighbours`); the tie points between overlapping
scenes tie the block together; and the control comes from the ``control`` CSV or, without
one, from the georeferences themselves (:func:`georeference_control`). So a block without
control lands where its georeferences say on average, its scenes made to agree by the ties.
"""

from __future__ import annotations

import math

import dask.array as da
import numpy as np
import xarray as xr
from affine import Affine

from ..errors import InputError
from ..geometry import pixel_to_world, world_to_pixel
from ..kernels.polynomial import PolyMap, fit_polymap
from ..scene import scene_transform
from .block import Matches

#: Default standard deviation (scene pixels) of a georeference's pseudo-control points.
GEOREFERENCE_SIGMA_PX = 5.0
#: Pseudo-control points per scene side (a grid of n x n).
GEOREFERENCE_POINTS = 5
#: Standard deviation (px) of a pseudo-control point's image observation: the pixel is exact.
IMAGE_SIGMA_PX = 0.05

VIRTUAL_SOURCE = "(none: the scenes' georeferences)"


def _checked(scenes: list[xr.DataArray]) -> tuple[object, list[Affine | None]]:
    """The CRS of the georeferenced scenes and every scene's transform (None: not georeferenced);
    refused, naming a scene, when none is georeferenced or one is in another CRS than the first."""
    crs, transforms = None, []
    for s in scenes:
        t = scene_transform(s)
        if t is not None and crs is None:
            crs = s.rio.crs
        elif t is not None and s.rio.crs != crs:
            raise InputError(s.attrs.get("source", "scene"), f"is in another CRS ({s.rio.crs}) than the first "
                             f"georeferenced scene ({crs}): without a reference orthoimage the scenes must share one")
        transforms.append(t)
    if crs is None:
        raise InputError(scenes[0].attrs.get("source", "scene"), "has no georeference (CRS and transform), nor has any "
                         "other scene: without a reference orthoimage at least one scene needs one (or give --reference)")
    return crs, transforms


def virtual_reference(scenes: list[xr.DataArray], tile: int) -> xr.DataArray:
    """The frame a block without a reference is adjusted in: an image-less scene in the scenes' CRS.

    Parameters
    ----------
    scenes : list of xarray.DataArray
        Opened scenes (:func:`geocoder.scene.open_scene`); those georeferenced, in one CRS, set the
        frame (the others are placed through their neighbours later).
    tile : int
        Chunk size of the (never computed) placeholder array.

    Returns
    -------
    xarray.DataArray
        ``(1, H, W)`` of a lazy constant, north-up, the finest scene pixel, covering every
        scene's footprint; ``attrs``: ``source`` (:data:`VIRTUAL_SOURCE`), ``georeferenced``
        and ``virtual`` (True). Nothing may read its pixels.

    Raises
    ------
    InputError
        No scene georeferenced, or one in another CRS than the first.
    """
    crs, transforms = _checked(scenes)
    pixel = min(math.sqrt(abs(t.determinant)) for t in transforms if t is not None)
    corners = []
    for s, t in zip(scenes, transforms):
        if t is None:
            continue
        h, w = s.sizes["y"], s.sizes["x"]
        corners.append(np.column_stack(t * (np.array([0.0, w, 0.0, w]), np.array([0.0, 0.0, h, h]))))  # pixel corners
    pts = np.concatenate(corners)
    x0, y1 = math.floor(pts[:, 0].min() / pixel) * pixel, math.ceil(pts[:, 1].max() / pixel) * pixel
    width = int(math.ceil((pts[:, 0].max() - x0) / pixel))
    height = int(math.ceil((y1 - pts[:, 1].min()) / pixel))
    transform = Affine(pixel, 0.0, x0, 0.0, -pixel, y1)
    xs, _ = pixel_to_world(transform, np.arange(width), np.zeros(width))
    _, ys = pixel_to_world(transform, np.zeros(height), np.arange(height))
    ref = xr.DataArray(da.zeros((1, height, width), dtype=np.float32, chunks=(1, tile, tile)), dims=("band", "y", "x"),
                       coords={"band": [1], "y": ys, "x": xs})
    ref = ref.rio.write_crs(crs).rio.write_transform(transform)
    ref.attrs = {"source": VIRTUAL_SOURCE, "georeferenced": True, "virtual": True}
    return ref


def _grid(shape: tuple[int, int], n: int) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    c, r = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    return c.ravel(), r.ravel()


def georeference_mappings(scene: xr.DataArray, ref: xr.DataArray, order: int) -> tuple[PolyMap, PolyMap]:
    """Scene pixel -> reference pixel and back, from the scene's georeference (exact: both are affine).

    Parameters
    ----------
    scene : xarray.DataArray
        A georeferenced scene in ``ref``'s CRS.
    ref : xarray.DataArray
        The frame (:func:`virtual_reference`).
    order : int
        Order of the polynomials (the block's); an affine is represented exactly by any order >= 1.

    Returns
    -------
    to_ref, ref_to : PolyMap
    """
    x, y = _grid((scene.sizes["y"], scene.sizes["x"]), 9)
    rx, ry = world_to_pixel(scene_transform(ref), *pixel_to_world(scene_transform(scene), x, y))
    return fit_polymap(x, y, rx, ry, order=order), fit_polymap(rx, ry, x, y, order=order)


def georeference_control(k: int, scene: xr.DataArray, sigma: float, points: int = GEOREFERENCE_POINTS) -> Matches:
    """Pseudo-control of scene ``k`` from its georeference: a ``points x points`` grid of scene
    pixels whose map positions are the georeference's.

    ``sigma`` (scene pixels) is the error of the georeference as a whole: one shift (and
    rotation, scale) of the scene, not an error of every point on its own. So the points
    together carry the weight of one position known to ``sigma``: each is known to
    ``sigma * points`` (a grid of ``points^2`` independent points would be as sure of the
    scene's position as a single one known to ``sigma``), and where the tie points determine
    the scenes' shapes and relative positions, the georeferences set the block's datum.
    Measured on the 2 x 2 test block (``tests/test_mosaic_georef.py``: georeferences 3.3-7.2 px
    RMS off, a rotation of 1-3 degrees left out): with ``sigma`` 5 px, points of 5 px each gave
    the mosaic 3.0 px RMS error, of 25 px each 1.8 px (``sigma`` 1 px: 3.0, 20 px: 2.3).

    The uncertainty is the ground point's (``ground_sigma``, map units), not the image
    observation's (:data:`IMAGE_SIGMA_PX`): a georeference's error is no blunder of a match,
    and the robust re-weighting of the image observations must not reject it.
    """
    x, y = _grid((scene.sizes["y"], scene.sizes["x"]), points)
    t = scene_transform(scene)
    ex, ny = pixel_to_world(t, x, y)
    return Matches(-1, k, np.column_stack([ex, ny]), np.column_stack([x, y]), np.full((x.size, 2), IMAGE_SIGMA_PX),
                   ground_sigma=np.full(x.size, float(sigma) * points * math.sqrt(abs(t.determinant))))


__all__ = ["GEOREFERENCE_POINTS", "GEOREFERENCE_SIGMA_PX", "VIRTUAL_SOURCE", "georeference_control",
           "georeference_mappings", "virtual_reference"]
