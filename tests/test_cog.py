"""COG export: real crops of the shared imagery, tiles computed on the test cluster, the result
read back by rasterio (GDAL) and judged by rio-cogeo's validator (GDAL's validation logic)."""

from __future__ import annotations

import os
import struct
import warnings

import numpy as np
import pytest
import rasterio
import rioxarray
import xarray as xr
from affine import Affine
from cli_batch import run_batch
from conftest import read_band
from rio_cogeo.cogeo import cog_validate

from geocoder.cog import to_cog
from geocoder.errors import GeocoderWarning, InputError, OutputError
from geocoder.scene import ingest, write_geotiff

pytestmark = [pytest.mark.cluster, pytest.mark.data]

S2 = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
AERIAL = "baviaanskloof/ngi_rgb_byte_1.tif"
ROWS, COLS = 500, 700  # edge tiles of 256 are partial
S2_WINDOW = (300, 300 + ROWS, 1100, 1100 + COLS)
AERIAL_WINDOW = (60, 60 + ROWS, 100, 100 + COLS)


def window_georef(path, window) -> tuple[object, Affine]:
    with rasterio.open(path) as src:
        return src.crs, src.transform * Affine.translation(window[2], window[0])


@pytest.fixture(scope="module")
def s2_store(shared_data, tmp_path_factory, client):
    """A real Sentinel-2 crop with a hole of NaN (nodata), ingested to Zarr on the cluster."""
    d = tmp_path_factory.mktemp("cog-s2")
    image = read_band(shared_data / S2, 1, S2_WINDOW).astype(np.float32)
    image[40:90, 500:620] = np.nan
    crs, transform = window_georef(shared_data / S2, S2_WINDOW)
    write_geotiff(d / "s2.tif", image, transform=transform, crs=crs.to_string(), dtype="float32")
    ingest(d / "s2.tif", d / "s2.zarr", tile=256, client=client)
    return d / "s2.zarr", image, crs, transform


@pytest.fixture(scope="module")
def aerial(shared_data):
    """A real 3-band uint8 aerial crop whose CRS has no EPSG code (WKT only), as a dask DataArray."""
    da = rioxarray.open_rasterio(shared_data / AERIAL, chunks={"band": -1, "y": 256, "x": 256})
    r0, r1, c0, c1 = AERIAL_WINDOW
    return da.isel(y=slice(r0, r1), x=slice(c0, c1))


