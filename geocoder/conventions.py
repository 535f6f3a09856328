"""Metadata conventions of the Zarr stores geocoder writes, so that other libraries read them.

One function per concern, applied by every writer (``register``, ``ingest``, ``simulate``):

* :func:`georeference` declares a CRS and an affine transform four ways at once:

  - the CF / rioxarray way: a scalar ``spatial_ref`` coordinate (CF grid-mapping attributes,
    ``crs_wkt``, ``spatial_ref`` and GDAL's ``GeoTransform``) named by the ``grid_mapping`` of
    every data variable on the ``(y, x)`` grid; ``xr.open_zarr(..., decode_coords="all").rio``
    finds the CRS and transform there;
  - GDAL's Zarr driver: it takes the transform from the ``x``/``y`` coordinate arrays (pixel
    centres, regularly spaced) and the CRS from a ``_CRS`` attribute (``wkt``, ``projjson``)
    of each array;
  - the Zarr conventions ``proj:`` (``proj:code``, ``proj:wkt2``) and ``spatial:``
    (``spatial:dimensions``, ``spatial:transform``, ``spatial:shape``, ``spatial:bbox``,
    ``spatial:registration``), declared in the root's ``zarr_conventions`` list (GeoZarr);
  - CF attributes of the ``x``/``y`` coordinates (``standard_name``, ``long_name``, ``units``).

* :func:`pixel_grid` describes the ``x``/``y`` coordinates of a scene without georeference
  (pixel indices: column and row of the pixel centre).

* :func:`status_attrs` gives the CF flag attributes of the ``status`` array
  (:mod:`geocoder.status`).

No function here changes an array's values or names: only attributes, the ``spatial_ref``
coordinate, and the ``grid_mapping`` encoding are added.
"""

from __future__ import annotations

import json

import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr
from affine import Affine
from pyproj import CRS

from .geometry import pixel_to_world

#: Name of the scalar coordinate that holds the CRS (CF grid mapping; rioxarray's default).
GRID_MAPPING = "spatial_ref"

#: Declaration of the ``proj:`` Zarr convention (zarr-experimental/geo-proj, v1).
PROJ_CONVENTION = {
    "schema_url": "https://raw.githubusercontent.com/zarr-experimental/geo-proj/refs/tags/v1/schema.json",
    "spec_url": "https://github.com/zarr-experimental/geo-proj/blob/v1/README.md",
    "uuid": "f17cb550-5864-4468-aeb7-f3180cfb622f",
    "name": "proj:",
    "description": "Coordinate reference system information for geospatial data",
}

#: Declaration of the ``spatial:`` Zarr convention (zarr-conventions/spatial, v1).
SPATIAL_CONVENTION = {
    "schema_url": "https://raw.githubusercontent.com/zarr-conventions/spatial/refs/tags/v1/schema.json",
    "spec_url": "https://github.com/zarr-conventions/spatial/blob/v1/README.md",
    "uuid": "689b58e2-cf7b-45e0-9fff-9cfc0883d6b4",
    "name": "spatial:",
    "description": "Spatial coordinate information",
}


def _on_grid(var: xr.DataArray) -> bool:
    return var.ndim >= 2 and var.dims[-2:] == ("y", "x")


def _declare(attrs: dict, convention: dict) -> None:
    declared = list(attrs.get("zarr_conventions", []))
    if not any(isinstance(c, dict) and c.get("name") == convention["name"] for c in declared):
        declared.append(dict(convention))
    attrs["zarr_conventions"] = declared


