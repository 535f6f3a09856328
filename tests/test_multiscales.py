"""Overview levels (``multiscales``) inside the stores geocoder writes.

Truth: a small georeferenced store with odd sides, NaN holes, flags and things that must not
be levelled is written to disk; every level is compared with the NaN-aware mean (or the
top-left pixel) of the full-resolution blocks computed in numpy, with the COG export's
overviews of the same data, and opened with xarray/rioxarray (and GDAL where it can). Then
``register`` and ``simulate`` end to end on a real LocalCluster.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import dask
import numpy as np
import pytest
import rasterio
import xarray as xr
import zarr
from affine import Affine
from pairs import legacy_codec_copy, real_pair

from geocoder import register
from geocoder.cog import to_cog
from geocoder.conventions import georeference, pixel_centres, pixel_grid, status_attrs
from geocoder.multiscales import (
    COUNTS_GROUP,
    _halve_mean,
    _level_tasks,
    _Levels,
    level_shapes,
    plan_overviews,
    write_overviews,
)

pytestmark = pytest.mark.cluster

SHAPE, CHUNK = (203, 150), 32  # odd sides: the last pixel of a level covers the edge only
TRANSFORM = Affine(10.0, 0.0, 500000.0, 0.0, -10.0, 5800000.0)
CRS = "EPSG:32633"


def _truth() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(16)
    h, w = SHAPE
    image = rng.normal(100.0, 20.0, (2, h, w)).astype(np.float32)
    image[:, 40:75, 20:61] = np.nan  # a hole across chunk and block borders
    image[0, rng.random((h, w)) < 0.3] = np.nan  # scattered nodata, band 1 only
    height = rng.normal(1500.0, 300.0, (h, w))
    height[:, 130:] = np.nan  # an empty edge: whole blocks without a valid pixel
    status = rng.integers(0, 5, (h, w)).astype(np.uint8)
    return {"image": image, "height": height, "status": status}


def _dataset(truth: dict) -> xr.Dataset:
    return xr.Dataset(
        {
            "image": (("band", "y", "x"), truth["image"], {"long_name": "an image", "units": "DN"}),
            "height": (("y", "x"), truth["height"], {"long_name": "terrain height", "units": "m"}),
            "status": (("y", "x"), truth["status"], status_attrs()),
            "dem": (("dem_y", "dem_x"), np.ones((5, 4)), {"long_name": "not on the grid"}),
        },
        coords={"band": ("band", [1, 2], {"long_name": "band"})},
        attrs={"geocoder_product": "test", "note": "root attribute"},
    ).chunk({"band": 1, "y": CHUNK, "x": CHUNK, "dem_y": -1, "dem_x": -1})


def _write(ds: xr.Dataset, path: Path) -> Path:
    ds.status.encoding["fill_value"] = np.uint8(255)  # a Zarr fill value that is not the default (0)
    ds.to_zarr(path, mode="w", zarr_format=3, consolidated=False)
    xr.Dataset({"line": (("point",), np.arange(7.0))}).to_zarr(path, group="tiepoints", mode="w", zarr_format=3,
                                                                consolidated=False)
    return path


def _block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """NaN-aware mean of every f x f block (sides padded with NaN to a multiple of f)."""
    h, w = a.shape[-2:]
    H, W = -(-h // f) * f, -(-w // f) * f
    pad = np.full((*a.shape[:-2], H, W), np.nan)
    pad[..., :h, :w] = a
    blocks = pad.reshape(*a.shape[:-2], H // f, f, W // f, f)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks
        return np.nanmean(blocks, axis=(-3, -1))


@pytest.fixture(scope="module")
def truth():
    return _truth()


@pytest.fixture(scope="module")
def store(truth, tmp_path_factory, client):
    """A georeferenced store with its levels; and the root as it was before them."""
    tmp = tmp_path_factory.mktemp("multiscales")
    path = _write(georeference(_dataset(truth), CRS, TRANSFORM), tmp / "small.zarr")
    before = xr.open_zarr(path, decode_coords="all", consolidated=False).load()
    levels = write_overviews(path, client=client)
    return {"path": path, "levels": levels, "before": before, "tmp": tmp}


def _level(store, k: int, **kw) -> xr.Dataset:
    return xr.open_zarr(store["path"], group=str(k), consolidated=False, **kw)


# ------------------------------------------------------------------------------ values


def test_levels_until_one_chunk(store):
    # default min_size: the larger side of a root chunk; 203 -> 102 -> 51 -> 26 <= 32
    assert store["levels"] == [1, 2, 3]
    assert level_shapes(SHAPE, CHUNK) == [(102, 75), (51, 38), (26, 19)]
    for k, shape in zip(store["levels"], level_shapes(SHAPE, CHUNK)):
        ds = _level(store, k)
        assert (ds.sizes["y"], ds.sizes["x"]) == shape
    assert level_shapes((256, 256), 256) == [] and level_shapes((257, 10), 256) == [(129, 5)]
    with pytest.raises(ValueError, match="min_size"):
        level_shapes(SHAPE, 0)


@pytest.mark.parametrize("name", ["image", "height"])
def test_float_levels_are_means_of_the_valid_full_resolution_pixels(store, truth, name):
    """Level k = NaN-aware mean of the 2**k x 2**k full-resolution block (not a mean of means)."""
    for k in store["levels"]:
        got = _level(store, k)[name].values
        expected = _block_mean(truth[name].astype(np.float64), 2**k)
        assert got.dtype == truth[name].dtype
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
        np.testing.assert_allclose(got, expected, rtol=2e-6 if got.dtype == np.float32 else 1e-12, equal_nan=True)
    # the holes make the difference: a mean of 2 x 2 means would be off near them
    level2 = _level(store, 2)[name].values
    means_of_means = _block_mean(_block_mean(truth[name].astype(np.float64), 2), 2)
    assert np.nanmax(np.abs(level2 - means_of_means)) > 1e-3


def test_status_takes_the_top_left_pixel(store, truth):
    for k in store["levels"]:
        status = _level(store, k).status
        f = 2**k
        np.testing.assert_array_equal(status.values, truth["status"][::f, ::f])
        assert status.dtype == np.uint8
        assert status.attrs["cell_methods"] == "y: x: point"
        assert list(status.attrs["flag_values"]) == list(status_attrs()["flag_values"])
        assert status.attrs["flag_meanings"] == status_attrs()["flag_meanings"]


def test_same_values_as_the_cog_overviews(store, client, tmp_path):
    """The Zarr levels and the COG export's overviews of the same variable are equal."""
    for name in ("height", "status"):
        cog = to_cog(store["path"], tmp_path / f"{name}.tif", variable=name, client=client, blocksize=CHUNK)
        for k in store["levels"]:
            with rasterio.open(cog, overview_level=k - 1) as f:
                ovr = f.read(1)
            np.testing.assert_allclose(_level(store, k)[name].values, ovr, rtol=1e-12, equal_nan=True)


