"""Compile the numba kernels once, into numba's on-disk cache, before many processes need them.

Every kernel is compiled with ``cache=True``; a process that finds no cache entry compiles the
kernel itself (about 95 s of CPU for the dense job's kernels), and processes that start together
on a fresh install all do so at the same time. Running :func:`compile_kernels` once first (when
an image is built, before a test session, before a cluster's workers start) leaves every later
process only the loading (about 1.5 s).

``python -m geocoder.warmup`` does the same from a shell.
"""

from __future__ import annotations

import tempfile
import time
import warnings

import numpy as np


def compile_kernels(*, size: int = 256, tile: int = 128) -> float:
    """Run the built-in demo job (dense matching on) on a tiny scene in this process, and every
    resampling method once.

    The job runs on a one-thread in-process Dask cluster, so each kernel is compiled once and its
    cache entry written before any other process looks for it.

    Parameters
    ----------
    size, tile : int
        Side of the demo scene and of its tiles in pixels; the default makes a 2 x 2 tiling, so
        the halo exchange, the lattice's rounds and the every-pixel pass all run.

    Returns
    -------
    float
        Seconds taken (compiling, or loading from the cache when it is already there).
    """
    from distributed import Client, LocalCluster

    from .demo import run_demo

    start = time.perf_counter()
    warm_small_kernels()  # the job resamples with one method only
    with warnings.catch_warnings(), tempfile.TemporaryDirectory(prefix="geocoder-warmup-") as directory, \
            LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster, set_as_default=False) as client:
        warnings.simplefilter("ignore")  # the demo's raw partner has no georeference, as it should not
        run_demo(size=size, tile=tile, directory=directory, client=client)
    return time.perf_counter() - start


def warm_small_kernels() -> None:
    """Run the interest operator and every resampling method once on a 32 x 32 image (compiles
    them, or loads them from numba's cache): what a worker runs first on any job."""
    from .kernels.interest import detect
    from .kernels.resample import METHODS, sample

    image = np.random.default_rng(0).normal(size=(32, 32)).astype(np.float32)
    for method in METHODS:
        sample(image, np.array([3.5]), np.array([4.25]), method=method)
    detect(image, cell=16)


if __name__ == "__main__":
    print(f"geocoder kernels compiled (or found in numba's cache) in {compile_kernels():.0f} s")
