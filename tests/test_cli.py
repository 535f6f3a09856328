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


def listed(after: dict, sub: str) -> set[str]:
    """The names directly in ``sub`` of a :func:`cli_batch.snapshot` of its parent."""
    return {k[len(sub) + 1:].split("/")[0] for k in after if k.startswith(sub + "/") and k != sub + "/"}


def leftovers(after: dict, sub: str) -> list[str]:
    """Hidden names (a job directory, a lock, a partial store) in ``sub`` after a case."""
    return [p for p in listed(after, sub) if p.startswith(".")]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, client):
    """The command lines of the tests below that need no shared imagery, in one process (see cli_batch),
    each test's files in a directory of its own: by name, (result, snapshot of the module's directory after it)."""
    d = tmp_path_factory.mktemp("cli")
    for sub in ("missing", "flat", "overlap", "demo", "satellite"):
        (d / sub).mkdir()
    write_geotiff(d / "flat" / "flat.tif", np.full((256, 256), 7.0, dtype=np.float32))
    write_geotiff(d / "flat" / "tex.tif", synthetic_ortho((256, 256), seed=1))
    img = synthetic_ortho((256, 256), seed=2)
    write_geotiff(d / "overlap" / "a.tif", img, transform=Affine(1, 0, 0, 0, -1, 0), crs="EPSG:32633")
    write_geotiff(d / "overlap" / "b.tif", img, transform=Affine(1, 0, 10000, 0, -1, 0), crs="EPSG:32633")
    sched = ("--scheduler", client.scheduler.address)
    demo = d / "demo"
    cases = {
        "missing": ["register", d / "missing/nope.tif", d / "missing/nope2.tif", "--out", d / "missing/o.zarr", *sched],
        "flat": ["register", d / "flat/flat.tif", d / "flat/tex.tif", "--out", d / "flat/o.zarr", "--tile", 128, *sched],
        "overlap": ["register", d / "overlap/a.tif", d / "overlap/b.tif", "--out", d / "overlap/o.zarr", "--tile", 128, *sched],
        "demo": ["demo", "--size", 512, "--tile", 256, "--out", demo / "demo", *sched],
        # the CLI's register on the demo's files
        "demo register": ["register", demo / "demo/base.tif", demo / "demo/distorted.tif", "--out", demo / "again.zarr",
                          "--tile", 256, "--resampling", "cubic", "--no-dense", *sched],
        "synthetic": ["simulate", "satellite", "--ortho", "synthetic", "--out", d / "satellite/syn.zarr", "--seed", 1,
                      "--pixel", 8, *sched],
    }
    return d, run_batch(cases, d)


def test_missing_file(runs):
    d, results = runs
    r, after = results["missing"]
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == f"geocoder: error: {d / 'missing' / 'nope.tif'}: no such file"
    assert "o.zarr" not in listed(after, "missing")


def test_flat_image_is_refused_and_leaves_nothing(runs):
    _, results = runs
    r, after = results["flat"]
    assert r.returncode == 2, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("geocoder: error: ") and "flat.tif" in last and "is constant" in last
    assert "Traceback" not in r.stderr
    assert "o.zarr" not in listed(after, "flat") and leftovers(after, "flat") == []


def test_no_overlap(runs):
    _, results = runs
    r, after = results["overlap"]
    assert r.returncode == 2
    assert "does not overlap" in r.stderr.strip().splitlines()[-1]
    assert "o.zarr" not in listed(after, "overlap") and leftovers(after, "overlap") == []


def test_demo_reports_error_against_truth(runs):
    d, results = runs
    r, after = results["demo"]
    assert r.returncode == 0, r.stderr
    m = re.search(r"displacement field against truth: RMSE ([0-9.]+) px", r.stdout)
    assert m, r.stdout
    assert float(m.group(1)) < 0.1
    assert "demo/demo/registered.zarr/zarr.json" in after
    # the CLI's register on the demo's files prints the summary
    r, _ = results["demo register"]
    assert r.returncode == 0, r.stderr
    assert "tie points:" in r.stdout and "robust RMS" in r.stdout and (d / "demo" / "again.zarr" / "zarr.json").exists()


@pytest.fixture(scope="module")
def quiet_verbose_runs(tmp_path_factory, client):
    """For both places of the flags, four command lines; all eight in one process (see cli_batch)."""
    d = write_synthetic_pair(tmp_path_factory.mktemp("flags"), 256, seed=5, max_displacement=4)
    common = ("--no-dense", "--tile", 128, "--scheduler", client.scheduler.address)
    cases = {}
    for where in ("before", "after"):
        def register(out, *flags):
            args = ["register", d / "base.tif", d / "dist.tif", "--out", d / f"{where}-{out}", *common]
            return [*flags, *args] if where == "before" else [*args, *flags]

        cases.update({f"{where} loud": register("loud.zarr"), f"{where} quiet": register("quiet.zarr", "-q"),
                      f"{where} verbose": register("verbose.zarr", "-v"), f"{where} dashes": register("x.zarr", "--", "-q")})
    return {name: r for name, (r, _) in run_batch(cases, d).items()}


