"""Coarse alignment of two scenes: overviews by dask, prior from the georeference."""

from __future__ import annotations

import math
from concurrent.futures import Future

import dask
import numpy as np
import xarray as xr
from rasterio.warp import transform as reproject_points

from ..errors import GeocoderError
from ..match.coarse import CoarseAlignment, align_overviews
from ..runtime import current_client
from ..scene import pixel_to_world, scene_transform, world_to_pixel


def overview(image: xr.DataArray, factor: int) -> xr.DataArray:
    """Lazy block mean (NaN-aware) of a 2-D ``(y, x)`` image over ``factor`` squares."""
    if factor <= 1:
        return image
    return image.coarsen(y=factor, x=factor, boundary="trim").mean()  # NaN-aware by default for floats


def overview_factor(base: xr.DataArray, dist: xr.DataArray, max_size: int = 512) -> int:
    """The pyramid factor of the coarse alignment: the overviews' larger side at most ``max_size``."""
    largest = max(base.sizes["y"], base.sizes["x"], dist.sizes["y"], dist.sizes["x"])
    return max(1, math.ceil(largest / max_size))


def georeference_prior(base: xr.DataArray, dist: xr.DataArray) -> np.ndarray | None:
    """Affine base pixel -> distorted pixel implied by both georeferences (or None).

    With different CRSs a 5 x 5 grid of base pixels is reprojected and an affine fitted.
    """
    tb, td = scene_transform(base), scene_transform(dist)
    if tb is None or td is None:
        return None
    h, w = base.sizes["y"], base.sizes["x"]
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5))
    wx, wy = pixel_to_world(tb, gx.ravel(), gy.ravel())
    if base.rio.crs != dist.rio.crs:
        wx, wy = (np.asarray(v) for v in reproject_points(base.rio.crs, dist.rio.crs, wx, wy))
    dx, dy = world_to_pixel(td, wx, wy)
    design = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
    coef = np.linalg.lstsq(design, np.stack([dx, dy], axis=1), rcond=None)[0]
    return coef.T


def coarse_alignment(
    base: xr.DataArray,
    dist: xr.DataArray,
    *,
    band: int = 0,
    dist_band: int | None = None,
    max_size: int = 512,
    use_georeference: bool = True,
    prior: np.ndarray | None = None,
) -> CoarseAlignment:
    """Coarse affine base pixel -> distorted pixel, found automatically.

    Parameters
    ----------
    base, dist : xarray.DataArray
        Scenes from :func:`geocoder.open_scene`.
    band, dist_band : int
        0-based band used for matching in each scene.
    max_size : int
        Largest side of the overviews the alignment runs on.
    use_georeference : bool
        Use the georeference as the prior when both scenes have one.
    prior : ndarray (2x3), optional
        A known approximate affine base pixel -> distorted pixel (e.g. both scenes already
        placed on a reference); it takes the georeference's place.
    """
    return submit_coarse_alignment(base, dist, band=band, dist_band=dist_band, max_size=max_size,
                                   use_georeference=use_georeference, prior=prior).result()


class PendingAlignment:
    """A coarse alignment computing on the cluster (:func:`submit_coarse_alignment`)."""

    def __init__(self, future) -> None:
        self._future = future

    def result(self) -> CoarseAlignment:
        """Wait for the alignment.

        Returns
        -------
        CoarseAlignment

        Raises
        ------
        GeocoderError
            Why the scenes could not be aligned.
        """
        value = self._future.result()
        if isinstance(value, GeocoderError):
            raise value
        return value

    def cancel(self) -> None:
        """Stop waiting: the cluster may drop the work (quietly, even if the cluster is gone)."""
        try:
            self._future.cancel()
        except Exception:  # noqa: BLE001 - a lost scheduler or closed client: nothing left to cancel
            pass


def submit_coarse_alignment(
    base: xr.DataArray,
    dist: xr.DataArray,
    *,
    band: int = 0,
    dist_band: int | None = None,
    max_size: int = 512,
    use_georeference: bool = True,
    prior: np.ndarray | None = None,
    overviews: tuple[np.ndarray, np.ndarray] | None = None,
) -> PendingAlignment:
    """:func:`coarse_alignment` started on the cluster; the caller goes on meanwhile.

    Parameters and result as :func:`coarse_alignment` (through
    :meth:`PendingAlignment.result`). ``overviews``: the two scenes' overviews at
    :func:`overview_factor` when the caller has them already (e.g. made while the scenes were
    ingested), else they are made from the scenes. Without a distributed client the alignment
    is computed before this returns.
    """
    dist_band = band if dist_band is None else dist_band
    factor = overview_factor(base, dist, max_size)
    if prior is None and use_georeference:
        prior = georeference_prior(base, dist)
    # one graph: the overviews and the alignment on them run on the cluster, not the client
    ob, od = overviews or (overview(s.isel(band=b), factor).data for s, b in ((base, band), (dist, dist_band)))
    task = dask.delayed(_align, pure=True)(ob, od, factor, prior)
    client = current_client()
    if client is not None:
        # ahead of the interest points submitted after it: its overviews are small, and the
        # alignment (one task) then runs on one worker while the others find the points
        return PendingAlignment(client.compute(task, priority=1))
    done = Future()
    done.set_result(task.compute())
    return PendingAlignment(done)


def _align(ob: np.ndarray, od: np.ndarray, factor: int, prior: np.ndarray | None) -> CoarseAlignment | GeocoderError:
    """The alignment, or the error that says why there is none (returned: not a failed task in the worker's log)."""
    try:
        return align_overviews(np.asarray(ob, dtype=np.float64), np.asarray(od, dtype=np.float64), factor, prior=prior)
    except GeocoderError as exc:
        return exc
