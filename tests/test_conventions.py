"""The stores geocoder writes, opened by the libraries others use: xarray/rioxarray, GDAL (rasterio).

Real imagery (a Sentinel-2 crop with its georeference, warped into a raw frame), a real
LocalCluster, real Zarr stores on disk; every georeference compared with the base GeoTIFF's.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rioxarray
import xarray as xr
import zarr
from pairs import legacy_codec_copy, real_pair

from geocoder import Status, ingest, register
from geocoder.conventions import GRID_MAPPING, pixel_centres
from geocoder.status import legend

pytestmark = [pytest.mark.cluster, pytest.mark.data]

SIZE, TILE = 256, 128


@pytest.fixture(scope="module")
def stores(shared_data, tmp_path_factory, client):
    """A register output, the ingested (georeferenced) base and the ingested raw distorted frame."""
    tmp = tmp_path_factory.mktemp("conventions")
    files = real_pair(shared_data, tmp, which="s2", size=SIZE, seed=3)
    out = tmp / "out.zarr"
    register(files.base, files.distorted, out=out, tile=TILE, client=client, dense=False)
    ingest(files.base, tmp / "base.zarr", tile=TILE, client=client)
    ingest(files.distorted, tmp / "raw.zarr", tile=TILE, client=client)
    with rasterio.open(files.base) as f:
        georef = {"crs": f.crs, "transform": f.transform, "shape": f.shape}
    return {"register": out, "scene": tmp / "base.zarr", "raw": tmp / "raw.zarr", "base": georef, "tmp": tmp}


def _same_georeference(crs, transform, base) -> None:
    assert crs is not None and crs == base["crs"]
    assert transform.almost_equals(base["transform"], precision=1e-9), (transform, base["transform"])


@pytest.mark.parametrize("name,variables", [("register", ("registered", "dx", "dy", "status")), ("scene", ("image",))])
def test_rioxarray_reads_crs_and_transform(stores, name, variables):
    ds = xr.open_zarr(stores[name], decode_coords="all", consolidated=False)
    base = stores["base"]
    _same_georeference(ds.rio.crs, ds.rio.transform(), base)
    # the CF grid mapping: a spatial_ref coordinate named by every data variable
    ref = ds[GRID_MAPPING].attrs
    assert {"crs_wkt", "spatial_ref", "GeoTransform", "grid_mapping_name"} <= set(ref)
    assert rasterio.crs.CRS.from_wkt(ref["crs_wkt"]) == base["crs"]
    for v in variables:
        assert ds[v].encoding.get("grid_mapping") == GRID_MAPPING, v
        _same_georeference(ds[v].rio.crs, ds[v].rio.transform(), base)
        assert ds[v].attrs.get("long_name"), v
    # x / y: the pixel centres of the base's transform, with CF attributes
    x, y = pixel_centres(base["transform"], base["shape"])
    np.testing.assert_allclose(ds.x.values, x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ds.y.values, y, rtol=0, atol=1e-9)
    assert ds.x.attrs["standard_name"] == "projection_x_coordinate" and ds.x.attrs["units"] == "metre"
    assert ds.y.attrs["standard_name"] == "projection_y_coordinate" and ds.y.attrs["units"] == "metre"


@pytest.mark.parametrize("name", ["register", "scene"])
def test_geozarr_proj_and_spatial_attributes(stores, name):
    attrs = zarr.open_group(stores[name], mode="r").attrs.asdict()  # the root attributes as stored
    base = stores["base"]
    declared = {c["name"] for c in attrs["zarr_conventions"]}
    assert {"proj:", "spatial:"} <= declared
    assert attrs["proj:code"] == f"EPSG:{base['crs'].to_epsg()}"
    assert rasterio.crs.CRS.from_wkt(attrs["proj:wkt2"]) == base["crs"]
    assert attrs["spatial:dimensions"] == ["y", "x"]
    assert attrs["spatial:shape"] == list(base["shape"])
    np.testing.assert_allclose(attrs["spatial:transform"], list(base["transform"])[:6])
    assert attrs["spatial:registration"] == "pixel"
    left, bottom, right, top = rasterio.transform.array_bounds(*base["shape"], base["transform"])
    np.testing.assert_allclose(attrs["spatial:bbox"], [left, bottom, right, top])


def test_status_flags_follow_cf_and_geocoder_status(stores):
    ds = xr.open_zarr(stores["register"], consolidated=False)
    attrs = ds.status.attrs
    assert list(attrs["flag_values"]) == [int(s) for s in Status]
    assert attrs["flag_meanings"].split() == [s.name.lower() for s in Status]
    assert json.loads(attrs["status_legend"]) == legend()
    # the codes in the data are among the declared ones
    assert set(np.unique(ds.status.values)) <= set(attrs["flag_values"])


def test_raw_frame_keeps_pixel_coordinates(stores):
    ds = xr.open_zarr(stores["raw"], decode_coords="all", consolidated=False)
    assert ds.rio.crs is None
    assert "proj:code" not in ds.attrs
    np.testing.assert_array_equal(ds.x.values, np.arange(ds.sizes["x"]))
    np.testing.assert_array_equal(ds.y.values, np.arange(ds.sizes["y"]))
    assert ds.x.attrs["units"] == "pixel" and ds.y.attrs["units"] == "pixel"


def test_data_variables_and_their_overviews_are_compressed_with_shuffled_lz4(stores):
    # geocoder.storage.compressors: Blosc's LZ4 on shuffled bytes (half zarr's default Zstandard's
    # write time, a quarter smaller), in every level of the output and in the ingested scenes
    from zarr.codecs import BloscCodec

    out = zarr.open_group(stores["register"], mode="r")
    arrays = [out[name] for name in ("registered", "dx", "dy", "status")] + [out["1"]["registered"]]
    arrays += [zarr.open_group(stores[k], mode="r")["image"] for k in ("scene", "raw")]
    for a in arrays:
        (codec,) = a.compressors
        assert isinstance(codec, BloscCodec) and codec.cname.value == "lz4" and codec.shuffle.value == "shuffle", a.name
    # and the values come back: the georeferenced output as the conventions above read it
    ds = xr.open_zarr(stores["register"], decode_coords="all", consolidated=False)
    assert np.isfinite(ds.dx.values).mean() > 0.9 and ds.rio.crs is not None


# ------------------------------------------------------------------------------------ GDAL


def _gdal_zarr_v3_failure(tmp: Path) -> str | None:
    """Why the installed GDAL cannot read a Zarr v3 array zarr-python writes (None if it can)."""
    if "Zarr" not in rasterio.drivers.raster_driver_extensions().values() and not _has_zarr_driver():
        return f"GDAL {rasterio.__gdal_version__} has no Zarr driver"
    probe = tmp / "probe.zarr"
    if not probe.exists():
        zarr.create_array(probe, shape=(4, 4), dtype="float32", dimension_names=["y", "x"], zarr_format=3)[:] = 1
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(f'ZARR:"{probe}"') as f:
                f.read()
    except rasterio.errors.RasterioError as exc:
        return f"GDAL {rasterio.__gdal_version__} cannot read Zarr v3 arrays written to the v3.0 spec: {exc}"
    return None


def _has_zarr_driver() -> bool:
    with rasterio.Env() as env:
        return "Zarr" in env.drivers()


def _gdal_georeference(location: str) -> tuple:
    with rasterio.open(location) as f:
        return f.crs, f.transform, f.shape


@pytest.mark.parametrize("name,variable", [("register", "registered"), ("register", "status"), ("register", "dx"),
                                           ("scene", "image")])
def test_gdal_reads_crs_and_transform(stores, name, variable):
    """GDAL's Zarr driver (rasterio.open, rioxarray.open_rasterio) on the stores as written."""
    why = _gdal_zarr_v3_failure(stores["tmp"])
    if why:
        pytest.skip(why)
    _gdal_sees_the_base_georeference(f'ZARR:"{stores[name]}":/{variable}', stores["base"])


