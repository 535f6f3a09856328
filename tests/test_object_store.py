"""Jobs whose inputs, working files and output live on an object store (S3 API).

A moto S3 server runs in this process; the worker processes and the CLI reach it over HTTP
through fsspec's configuration (``FSSPEC_S3_ENDPOINT_URL``), as a real cluster reaches S3.
Object stores have no rename: these tests hold the job to the guarantees the local disk
gives (identical output, resumable, nothing that looks complete before it is).
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from distributed import Client
from pairs import assert_identical, load_output, write_synthetic_pair

from geocoder import ingest, register, storage
from geocoder.pipeline.register import job_directory
from geocoder.runtime import local_cluster
from geocoder.testing import local_s3

pytestmark = pytest.mark.cluster

SIZE, TILE = 512, 256
BUCKET = "geocoder-test"
GEOCODER = [sys.executable, "-m", "geocoder.cli"]


@pytest.fixture(scope="module")
def s3():
    """A local S3 server; the environment points fsspec and GDAL (here and in child processes) at it."""
    with local_s3(BUCKET) as url:
        yield url


def fsspec_fs(url: str):
    import fsspec

    return fsspec.core.url_to_fs(url)


@pytest.fixture(scope="module")
def s3_client(s3):
    """Worker processes started after the environment names the S3 endpoint."""
    with local_cluster(2) as cluster, Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory) -> Path:
    return write_synthetic_pair(tmp_path_factory.mktemp("s3pair"), SIZE, seed=11, max_displacement=10.0)


@pytest.fixture(scope="module")
def reference(pair_dir, s3_client) -> dict[str, np.ndarray]:
    out = pair_dir / "reference.zarr"
    register(pair_dir / "base.tif", pair_dir / "dist.tif", out=out, tile=TILE, client=s3_client)
    return load_output(str(out))


@pytest.fixture(scope="module")
def reference_no_dense(pair_dir, s3_client) -> dict[str, np.ndarray]:
    out = pair_dir / "reference-no-dense.zarr"
    register(pair_dir / "base.tif", pair_dir / "dist.tif", out=out, tile=TILE, client=s3_client, dense=False)
    return load_output(str(out))


@pytest.fixture(scope="module")
def s3_inputs(pair_dir, s3, s3_client) -> tuple[str, str]:
    """Both scenes ingested to Zarr stores on the object store (Python API and CLI)."""
    base, dist = f"{s3}/inputs/base.zarr", f"{s3}/inputs/dist.zarr"
    ingest(str(pair_dir / "base.tif"), base, tile=TILE, client=s3_client)
    r = subprocess.run([*GEOCODER, "ingest", str(pair_dir / "dist.tif"), dist, "--tile", str(TILE),
                        "--scheduler", s3_client.scheduler.address], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    fs, path = fsspec_fs(f"{s3}/inputs")
    fs.invalidate_cache()
    names = {p.rsplit("/", 1)[-1] for p in fs.ls(path, detail=False)}
    assert {"base.zarr", "dist.zarr"} <= names and not [n for n in names if ".partial-" in n], names
    return base, dist


def test_storage_primitives_on_local_disk_and_object_store(s3, tmp_path):
    for root in (str(tmp_path / "root"), f"{s3}/primitives"):
        f = storage.join(root, "a", "x.bin")
        assert not storage.exists(f)
        with pytest.raises(FileNotFoundError):
            storage.read_bytes(f)
        storage.write_bytes(f, b"one")
        first = storage.identity(f)
        storage.write_bytes(f, b"second")
        assert storage.read_bytes(f) == b"second"
        assert storage.identity(f) != first, "a rewritten input must change the job's fingerprint"
        assert storage.list_names(storage.join(root, "a")) == {"x.bin"}
        assert storage.list_names(storage.join(root, "missing")) == set()
        storage.remove(storage.join(root, "a"))
        assert not storage.exists(f)
        storage.remove(storage.join(root, "a"))  # nothing there: no error


def test_commit_publishes_the_store_only_with_its_root_metadata(s3):
    final = f"{s3}/commit/out.zarr"
    for value in (1.0, 2.0):  # the second commit replaces the first store
        tmp = storage.temporary_sibling(final)
        # numpy-backed: written by this process (a default Client's workers may not know the endpoint)
        xr.Dataset({"v": (("y", "x"), np.full((40, 30), value))}).to_zarr(
            tmp, zarr_format=3, consolidated=False, encoding={"v": {"chunks": (10, 10)}})
        storage.remove(storage.join(final, storage.ROOT_METADATA))
        storage.remove(final)
        storage.copy_store_body(tmp, final)  # what a job killed in the middle of the commit leaves
        assert not storage.is_store(final)
        with pytest.raises(Exception):
            xr.open_zarr(final, consolidated=False)
        storage.commit_store(tmp, final)
        assert not storage.exists(tmp)
        assert storage.is_store(final)
        np.testing.assert_array_equal(xr.open_zarr(final, consolidated=False, chunks=None).v.values, value)


def test_geotiff_on_the_object_store_reads_like_the_local_file(s3, pair_dir, s3_client):
    from geocoder import open_scene

    url = f"{s3}/tiff/base.tif"
    storage.write_bytes(url, (pair_dir / "base.tif").read_bytes())
    remote = open_scene(url, chunks=TILE)
    local = open_scene(pair_dir / "base.tif", chunks=TILE)
    assert remote.rio.crs == local.rio.crs and remote.rio.transform() == local.rio.transform()
    np.testing.assert_array_equal(s3_client.compute(remote.data).result(), local.values)


def test_register_on_the_object_store_matches_local_disk(s3, s3_inputs, reference_no_dense, s3_client):
    """The polynomial job (the dense one on the object store runs, killed and resumed, below)."""
    out = f"{s3}/outputs/registered.zarr"
    ds = register(*s3_inputs, out=out, tile=TILE, client=s3_client, dense=False)
    assert ds.sizes["x"] == SIZE
    assert_identical(load_output(out), reference_no_dense)
    assert not storage.exists(job_directory(out)), "the job's working files are removed after the commit"


def test_killed_job_on_the_object_store_resumes(s3, s3_inputs, reference, s3_client):
    """The dense job on the object store, killed mid dense matching: the rerun's output is the local one."""
    out = f"{s3}/outputs/resumed.zarr"
    tiles = storage.join(job_directory(out), "tiles", "dense-r0")
    cmd = [*GEOCODER, "register", *s3_inputs, "--out", out, "--tile", str(TILE), "--scheduler", s3_client.scheduler.address]
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 600
    while len(storage.list_names(tiles)) < 2 and first.poll() is None and time.time() < deadline:
        time.sleep(0.1)
    assert first.poll() is None, "the job ended before it could be killed"
    first.send_signal(signal.SIGKILL)
    first.wait()
    assert not storage.is_store(out), "a killed job must not leave an output store"
    assert storage.exists(storage.join(job_directory(out), "manifest.json"))
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    m = re.search(r"resumed: (\d+) of (\d+) tile tasks finished earlier, at most (\d+) \(([\d.]+)%\) computed again", r.stdout)
    assert m, r.stdout
    print(m[0])
    assert int(m[1]) > int(m[2]) / 2 and float(m[4]) < 10
    assert_identical(load_output(out), reference)
    assert not storage.exists(job_directory(out))


def test_unwritable_bucket_is_named_in_the_error(s3, pair_dir, s3_client):
    from geocoder.errors import InputError

    with pytest.raises(InputError, match="no-such-bucket"):
        register(pair_dir / "base.tif", pair_dir / "dist.tif", out="s3://no-such-bucket/x.zarr", tile=TILE, client=s3_client)
