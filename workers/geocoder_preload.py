"""Dask worker preload: ``dask worker --preload workers/geocoder_preload.py SCHEDULER``.

Pins numeric libraries to one thread (parallelism comes from Dask tasks), compiles the
numba kernels once per worker process so the first tiles are not slowed by compilation,
and logs the geocoder version the worker runs.
"""

from __future__ import annotations

import logging
import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

log = logging.getLogger("geocoder.worker")


def warm_kernels() -> None:
    """Run every numba kernel once on a tiny input (compiles or loads the cache)."""
    import numpy as np

    from geocoder.kernels.interest import detect
    from geocoder.kernels.resample import METHODS, sample

    img = np.random.default_rng(0).normal(size=(32, 32)).astype(np.float32)
    for method in METHODS:
        sample(img, np.array([3.5]), np.array([4.25]), method=method)
    detect(img, cell=16)


def dask_setup(worker) -> None:
    import geocoder

    warm_kernels()
    log.info("geocoder %s ready on %s", geocoder.__version__, getattr(worker, "address", "?"))
