"""geocoder.set_options: validation, layers (call > options > Dask config > default), and where it is read."""

from __future__ import annotations

import json

import dask
import pytest
import xarray as xr
from affine import Affine
from pairs import write_synthetic_pair

import geocoder
from geocoder import RegisterOptions, get_option, get_options, register, set_options
from geocoder.runtime import dask_client
from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho


@pytest.mark.parametrize("options,named", [({"tile": 100}, "'tile'"), ({"tile": 32}, "'tile'"), ({"tile": True}, "'tile'"),
                                           ({"progress": "yes"}, "'progress'"), ({"n_workers": 0}, "'n_workers'"),
                                           ({"colour": "red"}, "'colour'")])
def test_bad_names_and_values_raise_naming_the_option(options, named):
    before = get_options()
    with pytest.raises(ValueError, match=named):
        set_options(**options)
    assert get_options() == before  # nothing half set


def test_context_manager_global_setter_and_dask_config():
    assert get_options() == {"tile": 512, "progress": None, "n_workers": None}
    with set_options(tile=256, progress=True):
        assert get_option("tile") == 256 and get_option("progress") is True
        with set_options(tile=1024):
            assert get_option("tile") == 1024
        assert get_option("tile") == 256
    assert get_option("tile") == 512 and get_option("progress") is None
    try:
        geocoder.set_options(n_workers=3)
        assert get_option("n_workers") == 3
    finally:
        geocoder.set_options(n_workers=None)
    # Dask config is the layer below the options
    with dask.config.set({"geocoder.tile": 128}):
        assert get_option("tile") == 128
        with set_options(tile=256):
            assert get_option("tile") == 256
    with dask.config.set({"geocoder.tile": 100}), pytest.raises(ValueError, match="geocoder.tile"):
        get_option("tile")
    with pytest.raises(ValueError, match="'nope'"):
        get_option("nope")


@pytest.mark.cluster
def test_local_cluster_size_from_option():
    with set_options(n_workers=1), dask_client() as c:
        assert len(c.scheduler_info()["workers"]) == 1


@pytest.mark.cluster
def test_register_tile_layers_and_progress(tmp_path, client, capsys):
    """Keyword > RegisterOptions > set_options > default; issue 18: order 3 and tile 256 from options."""
    work = write_synthetic_pair(tmp_path, 512, seed=5, max_displacement=4)
    base, dist = work / "base.tif", work / "dist.tif"

    def tile_of(store):
        return xr.open_zarr(store, consolidated=False).dx.data.chunksize

    with set_options(tile=128):
        ds = register(base, dist, out=tmp_path / "a.zarr", client=client, options=RegisterOptions(order=3, tile=256, dense=False))
        assert json.loads(ds.attrs["mapping"])["order"] == 3
        assert tile_of(tmp_path / "a.zarr") == (256, 256)
        register(base, dist, out=tmp_path / "b.zarr", client=client, tile=256, dense=False)
        assert tile_of(tmp_path / "b.zarr") == (256, 256)
        capsys.readouterr()
        with set_options(progress=True):
            register(base, dist, out=tmp_path / "c.zarr", client=client, dense=False)
        assert tile_of(tmp_path / "c.zarr") == (128, 128)
        assert "ingest (base, distorted)" in capsys.readouterr().err  # both scenes in one phase
    register(base, dist, out=tmp_path / "d.zarr", client=client, dense=False)
    assert tile_of(tmp_path / "d.zarr") == (512, 512)
    assert "ingest" not in capsys.readouterr().err  # no option, no display: as before


def test_default_tile_grows_with_the_scene_unless_set():
    """Issue 12: the default tile is 1024 from a smaller side of 2048 px on, 512 below, unless set (the rule; the
    speed behind it is measured by benchmarks/bench_speed.py, not here)."""
    from geocoder.options import default_tile

    assert default_tile((1024, 4096)) == 512 and default_tile((2047, 9000)) == 512
    assert default_tile((2048, 2048)) == 1024 and default_tile((8192, 4096)) == 1024
    with set_options(tile=256):
        assert default_tile((8192, 8192)) == 256
    with dask.config.set({"geocoder.tile": 128}):
        assert default_tile((8192, 8192)) == 128


@pytest.mark.cluster
def test_register_takes_the_large_tile_for_a_large_base(tmp_path, client):
    # the rule reads the base's size only: a 2048^2 base registered end to end against a raw copy
    # of itself (no warped partner to simulate, ~5 s of the test's ~12 s)
    image = synthetic_ortho((2048, 2048), seed=5)
    write_geotiff(tmp_path / "base.tif", image, transform=Affine(2, 0, 500000, 0, -2, 4000000), crs="EPSG:32633")
    write_geotiff(tmp_path / "dist.tif", image)
    ds = register(tmp_path / "base.tif", tmp_path / "dist.tif", out=tmp_path / "big.zarr", client=client, dense=False)
    assert ds.dx.data.chunksize == (1024, 1024)
    assert xr.open_zarr(tmp_path / "big.zarr", consolidated=False).dx.data.chunksize == (1024, 1024)
