"""Shared fixtures: a real LocalCluster with worker processes, the shared imagery, pairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from distributed import Client

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile the numba kernels once, before xdist's workers and the tests' clusters start.

    Otherwise every process that starts before the cache is written (both xdist workers, each
    one's LocalCluster workers, the CLI's subprocesses) compiles the same kernels at once.
    """
    if hasattr(session.config, "workerinput"):
        return  # an xdist worker: its controller has done it
    from geocoder.warmup import compile_kernels

    compile_kernels()


@pytest.fixture(scope="session")
def client():
    """Two worker processes with one thread each, as on the CI machine: geocoder's own local
    cluster (:func:`geocoder.runtime.local_cluster`, its workers' environment and configuration;
    with Dask's defaults glibc handed memory back to the system after every task, and the
    mosaic tests spent 21 % of their CPU time in the kernel)."""
    from geocoder.runtime import local_cluster

    with local_cluster(2) as cluster, Client(cluster) as c:
        yield c


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED.is_dir():
        pytest.fail(f"the shared imagery is missing: expected {SHARED} beside the project")
    return SHARED


def read_band(path: Path, band: int = 1, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """One band of a GeoTIFF as float64 (rows, cols), optionally a (row0, row1, col0, col1) crop."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(path) as src:
        win = None if window is None else Window(window[2], window[0], window[3] - window[2], window[1] - window[0])
        return src.read(band, window=win).astype(np.float64)


@pytest.fixture(scope="session")
def s2_turbulence(shared_data, tmp_path_factory, client):
    """A real S2 crop (256 px) warped with scan-line turbulence of known truth (seed 21), registered on
    the test cluster (tile 128), and the report of its store against the truth.

    ``test_report.py`` and ``test_report_browser.py`` look at the same run and the same page: a
    process that runs both computes them once. Returns ``(directory, store, PairFiles, report directory)``;
    the report directory is the return value of :func:`geocoder.report`. Read-only for the tests.
    """
    from pairs import real_pair

    from geocoder import register, report

    d = tmp_path_factory.mktemp("s2-turbulence")
    files = real_pair(shared_data, d, which="s2", size=256, seed=21, turbulence=(1.0, 3.0))
    out = d / "out.zarr"
    register(files.base, files.distorted, out=out, tile=128, client=client, show_progress=False)
    where = report(out, d / "report", truth=(files.pair.dx, files.pair.dy))
    return d, out, files, where
