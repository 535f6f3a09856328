"""The command line, run as a real subprocess against the test cluster."""

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from affine import Affine
from cli_batch import run_batch
from pairs import write_synthetic_pair

from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho

pytestmark = pytest.mark.cluster


def run(*args, cwd=None, env=None):
    return subprocess.run([sys.executable, "-m", "geocoder.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=600)


def leftovers(directory):
    return [p for p in os.listdir(directory) if p.startswith(".")]


def test_missing_file(tmp_path, client):
    r = run("register", tmp_path / "nope.tif", tmp_path / "nope2.tif", "--out", tmp_path / "o.zarr", "--scheduler", client.scheduler.address)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == f"geocoder: error: {tmp_path / 'nope.tif'}: no such file"
    assert not (tmp_path / "o.zarr").exists()


def test_flat_image_is_refused_and_leaves_nothing(tmp_path, client):
    write_geotiff(tmp_path / "flat.tif", np.full((256, 256), 7.0, dtype=np.float32))
    write_geotiff(tmp_path / "tex.tif", synthetic_ortho((256, 256), seed=1))
    r = run("register", tmp_path / "flat.tif", tmp_path / "tex.tif", "--out", tmp_path / "o.zarr", "--tile", 128, "--scheduler", client.scheduler.address)
    assert r.returncode == 2, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("geocoder: error: ") and "flat.tif" in last and "is constant" in last
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "o.zarr").exists() and leftovers(tmp_path) == []


def test_no_overlap(tmp_path, client):
    img = synthetic_ortho((256, 256), seed=2)
    write_geotiff(tmp_path / "a.tif", img, transform=Affine(1, 0, 0, 0, -1, 0), crs="EPSG:32633")
    write_geotiff(tmp_path / "b.tif", img, transform=Affine(1, 0, 10000, 0, -1, 0), crs="EPSG:32633")
    r = run("register", tmp_path / "a.tif", tmp_path / "b.tif", "--out", tmp_path / "o.zarr", "--tile", 128, "--scheduler", client.scheduler.address)
    assert r.returncode == 2
    assert "does not overlap" in r.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "o.zarr").exists() and leftovers(tmp_path) == []


def test_demo_reports_error_against_truth(tmp_path, client):
    r = run("demo", "--size", 512, "--tile", 256, "--out", tmp_path / "demo", "--scheduler", client.scheduler.address)
    assert r.returncode == 0, r.stderr
    m = re.search(r"displacement field against truth: RMSE ([0-9.]+) px", r.stdout)
    assert m, r.stdout
    assert float(m.group(1)) < 0.1
    assert (tmp_path / "demo" / "registered.zarr" / "zarr.json").exists()
    # the CLI's register on the demo's files prints the summary
    out = tmp_path / "again.zarr"
    r = run("register", tmp_path / "demo/base.tif", tmp_path / "demo/distorted.tif", "--out", out, "--tile", 256, "--resampling",
            "cubic", "--no-dense", "--scheduler", client.scheduler.address)
    assert r.returncode == 0, r.stderr
    assert "tie points:" in r.stdout and "robust RMS" in r.stdout and (out / "zarr.json").exists()


@pytest.mark.data
@pytest.mark.parametrize("where", ["before", "after"])
def test_quiet_and_verbose_before_or_after_the_subcommand(tmp_path, client, where):
    """``geocoder -q register ...`` and ``geocoder register ... -q`` are the same command (issue 16)."""
    write_synthetic_pair(tmp_path, 256, seed=5, max_displacement=4)
    common = ("--no-dense", "--tile", 128, "--scheduler", client.scheduler.address)

    def register(out, *flags):
        args = ["register", tmp_path / "base.tif", tmp_path / "dist.tif", "--out", tmp_path / out, *common]
        return [*flags, *args] if where == "before" else [*args, *flags]

    # one process for the four command lines (see cli_batch)
    runs = run_batch({"loud": register("loud.zarr"), "quiet": register("quiet.zarr", "-q"),
                      "verbose": register("verbose.zarr", "-v"), "dashes": register("x.zarr", "--", "-q")}, tmp_path)
    (loud, _), (quiet, _), (verbose, _), (dashes, _) = runs.values()
    for r in (loud, quiet, verbose):
        assert r.returncode == 0, r.stderr
    assert "tiles" in loud.stderr, "progress is shown by default"
    assert "tiles" not in quiet.stderr, "-q: no progress"
    assert len(verbose.stderr.splitlines()) > len(loud.stderr.splitlines()), "-v: the stages' log lines too"
    assert dashes.returncode == 2, "after --, -q is an argument, not the option"


