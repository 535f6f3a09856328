import os

import numpy as np
import pytest
import zarr
from affine import Affine

from geocoder import InputError, ingest, open_scene
from geocoder.scene import WindowReader, pixel_to_world, world_to_pixel, write_geotiff

S2 = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
RGB = "landsat7_rasterio/RGB.byte.tif"


@pytest.mark.data
def test_open_geotiff_keeps_crs_and_masks_nodata(shared_data):
    s = open_scene(shared_data / RGB, chunks=256)
    assert s.dims == ("band", "y", "x") and s.shape == (3, 718, 791)
    assert s.dtype == np.float32 and s.chunks[1][0] == 256
    assert s.rio.crs.to_epsg() == 32618
    assert s.attrs["georeferenced"] and s.attrs["source_dtype"] == "uint8"
    vals = s.isel(band=0).values
    assert np.isnan(vals).mean() > 0.1  # declared nodata 0 became NaN
    # the S2 file does not declare its nodata: it can be given
    s2 = open_scene(shared_data / S2, nodata=0)
    assert np.isnan(s2.isel(band=0, x=slice(0, 300), y=slice(2500, 3200)).values).any()


@pytest.mark.data
def test_pixel_centre_convention_matches_coordinates(shared_data):
    s = open_scene(shared_data / RGB)
    t = s.rio.transform()
    wx, wy = pixel_to_world(t, np.array([0.0, 10.0]), np.array([0.0, 5.0]))
    assert wx[0] == pytest.approx(float(s.x[0])) and wy[0] == pytest.approx(float(s.y[0]))
    assert wx[1] == pytest.approx(float(s.x[10])) and wy[1] == pytest.approx(float(s.y[5]))
    px, py = world_to_pixel(t, wx, wy)
    np.testing.assert_allclose(px, [0, 10]) and np.testing.assert_allclose(py, [0, 5])


@pytest.mark.data
def test_ingest_zarr_v3_roundtrip(shared_data, tmp_path, client):
    out = tmp_path / "rgb.zarr"
    z = ingest(shared_data / RGB, out, tile=256, client=client)
    meta = zarr.open_group(str(out), mode="r")
    assert meta.metadata.zarr_format == 3
    assert meta["image"].chunks == (3, 256, 256)
    assert z.rio.crs.to_epsg() == 32618 and z.rio.transform() == open_scene(shared_data / RGB).rio.transform()
    np.testing.assert_array_equal(z.values, open_scene(shared_data / RGB).values)
    assert not [p for p in os.listdir(tmp_path) if "partial" in p]
    win = WindowReader(str(out)).read(-5, 20, 780, 800)  # clipped, NaN outside
    assert win.shape == (3, 25, 20) and np.isnan(win[:, :5]).all() and np.isnan(win[:, :, 11:]).all()


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(InputError, match="nope.tif: no such file"):
        open_scene(tmp_path / "nope.tif")
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"this is not a tiff")
    with pytest.raises(InputError, match="bad.tif: cannot be read as a raster"):
        open_scene(bad)


def test_raw_image_gets_pixel_coordinates(tmp_path):
    path = tmp_path / "raw.tif"
    write_geotiff(path, np.arange(12.0).reshape(3, 4))
    s = open_scene(path)
    assert not s.attrs["georeferenced"]
    np.testing.assert_array_equal(s.x.values, np.arange(4))
    path2 = tmp_path / "geo.tif"
    write_geotiff(path2, np.ones((2, 3, 4)), transform=Affine(2, 0, 100, 0, -2, 50), crs="EPSG:32633")
    assert open_scene(path2).attrs["georeferenced"]


def test_rotated_geotransform_is_refused_as_a_grid_and_dropped_otherwise(tmp_path):
    """A rotated GeoTIFF (as the aerial photographs in ../shared/data) cannot define a north-up
    output grid: refused with the file named; as a distorted scene its georeference is dropped."""
    from affine import Affine

    from geocoder.errors import InputError
    from geocoder.scene import open_scene, write_geotiff

    path = tmp_path / "rotated.tif"
    img = np.random.default_rng(0).random((1, 64, 64)).astype(np.float32)
    write_geotiff(path, img, transform=Affine(-5.6, -0.02, 1000.0, -0.02, 5.6, 2000.0), crs="EPSG:32735")
    with pytest.raises(InputError, match="rotated.tif: has a rotated geotransform"):
        open_scene(path, grid=True)
    scene = open_scene(path)
    assert scene.attrs["georeferenced"] is False
    np.testing.assert_array_equal(scene.x.values, np.arange(64))
    np.testing.assert_array_equal(scene.values, img)


def test_a_geotiff_scene_s_chunks_share_no_input(tmp_path):
    """Every chunk's task holds the file's reader itself: as one shared input it lived on one
    worker, and every chunk's read and store of an ingest was drawn there."""
    path = tmp_path / "s.tif"
    write_geotiff(path, np.arange(64 * 96, dtype=np.float32).reshape(64, 96))
    scene = open_scene(path, chunks=32)
    graph = dict(scene.data.__dask_graph__())
    assert len(graph) == 6 and not any("original" in str(k) for k in graph)
    assert open_scene(path, chunks=32).data.name == scene.data.name  # a deterministic key
    np.testing.assert_array_equal(scene.values[0], np.arange(64 * 96, dtype=np.float32).reshape(64, 96))
