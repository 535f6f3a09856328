"""The same job on the embedded cluster and on `geocoder cluster up` (plain and TLS), with a
worker killed in the middle of dense matching, and with the whole job killed and rerun.

Every run must give the output of the undisturbed embedded run, bit for bit.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from distributed import Client
from pairs import assert_identical, load_output, write_synthetic_pair
from test_mosaic import block  # noqa: F401 (the module's fixture: the mosaic block's files)

from geocoder import register
from geocoder.mosaic import mosaic
from geocoder.pipeline.register import job_directory

pytestmark = pytest.mark.cluster

SIZE, TILE = 768, 256
GEOCODER = [sys.executable, "-m", "geocoder.cli"]


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory) -> Path:
    return write_synthetic_pair(tmp_path_factory.mktemp("pair"), SIZE, seed=5, max_displacement=12.0)


@pytest.fixture(scope="module")
def reference(pair_dir, client) -> dict[str, np.ndarray]:
    """The undisturbed job on the embedded default (a LocalCluster of worker processes)."""
    out = pair_dir / "reference.zarr"
    register(pair_dir / "base.tif", pair_dir / "dist.tif", out=out, tile=TILE, client=client)
    return load_output(out)


def cluster_up(directory: Path, *extra: str) -> dict:
    r = subprocess.run([*GEOCODER, "cluster", "up", "--workers", "2", "--dir", str(directory), *extra],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "dashboard http://" in r.stdout
    return json.loads((directory / "cluster.json").read_text())


def cluster_down(directory: Path) -> None:
    r = subprocess.run([*GEOCODER, "cluster", "down", "--dir", str(directory)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert not (directory / "cluster.json").exists()


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    d = tmp_path_factory.mktemp("cluster")
    info = cluster_up(d)
    try:
        yield d / "cluster.json", info
    finally:
        cluster_down(d)
    for pid in [info["scheduler_pid"], *info["worker_pids"]]:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def run_cli(pair_dir: Path, out: Path, scheduler: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*GEOCODER, "register", str(pair_dir / "base.tif"), str(pair_dir / "dist.tif"), "--out", str(out),
         "--tile", str(TILE), "--scheduler", str(scheduler)],
        capture_output=True, text=True, timeout=900,
    )


def finished_tiles(out: Path, stage: str) -> int:
    d = Path(job_directory(str(out))) / "tiles" / stage
    return len(list(d.glob("*.pkl"))) if d.is_dir() else 0


def test_cluster_up_runs_the_same_job_bit_for_bit(pair_dir, reference, launched):
    cluster_file, info = launched
    out = pair_dir / "on-cluster.zarr"
    r = run_cli(pair_dir, out, cluster_file)
    assert r.returncode == 0, r.stderr
    assert f"Dask dashboard: {info['dashboard']}" in r.stderr
    for phase in ("interest points", "correspondence", "dense matching", "resampling"):
        assert phase in r.stderr
    assert_identical(load_output(out), reference)
    assert not Path(job_directory(str(out))).exists()


def test_mosaic_on_cluster_up_is_the_embedded_mosaic(block, client, launched, tmp_path):  # noqa: F811
    """The mosaic (two scenes of test_mosaic's block) on a `cluster up` cluster: the embedded run's output."""
    cluster_file, _ = launched
    d, paths = block
    here = mosaic(paths[:2], reference=d / "ortho.tif", out=tmp_path / "embedded.zarr", tile=128, client=client)
    there = mosaic(paths[:2], reference=d / "ortho.tif", out=tmp_path / "cluster.zarr", tile=128,
                   scheduler=str(cluster_file))
    for name in ("mosaic", "source"):
        assert np.array_equal(there[name].values, here[name].values, equal_nan=True), name
    for name in ("models", "radiometry", "scenes"):
        assert there.attrs[name] == here.attrs[name], name


def test_worker_killed_during_dense_matching(pair_dir, reference, launched):
    cluster_file, _ = launched
    out = pair_dir / "worker-killed.zarr"
    errors: list[BaseException] = []

    def job():
        try:
            register(pair_dir / "base.tif", pair_dir / "dist.tif", out=out, tile=TILE, scheduler=str(cluster_file))
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    t = threading.Thread(target=job)
    t.start()
    killed = None
    with Client(json.loads(cluster_file.read_text())["address"], set_as_default=False, timeout=30) as c:
        deadline = time.time() + 600
        while killed is None and t.is_alive() and time.time() < deadline:
            busy = [w for w, keys in c.processing().items() if any("grow-" in str(k) for k in keys)]
            if busy and finished_tiles(out, "dense-r0") >= 1:
                pid = c.run(os.getpid, workers=[busy[0]])[busy[0]]
                os.kill(pid, signal.SIGKILL)
                killed = pid
            time.sleep(0.05)
        t.join(timeout=900)
        assert killed is not None, "the job never reached dense matching with a busy worker"
        assert not errors, errors
        c.wait_for_workers(2, timeout=120)  # the nanny restarted the killed worker
        assert killed not in c.run(os.getpid).values()
    assert_identical(load_output(out), reference)


def test_killed_job_resumes_and_recomputes_few_tiles(pair_dir, reference, launched):
    cluster_file, _ = launched
    out = pair_dir / "resumed.zarr"
    cmd = [*GEOCODER, "register", str(pair_dir / "base.tif"), str(pair_dir / "dist.tif"), "--out", str(out),
           "--tile", str(TILE), "--scheduler", str(cluster_file)]
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 600
    while finished_tiles(out, "dense-r0") < 2 and first.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert first.poll() is None, "the job ended before it could be killed"
    first.send_signal(signal.SIGKILL)
    first.wait()
    assert not out.exists(), "a killed job must not leave an output store"
    assert Path(job_directory(str(out))).is_dir()
    r = run_cli(pair_dir, out, cluster_file)
    assert r.returncode == 0, r.stderr
    m = re.search(r"resumed: (\d+) of (\d+) tile tasks finished earlier, at most (\d+) \(([\d.]+)%\) computed again", r.stdout)
    assert m, r.stdout
    print(m[0])
    skipped, total, again, percent = int(m[1]), int(m[2]), int(m[3]), float(m[4])
    assert skipped > total / 2
    assert 0 < again and percent < 10
    assert_identical(load_output(out), reference)
    assert not Path(job_directory(str(out))).exists()


def test_tls_cluster_runs_the_job_and_refuses_clients_without_certificates(pair_dir, reference, tmp_path):
    info = cluster_up(tmp_path, "--tls")
    try:
        assert info["address"].startswith("tls://")
        out = pair_dir / "tls.zarr"
        register(pair_dir / "base.tif", pair_dir / "dist.tif", out=out, tile=TILE, scheduler=str(tmp_path / "cluster.json"))
        assert_identical(load_output(out), reference)
        with pytest.raises((OSError, TimeoutError, TypeError)):
            Client(info["address"], timeout=5, set_as_default=False)
    finally:
        cluster_down(tmp_path)