@pytest.mark.data
@pytest.mark.parametrize("where", ["before", "after"])
def test_quiet_and_verbose_before_or_after_the_subcommand(quiet_verbose_runs, where):
    """``geocoder -q register ...`` and ``geocoder register ... -q`` are the same command (issue 16)."""
    loud, quiet, verbose, dashes = (quiet_verbose_runs[f"{where} {k}"] for k in ("loud", "quiet", "verbose", "dashes"))
    for r in (loud, quiet, verbose):
        assert r.returncode == 0, r.stderr
    assert "tiles" in loud.stderr, "progress is shown by default"
    assert "tiles" not in quiet.stderr, "-q: no progress"
    assert len(verbose.stderr.splitlines()) > len(loud.stderr.splitlines()), "-v: the stages' log lines too"
    assert dashes.returncode == 2, "after --, -q is an argument, not the option"


@pytest.fixture(scope="module")
def shared_data_runs(shared_data, tmp_path_factory, client):
    """The command lines of the tests below that read the shared imagery, in one process (see cli_batch)."""
    d = tmp_path_factory.mktemp("cli-data")
    sched = ("--scheduler", client.scheduler.address)
    cases = {
        "ingest": ["ingest", shared_data / "landsat7_rasterio/RGB.byte.tif", d / "rgb.zarr", "--tile", 256, *sched],
        "simulate": ["simulate", "airborne", "--ortho", shared_data / "baviaanskloof/ngi_rgb_byte_1.tif", "--band", 1,
                     "--out", d / "sim.zarr", "--seed", 5, "--sensor", "caesar", "--rows", 300, "--tile", 256, *sched],
        "simulate missing": ["simulate", "satellite", "--ortho", d / "missing.tif", "--out", d / "x.zarr"],
    }
    return d, {name: r for name, (r, _) in run_batch(cases, d).items()}


def test_ingest_command(shared_data_runs):
    d, results = shared_data_runs
    out = d / "rgb.zarr"
    r = results["ingest"]
    assert r.returncode == 0, r.stderr
    assert "3 band(s), 718 x 791 px" in r.stdout
    from geocoder import open_scene

    z = open_scene(out)
    assert z.rio.crs.to_epsg() == 32618 and z.chunks[1][0] == 512 and z.shape == (3, 718, 791)


@pytest.mark.data
def test_simulate_command(shared_data_runs):
    d, results = shared_data_runs
    out = d / "sim.zarr"
    r = results["simulate"]
    assert r.returncode == 0, r.stderr
    assert "truth ground_x/ground_y/ground_z" in r.stdout
    import xarray as xr

    ds = xr.open_zarr(out, consolidated=False)
    assert ds.image.shape[1] == 300 and {"ground_x", "ground_y", "ground_z", "dem"} <= set(ds.variables)
    assert ds.attrs["sensor_class"] == "AirborneScanner" and ds.attrs["seed"] == 5
    r = results["simulate missing"]
    assert r.returncode == 2 and "missing.tif: no such file" in r.stderr


def test_simulate_synthetic_ortho(runs):
    d, results = runs
    r, after = results["synthetic"]
    assert r.returncode == 0, r.stderr
    import xarray as xr

    ds = xr.open_zarr(d / "satellite" / "syn.zarr", consolidated=False)
    assert ds.attrs["sensor_class"] == "LineScanner" and float(ds.image.isnull().mean()) < 0.05
    assert leftovers(after, "satellite") == []


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

    # the three command lines of one environment in one process, one after the other (see cli_batch)
    runs = run_batch({"register": ["register", base, dist, "--out", tmp_path / "option.zarr", "--no-dense", *scheduler],
                      "ingest --tile": ["ingest", base, tmp_path / "flag.zarr", "--tile", 256, *scheduler],
                      "ingest": ["ingest", base, tmp_path / "base.zarr", *scheduler]}, tmp_path, env=env)
    r = runs["register"][0]
    assert r.returncode == 0, r.stderr
    assert tile_of(tmp_path / "option.zarr") == (128, 128)  # not the 384 of one 512 tile
    r = runs["ingest --tile"][0]  # the flag wins (same option)
    assert r.returncode == 0, r.stderr
    assert xr.open_zarr(tmp_path / "flag.zarr", consolidated=False).image.data.chunksize == (1, 256, 256)
    r = runs["ingest"][0]
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().endswith("384 x 384 px, tile 128")
    assert xr.open_zarr(tmp_path / "base.zarr", consolidated=False).image.data.chunksize == (1, 128, 128)
    r = run("ingest", base, tmp_path / "bad.zarr", *scheduler, env=dict(os.environ, DASK_GEOCODER__TILE="100"))
    assert r.returncode == 2 and "geocoder.tile must be a positive multiple of 64" in r.stderr.strip().splitlines()[-1]
