"""The mosaic's output grid: its pixels -> the reference's map coordinates, where the scenes' models live.

By default the output grid is the reference's pixel grid: an :class:`affine.Affine` in the
reference's CRS (:func:`geocoder.geometry.pixel_to_world`). ``resolution=`` gives another
pixel size in that CRS: still an affine. ``crs=`` gives another CRS: a :class:`Reprojected`
grid, whose pixels are mapped to the reference's CRS through pyproj exactly, point by point
(about 0.05 s per million points; no interpolation error). Every function here takes either.

Output grids other than the reference's are north-up with square pixels of the resolution,
aligned to its multiples (pixel edges at ``k * resolution``, as ``gdalwarp -tap``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from affine import Affine

from ..geometry import pixel_to_world, world_to_pixel

__all__ = ["Reprojected", "aligned_grid", "from_map", "linear", "native_resolution", "other_grid", "reproject_points", "to_map"]


@dataclass(frozen=True)
class Reprojected:
    """An output grid in another CRS than the reference's.

    Attributes
    ----------
    transform : affine.Affine
        The grid's GDAL transform (pixel corners), in ``crs``.
    crs : str
        The grid's CRS (WKT).
    ref_crs : str
        The reference's CRS (WKT): the scenes' models map its coordinates.
    """

    transform: Affine
    crs: str
    ref_crs: str


@functools.lru_cache(maxsize=16)
def _transformer(src: str, dst: str):
    from pyproj import Transformer

    return Transformer.from_crs(src, dst, always_xy=True)


def reproject_points(src: str, dst: str, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates ``x, y`` of CRS ``src`` in CRS ``dst`` (WKT or anything pyproj accepts), shape kept."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    u, v = _transformer(src, dst).transform(x.ravel(), y.ravel())
    return np.asarray(u).reshape(x.shape), np.asarray(v).reshape(y.shape)


def to_map(grid: Affine | Reprojected, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference map coordinates of output pixel centres ``(x=col, y=row)``.

    Parameters
    ----------
    grid : Affine or Reprojected
        The output grid (an affine: the reference's CRS).
    x, y : ndarray
        Output pixel coordinates, pixel centres at integers.

    Returns
    -------
    e, n : ndarray
        Easting and northing in the reference's CRS, the shape of ``x``.
    """
    if isinstance(grid, Affine):
        return pixel_to_world(grid, x, y)
    ex, ny = pixel_to_world(grid.transform, x, y)
    return reproject_points(grid.crs, grid.ref_crs, ex, ny)


def from_map(grid: Affine | Reprojected, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Output pixel coordinates ``(x=col, y=row)`` of reference map coordinates (inverse of :func:`to_map`).

    Parameters
    ----------
    grid : Affine or Reprojected
    e, n : ndarray
        Map coordinates in the reference's CRS.

    Returns
    -------
    x, y : ndarray
    """
    if isinstance(grid, Affine):
        return world_to_pixel(grid, e, n)
    return world_to_pixel(grid.transform, *reproject_points(grid.ref_crs, grid.crs, e, n))


def linear(grid: Affine | Reprojected, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``d(E, N) / d(col, row)`` of :func:`to_map`: ``(2, 2)`` for an affine, else ``(n, 2, 2)`` at every point.

    Parameters
    ----------
    grid : Affine or Reprojected
    x, y : ndarray, shape (n,)
        Output pixel coordinates.

    Returns
    -------
    ndarray
        The Jacobian (central differences over one pixel for a :class:`Reprojected` grid).
    """
    if isinstance(grid, Affine):
        return np.array([[grid.a, grid.b], [grid.d, grid.e]])
    x, y = np.ravel(x).astype(np.float64), np.ravel(y).astype(np.float64)
    d = np.array([-0.5, 0.5])
    e, n = to_map(grid, np.concatenate([x[None] + d[:, None], np.repeat(x[None], 2, 0)]).ravel(),
                  np.concatenate([np.repeat(y[None], 2, 0), y[None] + d[:, None]]).ravel())
    e, n = e.reshape(4, -1), n.reshape(4, -1)
    return np.stack([np.stack([e[1] - e[0], e[3] - e[2]], -1), np.stack([n[1] - n[0], n[3] - n[2]], -1)], 1)


def native_resolution(ref_transform: Affine, ref_crs: str, crs: str, e: float, n: float) -> float:
    """The reference's pixel size expressed in ``crs`` at map point ``(e, n)`` of the reference.

    The square root of the area of one reference pixel there, in ``crs`` units: what the
    output's pixel is when ``crs`` is given without ``resolution``.
    """
    size = math.sqrt(abs(ref_transform.determinant))
    u, v = reproject_points(ref_crs, crs, np.array([e, e + size, e]), np.array([n, n, n + size]))
    return float(math.sqrt(abs((u[1] - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (v[1] - v[0]))))


def aligned_grid(x: np.ndarray, y: np.ndarray, resolution: float) -> tuple[Affine, tuple[int, int]]:
    """The north-up grid of square ``resolution`` pixels, edges at its multiples, whose pixel
    centres cover the points ``(x, y)`` (map coordinates of the grid's CRS).

    Parameters
    ----------
    x, y : ndarray
        Map coordinates (e.g. the scenes' footprints).
    resolution : float
        Pixel size, in the CRS's units.

    Returns
    -------
    transform : affine.Affine
        GDAL transform (pixel corners).
    shape : (rows, cols)
    """
    cols = np.asarray(x, dtype=np.float64) / resolution - 0.5  # pixel index of the global grid, centres at integers
    rows = -np.asarray(y, dtype=np.float64) / resolution - 0.5
    c0, c1 = int(np.floor(cols.min())), int(np.ceil(cols.max())) + 1
    r0, r1 = int(np.floor(rows.min())), int(np.ceil(rows.max())) + 1
    return Affine(resolution, 0.0, c0 * resolution, 0.0, -resolution, -r0 * resolution), (r1 - r0, c1 - c0)


def other_grid(ref_transform: Affine, ref_crs: str, e: np.ndarray, n: np.ndarray, *, resolution: float | None,
               crs: str | None) -> tuple[Affine, tuple[int, int], Affine | Reprojected]:
    """The output grid of ``resolution`` in ``crs`` covering reference map points ``(e, n)``.

    Parameters
    ----------
    ref_transform : affine.Affine
        The reference's transform.
    ref_crs : str
        The reference's CRS (WKT).
    e, n : ndarray
        The points to cover (the scenes' footprints), reference map coordinates.
    resolution : float, optional
        Pixel size in ``crs`` units; default :func:`native_resolution` at the points' centre.
    crs : str, optional
        The output's CRS (WKT); None: the reference's.

    Returns
    -------
    transform : affine.Affine
        The grid's transform, in ``crs`` (:func:`aligned_grid`).
    shape : (rows, cols)
    grid : Affine or Reprojected
        What :func:`to_map` takes: ``transform`` itself in the reference's CRS, else a
        :class:`Reprojected`.
    """
    if crs is None:
        u, v = np.asarray(e, dtype=np.float64), np.asarray(n, dtype=np.float64)
    else:
        u, v = reproject_points(ref_crs, crs, e, n)
    if resolution is None:
        resolution = native_resolution(ref_transform, ref_crs, crs or ref_crs, float(np.mean(e)), float(np.mean(n)))
    transform, shape = aligned_grid(u, v, resolution)
    return transform, shape, transform if crs is None else Reprojected(transform, crs, ref_crs)