def test_halve_mean_kernel_carries_the_counts():
    a = np.array([[1.0, np.nan, 4.0], [3.0, np.nan, np.nan], [np.nan, np.nan, 7.0]])
    mean, n = _halve_mean(a)
    np.testing.assert_array_equal(n, [[2, 1], [0, 1]])
    np.testing.assert_allclose(mean, [[2.0, 4.0], [np.nan, 7.0]], equal_nan=True)
    # the next level weights each mean by its count: (2 * 2 + 4 + 7) / 4, not (2 + 4 + 7) / 3
    mean2, n2 = _halve_mean(mean, n)
    assert n2[0, 0] == 4 and mean2[0, 0] == pytest.approx(15.0 / 4)


# ------------------------------------------------------------------------------ layout


def test_levels_are_georeferenced(store):
    base_crs = rasterio.crs.CRS.from_user_input(CRS)
    for k in store["levels"]:
        ds = _level(store, k, decode_coords="all")
        t = TRANSFORM * Affine.scale(2**k)
        assert ds.rio.crs == base_crs
        assert ds.rio.transform().almost_equals(t, precision=1e-9)
        assert ds.height.rio.transform().almost_equals(t, precision=1e-9)
        x, y = pixel_centres(t, (ds.sizes["y"], ds.sizes["x"]))
        np.testing.assert_allclose(ds.x.values, x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ds.y.values, y, rtol=0, atol=1e-9)
        attrs = zarr.open_group(store["path"], path=str(k), mode="r").attrs.asdict()
        assert attrs["proj:code"] == CRS
        assert attrs["spatial:shape"] == [ds.sizes["y"], ds.sizes["x"]]
        np.testing.assert_allclose(attrs["spatial:transform"], list(t)[:6])
        assert {c["name"] for c in attrs["zarr_conventions"]} == {"proj:", "spatial:"}
        # the GDAL / CF pieces of conventions.georeference on every levelled variable
        for name in ("image", "height", "status"):
            assert ds[name].encoding["grid_mapping"] == "spatial_ref"
            assert ds[name].attrs["_CRS"]["projjson"]["id"]["code"] == 32633


