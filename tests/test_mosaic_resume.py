"""A mosaic job killed part-way resumes where it stopped, and never reuses work of changed inputs.

Two scenes of the 2 x 2 block of ``test_mosaic`` (one overlapping pair), through the real
command line killed with SIGKILL (a crash: no clean-up, a stale lock) once the job's directory
shows finished tile files, then run again. The re-run must skip what was finished (the
summary's ``job`` counters) and write the same pixels as an uninterrupted run; a scene
replaced at the same path between the two must start the job afresh. Whether the job is still
running when its files appear is not assumed: a job that finished first is tolerated.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr
from test_mosaic import block  # noqa: F401 (the module's fixture: the block's files)

from geocoder.mosaic import mosaic
from geocoder.scene import write_geotiff

pytestmark = pytest.mark.cluster

TILE = 128
JOB = ".m.zarr.geocoder-job"


def run_and_kill(args: list, cwd: Path, pattern: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``geocoder mosaic ARGS --out m.zarr`` and SIGKILL it once a file matching ``pattern``
    (a glob under its job directory) exists, or let it be if it finished first."""
    p = subprocess.Popen([sys.executable, "-m", "geocoder.cli", "-q", "mosaic", *map(str, args), "--out", "m.zarr"],
                         cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + timeout
    while p.poll() is None and not any((cwd / JOB).glob(pattern)) and time.monotonic() < deadline:
        time.sleep(0.05)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGKILL)
    out, err = p.communicate(timeout=60)
    assert p.returncode in (0, -signal.SIGKILL), err
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def tile_files(cwd: Path) -> int:
    """Finished tile results in the job's directory."""
    return sum(1 for _ in (cwd / JOB).glob("tiles/*/*.pkl"))


def ingest_tiles(*files: Path) -> int:
    """Tiles of the inputs' ingest (counted by the job, stored as Zarr rather than as tile files)."""
    n = 0
    for path in files:
        with rasterio.open(path) as f:
            n += math.ceil(f.height / TILE) * math.ceil(f.width / TILE)
    return n


def pixels(ds) -> dict[str, np.ndarray]:
    return {"mosaic": ds.mosaic.values, "source": ds.source.values}


def assert_same_pixels(ds, expected: dict[str, np.ndarray]) -> None:
    got = pixels(ds)
    for name, value in expected.items():
        assert np.array_equal(got[name], value, equal_nan=True), f"{name} differs from the uninterrupted run"


@pytest.fixture(scope="module")
def scenes(block):  # noqa: F811
    d, paths = block
    return d / "ortho.tif", paths[:2]


@pytest.fixture(scope="module")
def uninterrupted(scenes, client, tmp_path_factory) -> tuple[dict[str, np.ndarray], dict]:
    """The pixels and the job counters of the job run once, start to end."""
    reference, paths = scenes
    ds = mosaic(paths, reference=reference, out=tmp_path_factory.mktemp("fresh") / "m.zarr", tile=TILE, client=client)
    return pixels(ds), json.loads(ds.attrs["summary"])["job"]


def test_killed_mosaic_resumes_and_gives_the_same_output(scenes, uninterrupted, client, tmp_path):
    reference, paths = scenes
    expected, fresh = uninterrupted
    assert not fresh["resumed"] and fresh["skipped"] == 0 and fresh["run"] == fresh["tile_tasks"] > 0
    args = [*paths, "--reference", reference, "--tile", TILE, "--scheduler", client.scheduler.address]
    # killed once matching of the pair has begun (control points of both scenes finished) ...
    first = run_and_kill(args, tmp_path, "tiles/ties-*/*.pkl")
    runs = [first]
    if first.returncode != 0:
        assert not (tmp_path / "m.zarr").exists() and (tmp_path / JOB / "manifest.json").exists()
        # ... and again once output tiles are written (the adjustment and the seams finished)
        runs.append(run_and_kill(args, tmp_path, "tiles/mosaic/*.pkl"))
    if runs[-1].returncode == 0:  # a job that finished before it was killed: its summary tells the resume
        ds = xr.open_zarr(tmp_path / "m.zarr", decode_coords="all", consolidated=False)
        with_resume = json.loads(ds.attrs["summary"])
        assert ("resumed:" in runs[-1].stdout) == (first.returncode != 0)
    else:
        finished = tile_files(tmp_path)
        assert finished > 0 and not (tmp_path / "m.zarr").exists()
        assert any((tmp_path / JOB).glob("tiles/mosaic/*.pkl"))  # output tiles among the work kept
        ds = mosaic(paths, reference=reference, out=tmp_path / "m.zarr", tile=TILE, client=client)
        with_resume = json.loads(ds.attrs["summary"])
        # exactly the tiles finished before the kill are skipped: the stored results, and the ingest's
        assert with_resume["job"]["skipped"] == finished + ingest_tiles(reference, *paths)
        assert not (tmp_path / JOB).exists()
    job = with_resume["job"]
    if first.returncode != 0:
        assert job["resumed"] and 0 < job["skipped"] < job["tile_tasks"] == fresh["tile_tasks"]
        assert job["run"] + job["skipped"] == job["tile_tasks"]
    assert_same_pixels(ds, expected)


def test_scene_replaced_at_the_same_path_is_not_reused(scenes, uninterrupted, client, tmp_path):
    reference, paths = scenes
    expected, fresh = uninterrupted
    replaced = tmp_path / "scene1.tif"
    with rasterio.open(paths[1]) as f:  # an older version of scene 1: other grey values, the same shape
        write_geotiff(replaced, 1.3 * f.read().astype(np.float32) + 5.0)
    args = [paths[0], replaced, "--reference", reference, "--tile", TILE, "--scheduler", client.scheduler.address]
    # killed once the scenes are ingested and their first interest points found
    first = run_and_kill(args, tmp_path, "tiles/*/*.pkl")
    shutil.copyfile(paths[1], replaced)  # the scene as it is now, at the same path
    ds = mosaic([paths[0], replaced], reference=reference, out=tmp_path / "m.zarr", tile=TILE, client=client,
                overwrite=first.returncode == 0)
    job = json.loads(ds.attrs["summary"])["job"]
    assert not job["resumed"] and job["skipped"] == 0 and job["run"] == fresh["tile_tasks"]
    assert_same_pixels(ds, expected)