def block_means(image: np.ndarray, f: int) -> np.ndarray:
    """Mean of the valid pixels of every f x f block (partial at the edges), NaN where none."""
    b, h, w = image.shape
    ph, pw = -(-h // f) * f, -(-w // f) * f
    padded = np.full((b, ph, pw), np.nan)
    padded[:, :h, :w] = image
    blocks = padded.reshape(b, ph // f, f, pw // f, f)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(blocks, axis=(2, 4))


def offsets(path) -> tuple[list[int], list[int]]:
    """IFD offsets (full resolution, then overviews) and the offsets of every level's tiles, as GDAL reports them."""
    ifds, data = [], []
    with rasterio.open(path) as src:
        levels = [None, *range(len(src.overviews(1)))]
        for ovr in levels:
            ifds.append(int(src.get_tag_item("IFD_OFFSET", "TIFF", bidx=1, ovr=ovr)))
            with rasterio.open(path, OVERVIEW_LEVEL=ovr) if ovr is not None else rasterio.open(path) as lvl:
                ny, nx = -(-lvl.height // 256), -(-lvl.width // 256)
            data.append([int(src.get_tag_item(f"BLOCK_OFFSET_{x}_{y}", "TIFF", bidx=1, ovr=ovr))
                         for y in range(ny) for x in range(nx)])
    return ifds, data


def assert_cog(path):
    valid, errors, warns = cog_validate(path, strict=True, quiet=True)
    assert valid, (errors, warns)
    with rasterio.open(path) as src:
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"  # GDAL recognised its own layout
    ifds, data = offsets(path)
    assert ifds == sorted(ifds) and max(ifds) < min(min(d) for d in data)  # every IFD before any tile
    for coarser, finer in zip(data[:0:-1], data[-2::-1]):
        assert max(coarser) < min(finer)  # smallest overview first, full resolution last
    for level in data:
        assert level == sorted(level)  # row-major inside a level


def test_store_round_trip_exact(s2_store, tmp_path, client):
    store, image, crs, transform = s2_store
    out = to_cog(store, tmp_path / "s2.tif", client=client, blocksize=256)
    assert_cog(out)
    with rasterio.open(out) as src:
        assert src.crs == crs and src.crs.to_epsg() == 32633
        assert src.transform == transform
        assert (src.width, src.height, src.count, src.dtypes[0]) == (COLS, ROWS, 1, "float32")
        assert src.block_shapes == [(256, 256)]
        assert np.isnan(src.nodata)
        assert src.overviews(1) == [2, 4]
        np.testing.assert_array_equal(src.read(1), image)  # NaN where NaN, every other value bit for bit
        assert not src.read_masks(1)[40:90, 500:620].any() and src.read_masks(1)[0, 0] == 255
    for level, f in enumerate((2, 4)):
        with rasterio.open(out, OVERVIEW_LEVEL=level) as ovr:
            assert (ovr.height, ovr.width) == (-(-ROWS // f), -(-COLS // f))
            assert ovr.block_shapes == [(256, 256)]
            np.testing.assert_allclose(ovr.read(1), block_means(image[None], f)[0], rtol=1e-6)


def test_multiband_integer_wkt_crs(aerial, tmp_path, client):
    out = to_cog(aerial, tmp_path / "rgb.tif", client=client, blocksize=256)
    assert_cog(out)
    expected = aerial.values
    with rasterio.open(out) as src, rasterio.open(aerial.encoding["source"]) as orig:
        assert src.crs == orig.crs and src.crs.to_epsg() is None  # written as WKT in GeoAsciiParams
        assert src.transform == aerial.rio.transform()
        assert (src.count, src.dtypes, src.nodata) == (3, ("uint8",) * 3, 0)
        assert src.tags(ns="IMAGE_STRUCTURE")["INTERLEAVE"] == "PIXEL"
        assert src.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == "2"
        np.testing.assert_array_equal(src.read(), expected)
        assert src.overviews(1) == [2, 4]
    with rasterio.open(out, OVERVIEW_LEVEL=1) as ovr:  # nearest: full-resolution pixel (4i, 4j)
        np.testing.assert_array_equal(ovr.read(), expected[:, ::4, ::4])


def test_float_nodata_value_bigtiff_and_status(s2_store, tmp_path, client):
    store, image, crs, transform = s2_store
    scene = xr.open_zarr(store, decode_coords="all", consolidated=False)["image"]
    out = to_cog(scene, tmp_path / "big.tif", client=client, blocksize=256, nodata=-9999.0, bigtiff=True, overviews=1)
    assert_cog(out)
    with open(out, "rb") as f:
        assert struct.unpack("<2sH", f.read(4)) == (b"II", 43)
    with rasterio.open(out) as src:
        assert src.nodata == -9999.0 and src.overviews(1) == [2]
        values = src.read(1)
    np.testing.assert_array_equal(values, np.where(np.isnan(image), -9999.0, image).astype(np.float32))

    status = (scene.fillna(0) // 500).clip(0, 5).astype(np.uint8).rio.write_crs(crs)
    out = to_cog(status, tmp_path / "status.tif", client=client, blocksize=256)
    assert_cog(out)
    with rasterio.open(out) as src:
        assert src.nodata is None and src.transform == transform
        np.testing.assert_array_equal(src.read(), status.values)
    with rasterio.open(out, OVERVIEW_LEVEL=0) as ovr:
        np.testing.assert_array_equal(ovr.read(), status.values[:, ::2, ::2])


def test_refusals_and_overwrite(s2_store, aerial, tmp_path, client):
    store = s2_store[0]
    target = tmp_path / "mine.tif"
    target.write_bytes(b"not geocoder's")
    for overwrite in (False, True):
        with pytest.raises(OutputError, match="geocoder did not write"):
            to_cog(store, target, client=client, blocksize=256, overwrite=overwrite)
    assert target.read_bytes() == b"not geocoder's"
    gdal_tif = tmp_path / "gdal.tif"
    write_geotiff(gdal_tif, np.zeros((32, 32), np.float32))
    with pytest.raises(OutputError, match="geocoder did not write"):
        to_cog(store, gdal_tif, client=client, overwrite=True)

    out = to_cog(aerial, tmp_path / "cog.tif", client=client, blocksize=256)
    with pytest.raises(OutputError, match="pass --overwrite"):
        to_cog(store, out, client=client, blocksize=256)
    to_cog(store, out, client=client, blocksize=256, overwrite=True)
    with rasterio.open(out) as src:
        assert src.count == 1 and src.tags()["variable"] == "image"
    with pytest.raises(InputError, match="no image variable 'registered'; it has: image"):
        to_cog(store, tmp_path / "x.tif", variable="registered", client=client)
    with pytest.raises(InputError, match="no such Zarr store"):
        to_cog(tmp_path / "missing.zarr", tmp_path / "x.tif", client=client)
    assert sorted(os.listdir(tmp_path)) == ["cog.tif", "gdal.tif", "mine.tif"]


def _fail(block):
    raise RuntimeError("tile failed")


def test_failed_job_leaves_nothing(aerial, tmp_path, client):
    broken = aerial.copy(data=aerial.data.map_blocks(_fail, dtype=aerial.dtype))
    with pytest.raises(RuntimeError, match="tile failed"):
        to_cog(broken, tmp_path / "broken.tif", client=client, blocksize=256)
    assert os.listdir(tmp_path) == []


def test_no_crs_warns_and_writes_raw(tmp_path, client):
    raw = xr.DataArray(np.arange(300 * 200, dtype=np.float32).reshape(1, 300, 200), dims=("band", "y", "x")).chunk(128)
    with pytest.warns(GeocoderWarning, match="has no CRS"):
        out = to_cog(raw, tmp_path / "raw.tif", client=client, blocksize=128)
    with pytest.warns(rasterio.errors.NotGeoreferencedWarning):
        verdict = cog_validate(out, strict=True, quiet=True)
    assert verdict[0], verdict
    with pytest.warns(rasterio.errors.NotGeoreferencedWarning):
        src = rasterio.open(out)
    with src:
        assert src.crs is None
        np.testing.assert_array_equal(src.read(), raw.values)


@pytest.fixture(scope="module")
def cli_runs(s2_store, tmp_path_factory, client):
    """The export command lines of the two tests below in one fresh process (see cli_batch), each
    test's files in a directory of its own: by name, (result, snapshot of the module's directory after it)."""
    d = tmp_path_factory.mktemp("cog-cli")
    store = s2_store[0]
    ex, raw = d / "export", d / "raw"
    ex.mkdir()
    raw.mkdir()
    write_geotiff(raw / "raw.tif", np.arange(200 * 300, dtype=np.float32).reshape(200, 300))
    ingest(raw / "raw.tif", raw / "raw.zarr", tile=128, client=client)
    sched = ("--scheduler", client.scheduler.address)
    cases = {
        "export": ["export", store, "--var", "image", "--cog", ex / "s2.tif", "--blocksize", 256, *sched],
        "exists": ["export", store, "--cog", ex / "s2.tif", *sched],
        "no variable": ["export", store, "--var", "registered", "--cog", ex / "o.tif", *sched],
        "no store": ["export", ex / "nope.zarr", "--cog", ex / "o.tif", *sched],
        "unreferenced": ["export", raw / "raw.zarr", "--cog", raw / "raw-cog.tif", "--blocksize", 128, *sched],
    }
    return d, run_batch(cases, d)


def _listed(after: dict, sub: str) -> dict[str, str]:
    """The files and directories under ``sub`` of a :func:`cli_batch.snapshot` of its parent, with their hashes."""
    return {k[len(sub) + 1:]: v for k, v in after.items() if k.startswith(sub + "/") and k != sub + "/"}


def test_cli_export(s2_store, cli_runs):
    store, image, _, _ = s2_store
    d, results = cli_runs
    out = d / "export" / "s2.tif"
    r, after = results["export"]
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"wrote {out}: 1 band(s) float32, 500 x 700 px, tile 256, 2 overview(s)")
    written = _listed(after, "export")
    assert sorted(written) == ["s2.tif"]

    r, after = results["exists"]
    assert r.returncode == 2 and r.stderr.strip() == f"geocoder: error: {out}: exists (a geocoder cog output); pass --overwrite to replace it"
    r, after = results["no variable"]
    assert r.returncode == 2 and r.stderr.strip() == f"geocoder: error: {store}: has no image variable 'registered'; it has: image"
    r, after = results["no store"]
    assert r.returncode == 2 and r.stderr.strip() == f"geocoder: error: {d / 'export' / 'nope.zarr'}: no such Zarr store"
    assert _listed(after, "export") == written  # the refusals left s2.tif as the first command wrote it, and nothing else
    # (the file on disk now: the refusals' runs have not touched it, see above)
    assert_cog(out)
    with rasterio.open(out) as src:
        np.testing.assert_array_equal(src.read(1), image)


def test_cli_export_unreferenced_store_warns(cli_runs):
    d, results = cli_runs
    raw = d / "raw"
    r, _ = results["unreferenced"]
    assert r.returncode == 0, r.stderr
    warning = f"geocoder: warning: {raw / 'raw.zarr'}: has no CRS; the COG is written without georeference"
    assert warning in r.stderr.splitlines() and "Warning" not in r.stderr
    with pytest.warns(rasterio.errors.NotGeoreferencedWarning):
        src = rasterio.open(raw / "raw-cog.tif")
    with src:
        assert src.crs is None and src.overviews(1) == [2, 4]  # 300 -> 150 -> 75 px fits one 128 tile


def test_graph_one_task_per_tile_and_source_blocks_read_once():
    """Graph construction only: a task per tile of every level, each source block one task shared by all levels."""
    import dask
    import dask.array as da

    from geocoder.cog import _tile_tasks, _TileSpec

    source = da.zeros((2, ROWS, COLS), chunks=(2, 256, 256), dtype=np.float32)
    spec = _TileSpec(256, "<f4", np.nan, np.nan, "deflate", 3, 0, True)
    tasks, layout = _tile_tasks(source, 2, 256, spec)
    assert layout == [(500, 700, 2, 3), (250, 350, 1, 2), (125, 175, 1, 1)]
    assert sorted(tasks) == [(0, y, x) for y in range(2) for x in range(3)] + [(1, 0, 0), (1, 0, 1), (2, 0, 0)]
    graph = dict(dask.delayed(list)(list(tasks.values())).__dask_graph__())
    assert sum(1 for key in graph if "encode" in str(key)) == len(tasks)
    assert sum(1 for key in graph if str(key).startswith(f"('{source.name}'")) == 6