def test_multiscales_attribute_lists_every_level(store):
    attrs = zarr.open_group(store["path"], mode="r").attrs.asdict()
    declared = {c["name"]: c for c in attrs["zarr_conventions"]}
    assert {"multiscales", "proj:", "spatial:"} <= set(declared)
    assert declared["multiscales"]["uuid"] == "d35379db-88df-4056-af3a-620245f8e347"
    ms = attrs["multiscales"]
    layout = ms["layout"]
    assert [e["asset"] for e in layout] == [".", "1", "2", "3"]
    assert layout[0]["transform"] == {"scale": [1.0, 1.0], "translation": [0.0, 0.0]} and "derived_from" not in layout[0]
    assert layout[0]["spatial:shape"] == list(SHAPE)
    for k, entry in enumerate(layout[1:], start=1):
        assert entry["derived_from"] == ("." if k == 1 else str(k - 1))
        assert entry["transform"] == {"scale": [2.0, 2.0], "translation": [0.0, 0.0]}
        ds = _level(store, k)
        assert entry["spatial:shape"] == [ds.sizes["y"], ds.sizes["x"]]
        np.testing.assert_allclose(entry["spatial:transform"], list(TRANSFORM * Affine.scale(2**k))[:6])
    assert ms["resampling_method"] == "average"
    assert ms["resampling_method_by_variable"] == {"height": "average", "image": "average", "status": "nearest"}
    # the scratch counts are gone; nothing else than the levels was added to the store
    group = zarr.open_group(store["path"], mode="r")
    assert COUNTS_GROUP not in group
    assert {name for name, _ in group.groups()} == {"1", "2", "3", "tiepoints"}


def test_root_is_unchanged(store):
    before = store["before"]
    after = xr.open_zarr(store["path"], decode_coords="all", consolidated=False).load()
    added = {"multiscales"}
    assert set(after.attrs) - set(before.attrs) == added
    conventions = [c for c in after.attrs["zarr_conventions"] if c["name"] != "multiscales"]
    assert conventions == before.attrs["zarr_conventions"]
    after.attrs = {k: v for k, v in after.attrs.items() if k not in added}
    after.attrs["zarr_conventions"] = conventions
    xr.testing.assert_identical(after, before)
    for name in after.variables:
        assert after[name].encoding.get("chunks") == before[name].encoding.get("chunks"), name


def test_dtype_fill_value_chunks_and_attributes_kept(store):
    root = store["before"]
    for k in store["levels"]:
        ds = _level(store, k, decode_coords="all")
        assert set(ds.data_vars) == {"image", "height", "status"}  # not the dem, not the tie points
        assert "dem_y" not in ds.dims and not list(zarr.open_group(store["path"], path=str(k), mode="r").groups())
        np.testing.assert_array_equal(ds.band.values, [1, 2])
        assert ds.band.attrs["long_name"] == "band"
        for name in ds.data_vars:
            var, src = ds[name], root[name]
            assert var.dtype == src.dtype
            assert var.encoding["chunks"] == tuple(min(c, n) for c, n in zip(src.encoding["chunks"], var.shape))
            assert var.encoding["compressors"] == src.encoding["compressors"]
            stored = zarr.open_array(store["path"], path=f"{k}/{name}", mode="r").metadata.fill_value
            root_fill = zarr.open_array(store["path"], path=name, mode="r").metadata.fill_value
            assert stored == root_fill or (np.isnan(stored) and np.isnan(root_fill)), name
            assert var.attrs["long_name"] == src.attrs["long_name"]
            if name != "status":
                assert np.isnan(var.encoding["_FillValue"])
                assert var.attrs["units"] == src.attrs["units"]
                assert var.attrs["cell_methods"] == "y: x: mean"