def pixel_centres(transform: Affine, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """World ``x`` and ``y`` coordinates of the pixel centres of a north-up grid.

    Parameters
    ----------
    transform : affine.Affine
        GDAL transform (pixel corners) of the grid; it must have no rotation.
    shape : tuple of int
        ``(rows, cols)``.

    Returns
    -------
    x, y : numpy.ndarray
        float64 centre coordinates of the columns and of the rows.
    """
    if transform.b or transform.d:
        raise ValueError(f"a rotated transform has no 1-D x/y coordinates: {tuple(transform)[:6]}")
    rows, cols = shape
    x, _ = pixel_to_world(transform, np.arange(cols), np.zeros(cols))
    _, y = pixel_to_world(transform, np.zeros(rows), np.arange(rows))
    return x, y


def georeference(ds: xr.Dataset, crs, transform: Affine) -> xr.Dataset:
    """Declare ``crs`` and ``transform`` on ``ds`` for rioxarray, GDAL, CF and GeoZarr readers.

    Parameters
    ----------
    ds : xarray.Dataset
        Data variables on dims ``(..., y, x)``; ``x``/``y`` coordinates, when present, must
        be the pixel centres of ``transform`` (they are added when missing).
    crs : pyproj.CRS, rasterio.crs.CRS or str
        The coordinate reference system (anything :class:`pyproj.CRS` accepts).
    transform : affine.Affine
        GDAL transform (pixel corners) of the ``(y, x)`` grid.

    Returns
    -------
    xarray.Dataset
        A new dataset with the ``spatial_ref`` coordinate, ``grid_mapping`` and ``_CRS`` on
        every data variable of the grid, CF attributes on ``x``/``y`` and the ``proj:`` /
        ``spatial:`` root attributes. Values and names of the arrays are unchanged.

    Raises
    ------
    ValueError
        If the existing ``x``/``y`` coordinates are not the pixel centres of ``transform``.
    """
    crs = CRS.from_user_input(crs)
    shape = (ds.sizes["y"], ds.sizes["x"])
    x, y = pixel_centres(transform, shape)
    for name, centres in (("x", x), ("y", y)):
        if name in ds.coords:
            tol = 1e-6 * max(abs(transform.a), abs(transform.e))
            if not np.allclose(ds[name].values, centres, rtol=0, atol=tol):
                raise ValueError(f"the {name} coordinate is not the pixel centres of the transform {tuple(transform)[:6]}")
        else:
            ds = ds.assign_coords({name: centres})
    ds = ds.rio.write_crs(crs.to_wkt(), grid_mapping_name=GRID_MAPPING)
    ds = ds.rio.write_transform(transform, grid_mapping_name=GRID_MAPPING)
    ds = ds.rio.write_coordinate_system()
    gdal_crs = {"wkt": crs.to_wkt(), "projjson": json.loads(crs.to_json())}
    for name, var in ds.data_vars.items():
        if _on_grid(var):
            var.encoding["grid_mapping"] = GRID_MAPPING
            var.attrs["_CRS"] = gdal_crs
    attrs = dict(ds.attrs)
    _declare(attrs, PROJ_CONVENTION)
    _declare(attrs, SPATIAL_CONVENTION)
    authority = crs.to_authority()
    if authority is not None:
        attrs["proj:code"] = ":".join(authority)
    attrs["proj:wkt2"] = crs.to_wkt()
    rows, cols = shape
    xs = [transform.c, transform.c + cols * transform.a]
    ys = [transform.f, transform.f + rows * transform.e]
    attrs.update({
        "spatial:dimensions": ["y", "x"],
        "spatial:transform": [transform.a, transform.b, transform.c, transform.d, transform.e, transform.f],
        "spatial:shape": [rows, cols],
        "spatial:bbox": [min(xs), min(ys), max(xs), max(ys)],
        "spatial:registration": "pixel",
    })
    ds.attrs = attrs
    return ds


def pixel_grid(ds: xr.Dataset) -> xr.Dataset:
    """Describe the ``x``/``y`` coordinates of a grid without georeference (pixel indices).

    ``x`` is the column and ``y`` the row of the pixel centre (the project's image
    convention); coordinates are added when missing, existing values are kept.

    Parameters
    ----------
    ds : xarray.Dataset
        Data variables on dims ``(..., y, x)``.

    Returns
    -------
    xarray.Dataset
        A new dataset with CF attributes on ``x`` and ``y``.
    """
    for name in ("x", "y"):
        if name not in ds.coords:
            ds = ds.assign_coords({name: np.arange(ds.sizes[name], dtype=np.float64)})
    ds = ds.copy()
    ds["x"].attrs.update({"long_name": "column of the pixel centre", "units": "pixel", "axis": "X"})
    ds["y"].attrs.update({"long_name": "row of the pixel centre", "units": "pixel", "axis": "Y"})
    return ds


def status_attrs() -> dict:
    """CF attributes of a ``status`` array: ``flag_values``, ``flag_meanings``, ``long_name``.

    ``flag_meanings`` lists the names of :class:`geocoder.status.Status` (lower case),
    space-separated, in the order of ``flag_values``; ``status_legend`` keeps the same table
    as JSON (``{"outside": 0, ...}``, :func:`geocoder.status.legend`).

    Returns
    -------
    dict
        Attributes for the ``status`` variable.
    """
    from .status import legend

    table = sorted(legend().items(), key=lambda kv: kv[1])
    return {
        "long_name": "what the displacement of the pixel rests on",
        "flag_values": np.array([v for _, v in table], dtype=np.uint8),
        "flag_meanings": " ".join(k for k, _ in table),
        "status_legend": json.dumps(legend()),
    }
