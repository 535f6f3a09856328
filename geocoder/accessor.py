"""The ``.geocoder`` accessor on xarray objects: module functions bound to a DataArray or Dataset.

Every operation exists once, as a function of its module; the accessor only passes the
object it is attached to as the first argument (odc-geo's ``.odc`` and rioxarray's ``.rio``
work the same way). Importing :mod:`geocoder` registers it::

    import geocoder

    base = geocoder.open_scene("base.tif")
    result = base.geocoder.register("distorted.tif", out="out.zarr")   # geocoder.register
    result.geocoder.to_cog("registered.tif", variable="registered")     # geocoder.cog.to_cog
    result.geocoder.summary().status_counts                            # RegisterSummary
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import xarray as xr

if TYPE_CHECKING:  # imported where used: ``import geocoder`` registers the accessors without loading the pipeline
    from .kernels.polynomial import PolyMap
    from .pipeline.register import RegisterSummary

__all__ = ["GeocoderArrayAccessor", "GeocoderDatasetAccessor"]


@xr.register_dataarray_accessor("geocoder")
class GeocoderArrayAccessor:
    """``DataArray.geocoder``: a scene (``(band, y, x)``, as :func:`geocoder.open_scene` returns).

    Parameters
    ----------
    obj : xarray.DataArray
        The scene the accessor is attached to.
    """

    def __init__(self, obj: xr.DataArray) -> None:
        self._obj = obj

    def register(self, distorted: xr.DataArray | str | os.PathLike, **kwargs: Any) -> xr.Dataset:
        """Register ``distorted`` onto this scene's grid: :func:`geocoder.register` with this scene as base.

        Parameters
        ----------
        distorted : xarray.DataArray, str or PathLike
            The scene to register: a path (GeoTIFF/COG/Zarr) or a scene DataArray.
        **kwargs
            Keywords of :func:`geocoder.register` (``out``, ``tile``, ``client``, ``options``, ...).

        Returns
        -------
        xarray.Dataset
            As :func:`geocoder.register`: read back from ``out`` when given, else in memory.

        Notes
        -----
        A DataArray is used as it is: it should be a scene as :func:`geocoder.open_scene`
        returns (dims ``(band, y, x)``, float with NaN as nodata, CRS through rioxarray).
        """
        from .pipeline.register import register

        return register(self._obj, distorted, **kwargs)

    def ingest(self, out: str | os.PathLike, **kwargs: Any) -> xr.DataArray:
        """Write this scene to a Zarr v3 store: :func:`geocoder.ingest`.

        Parameters
        ----------
        out : str or PathLike
            The store to write (path or fsspec URL).
        **kwargs
            Keywords of :func:`geocoder.ingest` (``tile``, ``client``, ``overwrite``, ...).

        Returns
        -------
        xarray.DataArray
            The scene re-opened from ``out``.
        """
        from .scene import ingest

        return ingest(self._obj, out, **kwargs)

    def to_cog(self, path: str | os.PathLike, **kwargs: Any) -> Path:
        """Write this image as a Cloud-Optimized GeoTIFF: :func:`geocoder.cog.to_cog`.

        Parameters
        ----------
        path : str or PathLike
            The COG to write (a local path).
        **kwargs
            Keywords of :func:`geocoder.cog.to_cog` (``blocksize``, ``overviews``, ``client``, ...).

        Returns
        -------
        pathlib.Path
            The path written.
        """
        from .cog import to_cog

        return to_cog(self._obj, path, **kwargs)


@xr.register_dataset_accessor("geocoder")
class GeocoderDatasetAccessor:
    """``Dataset.geocoder``: a store geocoder wrote (the result of :func:`geocoder.register`).

    Parameters
    ----------
    obj : xarray.Dataset
        The dataset the accessor is attached to.
    """

    def __init__(self, obj: xr.Dataset) -> None:
        self._obj = obj

    def to_cog(self, path: str | os.PathLike, *, variable: str | None = None, **kwargs: Any) -> Path:
        """Write one image variable as a Cloud-Optimized GeoTIFF: :func:`geocoder.cog.to_cog`.

        Parameters
        ----------
        path : str or PathLike
            The COG to write (a local path).
        variable : str, optional
            The variable (``registered``, ``dx``, ``status``, ...); required when there are several.
        **kwargs
            Keywords of :func:`geocoder.cog.to_cog`.

        Returns
        -------
        pathlib.Path
            The path written.
        """
        from .cog import to_cog

        return to_cog(self._obj, path, variable=variable, **kwargs)

    def summary(self) -> RegisterSummary:
        """The job's summary (tie points, RMS, status counts, times) from ``attrs["summary"]``.

        Returns
        -------
        RegisterSummary
            ``.lines()`` gives what the CLI prints; ``.status_counts`` the pixels per status.

        Raises
        ------
        ValueError
            If the dataset is not a register output (no ``summary`` attribute).
        """
        from .pipeline.register import RegisterSummary

        return RegisterSummary(**json.loads(self._attr("summary")))

    def mapping(self) -> PolyMap:
        """The fitted global polynomial (base pixel -> distorted pixel) from ``attrs["mapping"]``.

        Returns
        -------
        PolyMap
            Callable on pixel coordinates ``(x, y)``.

        Raises
        ------
        ValueError
            If the dataset is not a register output (no ``mapping`` attribute).
        """
        from .kernels.polynomial import PolyMap

        return PolyMap.from_dict(json.loads(self._attr("mapping")))

    def _attr(self, name: str) -> str:
        try:
            return self._obj.attrs[name]
        except KeyError:
            raise ValueError(f"the dataset has no '{name}' attribute: it is not a geocoder register output") from None