def test_one_task_per_output_chunk_and_variable(store):
    """A level's chunk of a variable is one task, which takes only the (at most 2 x 2) tasks of
    the chunks below it: the graph of all levels is exactly one key per output chunk."""
    root = xr.open_zarr(store["path"], decode_coords="all", consolidated=False)
    levels = _Levels(str(store["path"]), ["height", "image", "status"], root)
    shapes = level_shapes(SHAPE, CHUNK)
    specs = levels.specs(shapes)
    assert [s.name for s in specs] == ["height", "image", "status"]
    for spec in specs:
        tasks = _level_tasks(spec)
        for k, (h, w) in enumerate(shapes, start=1):
            assert sorted((iy, ix) for (kk, iy, ix) in tasks if kk == k) == [
                (iy, ix) for iy in range(-(-h // CHUNK)) for ix in range(-(-w // CHUNK))]
        last = [t for (k, _, _), t in tasks.items() if k == len(shapes)]
        graph = {k: v for task in last for k, v in dict(task.__dask_graph__()).items()}
        assert set(graph) == {t.key for t in tasks.values()}  # no reader, no getitem, no cast of its own
        for (k, iy, ix), task in tasks.items():
            below = {tasks[(k - 1, 2 * iy + a, 2 * ix + b)].key for a in (0, 1) for b in (0, 1)
                     if (k - 1, 2 * iy + a, 2 * ix + b) in tasks}
            assert dask.core.get_dependencies(graph, task.key) == below  # the first level's: none (spread)
        # the same keys from a second opening of the store: a rerun's tasks are the same tasks
        again = _level_tasks(_Levels(str(store["path"]), [spec.name], root).specs(shapes)[0])
        assert {k: t.key for k, t in again.items()} == {k: t.key for k, t in tasks.items()}


def test_pixel_grid_store_and_rerun(truth, tmp_path, client):
    """A store without CRS: level coordinates in full-resolution pixels; a second call replaces the levels."""
    path = _write(pixel_grid(_dataset(truth)), tmp_path / "raw.zarr")
    assert write_overviews(path, client=client, min_size=60, variables=["height", "status"]) == [1, 2]
    assert write_overviews(path, client=client, min_size=60, variables=["height", "status"]) == [1, 2]
    level = xr.open_zarr(path, group="1", decode_coords="all", consolidated=False)
    assert level.rio.crs is None and set(level.data_vars) == {"height", "status"}
    np.testing.assert_array_equal(level.x.values, 2 * np.arange(75) + 0.5)  # centre of columns 2j and 2j + 1
    np.testing.assert_array_equal(level.y.values, 2 * np.arange(102) + 0.5)
    assert level.x.attrs["units"] == "pixel"
    np.testing.assert_allclose(xr.open_zarr(path, group="2", consolidated=False).height.values,
                               _block_mean(truth["height"], 4), rtol=1e-12, equal_nan=True)
    attrs = zarr.open_group(path, mode="r").attrs.asdict()
    assert [c["name"] for c in attrs["zarr_conventions"]] == ["multiscales"]
    assert all("spatial:transform" not in e for e in attrs["multiscales"]["layout"])
    with pytest.raises(ValueError, match="not variables on the"):
        write_overviews(path, variables=["dem"])
    small = tmp_path / "small.zarr"
    shutil.copytree(path, small)
    assert write_overviews(small, min_size=300) == []  # fits already: nothing written


def test_planned_before_the_root_is_written(store, truth, tmp_path, client):
    """The levels planned on a store whose root holds metadata only (as register plans them while
    its tiles are written), computed once the values are in: the same store as write_overviews'."""
    ds = georeference(_dataset(truth), CRS, TRANSFORM)
    path = tmp_path / "planned.zarr"
    ds.status.encoding["fill_value"] = np.uint8(255)
    ds.to_zarr(path, mode="w", zarr_format=3, consolidated=False, compute=False)
    assert not (path / "image" / "c").exists()  # the root: metadata only
    plan = plan_overviews(path)
    assert (path / "1" / "image" / "zarr.json").exists() and not (path / "1" / "image" / "c").exists()
    ds.to_zarr(path, mode="r+", zarr_format=3, consolidated=False)  # the values, after the plan
    assert plan.compute(client) == store["levels"]
    for k in store["levels"]:
        xr.testing.assert_identical(_level(store, k).load(), xr.open_zarr(path, group=str(k), consolidated=False).load())
    assert zarr.open_group(path, mode="r").attrs["multiscales"] == zarr.open_group(store["path"], mode="r").attrs["multiscales"]
    assert plan_overviews(path, min_size=300).compute(client) == []  # fits already: nothing to do


# ------------------------------------------------------------------------------ writers


def _gdal_can_read_copies() -> bool:
    with rasterio.Env() as env:
        return "Zarr" in env.drivers()


@pytest.mark.data
def test_register_writes_levels(shared_data, tmp_path, client):
    files = real_pair(shared_data, tmp_path, which="s2", size=256, seed=3)
    out = tmp_path / "out.zarr"
    register(files.base, files.distorted, out=out, tile=128, client=client, dense=False)
    root = xr.open_zarr(out, decode_coords="all", consolidated=False)
    with rasterio.open(files.base) as f:
        crs, transform = f.crs, f.transform
    ms = zarr.open_group(out, mode="r").attrs["multiscales"]
    assert [e["asset"] for e in ms["layout"]] == [".", "1"]  # 256 px, tile 128: one level of one chunk
    level = xr.open_zarr(out, group="1", decode_coords="all", consolidated=False)
    assert level.rio.crs == crs
    assert level.rio.transform().almost_equals(transform * Affine.scale(2), precision=1e-9)
    assert set(level.data_vars) == {"registered", "dx", "dy", "status"}
    for name in ("registered", "dx"):
        np.testing.assert_allclose(level[name].values, _block_mean(root[name].values.astype(np.float64), 2),
                                   rtol=2e-6, equal_nan=True)
    np.testing.assert_array_equal(level.status.values, root.status.values[::2, ::2])
    assert "tiepoints" in zarr.open_group(out, mode="r") and "tiepoints" not in zarr.open_group(out, path="1", mode="r")
    if not _gdal_can_read_copies():
        return
    copy = legacy_codec_copy(zarr.open_group(out, path="1", mode="r"), tmp_path / "level1.zarr")
    with rasterio.open(f'ZARR:"{copy}":/dx') as f:
        assert f.crs == crs and f.transform.almost_equals(transform * Affine.scale(2), precision=1e-9)
        np.testing.assert_array_equal(f.read(1), level.dx.values)


def test_simulate_writes_levels(tmp_path, client):
    from geocoder.pipeline.simulate import Radiometry, simulate
    from geocoder.scene import write_geotiff
    from geocoder.simulate.texture import synthetic_ortho

    ortho = tmp_path / "ortho.tif"
    write_geotiff(ortho, synthetic_ortho((256, 256), seed=5), transform=Affine(2.0, 0, 500000.0, 0, -2.0, 5800000.0),
                  crs="EPSG:32633")
    ds = simulate("satellite", ortho, out=tmp_path / "sim.zarr", pixel=2.0, tile=64, client=client,
                  radiometry=Radiometry(noise=0.0))
    h, w = ds.sizes["y"], ds.sizes["x"]
    layout = zarr.open_group(tmp_path / "sim.zarr", mode="r").attrs["multiscales"]["layout"]
    assert [e["asset"] for e in layout] == [".", *map(str, range(1, len(level_shapes((h, w), 64)) + 1))]
    level = xr.open_zarr(tmp_path / "sim.zarr", group="1", consolidated=False)
    assert set(level.data_vars) == {"image", "ground_x", "ground_y", "ground_z"}  # not the DEM
    np.testing.assert_allclose(level.ground_x.values, _block_mean(ds.ground_x.values, 2), rtol=1e-12)
    np.testing.assert_allclose(level.image.values, _block_mean(ds.image.values.astype(np.float64), 2), rtol=2e-6,
                               equal_nan=True)
    np.testing.assert_array_equal(level.x.values, 2 * np.arange(level.sizes["x"]) + 0.5)