def test_ingest_command(shared_data, tmp_path, client):
    out = tmp_path / "rgb.zarr"
    r = run("ingest", shared_data / "landsat7_rasterio/RGB.byte.tif", out, "--tile", 256, "--scheduler", client.scheduler.address)
    assert r.returncode == 0, r.stderr
    assert "3 band(s), 718 x 791 px" in r.stdout
    from geocoder import open_scene

    z = open_scene(out)
    assert z.rio.crs.to_epsg() == 32618 and z.chunks[1][0] == 512 and z.shape == (3, 718, 791)


@pytest.mark.data
def test_simulate_command(shared_data, tmp_path, client):
    out = tmp_path / "sim.zarr"
    r = run("simulate", "airborne", "--ortho", shared_data / "baviaanskloof/ngi_rgb_byte_1.tif", "--band", 1,
            "--out", out, "--seed", 5, "--sensor", "caesar", "--rows", 300, "--tile", 256,
            "--scheduler", client.scheduler.address)
    assert r.returncode == 0, r.stderr
    assert "truth ground_x/ground_y/ground_z" in r.stdout
    import xarray as xr

    ds = xr.open_zarr(out, consolidated=False)
    assert ds.image.shape[1] == 300 and {"ground_x", "ground_y", "ground_z", "dem"} <= set(ds.variables)
    assert ds.attrs["sensor_class"] == "AirborneScanner" and ds.attrs["seed"] == 5
    r = run("simulate", "satellite", "--ortho", tmp_path / "missing.tif", "--out", tmp_path / "x.zarr")
    assert r.returncode == 2 and "missing.tif: no such file" in r.stderr


def test_simulate_synthetic_ortho(tmp_path, client):
    out = tmp_path / "syn.zarr"
    r = run("simulate", "satellite", "--ortho", "synthetic", "--out", out, "--seed", 1, "--pixel", 8,
            "--scheduler", client.scheduler.address)
    assert r.returncode == 0, r.stderr
    import xarray as xr

    ds = xr.open_zarr(out, consolidated=False)
    assert ds.attrs["sensor_class"] == "LineScanner" and float(ds.image.isnull().mean()) < 0.05
    assert leftovers(tmp_path) == []


def test_tile_from_options_unless_given(tmp_path, client):
    """Issue 16 item 4: without --tile the library's options decide (here Dask config from the
    environment, ``DASK_GEOCODER__TILE``); a --tile on the command line wins over them."""
    write_synthetic_pair(tmp_path, 384, seed=5, max_displacement=4)
    base, dist = tmp_path / "base.tif", tmp_path / "dist.tif"
    env = dict(os.environ, DASK_GEOCODER__TILE="128")
    scheduler = ("--scheduler", client.scheduler.address)
    import xarray as xr

    def tile_of(store):
        return xr.open_zarr(store, consolidated=False).dx.data.chunksize

    r = run("register", base, dist, "--out", tmp_path / "option.zarr", "--no-dense", *scheduler, env=env)
    assert r.returncode == 0, r.stderr
    assert tile_of(tmp_path / "option.zarr") == (128, 128)  # not the 384 of one 512 tile
    r = run("ingest", base, tmp_path / "flag.zarr", "--tile", 256, *scheduler, env=env)  # the flag wins (same option)
    assert r.returncode == 0, r.stderr
    assert xr.open_zarr(tmp_path / "flag.zarr", consolidated=False).image.data.chunksize == (1, 256, 256)
    r = run("ingest", base, tmp_path / "base.zarr", *scheduler, env=env)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().endswith("384 x 384 px, tile 128")
    assert xr.open_zarr(tmp_path / "base.zarr", consolidated=False).image.data.chunksize == (1, 128, 128)
    r = run("ingest", base, tmp_path / "bad.zarr", *scheduler, env=dict(os.environ, DASK_GEOCODER__TILE="100"))
    assert r.returncode == 2 and "geocoder.tile must be a positive multiple of 64" in r.stderr.strip().splitlines()[-1]