def _gdal_sees_the_base_georeference(location: str, base: dict):
    """GDAL (through rasterio and rioxarray) reads the base image's CRS, transform and shape."""
    crs, transform, shape = _gdal_georeference(location)
    _same_georeference(crs, transform, base)
    assert shape == base["shape"]
    da = rioxarray.open_rasterio(location)
    _same_georeference(da.rio.crs, da.rio.transform(), base)
    return da


@pytest.mark.parametrize("name,variable", [("register", "registered"), ("register", "status"), ("scene", "image")])
def test_gdal_reads_the_georeference_attributes(stores, name, variable, tmp_path):
    """What GDAL's Zarr driver takes from geocoder's attributes: CRS from ``_CRS``, transform from x/y.

    Run on a copy with the codec names this GDAL knows (see :func:`_legacy_codec_copy`), so
    the conventions are checked even where GDAL cannot decode the v3.0 chunks themselves.
    """
    if not _has_zarr_driver():
        pytest.skip(f"GDAL {rasterio.__gdal_version__} has no Zarr driver")
    copy = legacy_codec_copy(Path(stores[name]), tmp_path / "copy.zarr")
    da = _gdal_sees_the_base_georeference(f'ZARR:"{copy}":/{variable}', stores["base"])
    expected = xr.open_zarr(stores[name], consolidated=False)[variable].values
    np.testing.assert_array_equal(da.values.reshape(expected.shape), expected)
