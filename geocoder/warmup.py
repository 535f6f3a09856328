"""Compile the numba kernels once, into numba's on-disk cache, before many processes need them.

Every kernel is compiled with ``cache=True``; a process that finds no cache entry compiles the
kernel itself (about 95 s of CPU for the dense job's kernels), and processes that start together
on a fresh install all do so at the same time. Running :func:`compile_kernels` once first (when
an image is built, before a test session, before a cluster's workers start) leaves every later
process only the loading (about 1.5 s).

Numba compiles one kernel at a time per process, and three kernels hold two thirds of the time
(the region growing's ``grow`` ~35 s, the every-pixel pass's ``_solve_window`` ~16 s, the
post-filter's ~15 s). :func:`compile_kernels` therefore compiles ``grow`` in a second process
while this one compiles the other two and the small kernels, and only then runs the demo job,
which finds all three in the cache and compiles what is left (72 s instead of 104 on two
cores). Each part calls the kernels' own Python entry points, which fix the argument types,
so the job uses the very signatures the parts compiled (``tests/test_warmup.py`` checks it).

``python -m geocoder.warmup`` does the same from a shell.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

#: The parts :func:`compile_kernels` may hand to another process (``python -m geocoder.warmup --part NAME``).
PARTS = ("growth",)


def compile_kernels(*, size: int = 256, tile: int = 128, parallel: bool = True) -> float:
    """Compile every kernel of the built-in demo job (dense matching on) into numba's cache.

    The region growing's kernel is compiled in a second Python process (``parallel``), the
    every-pixel pass, the post-filter and the small kernels in this one; then the demo job runs
    on a one-thread in-process Dask cluster and compiles the rest, each kernel once, before any
    other process looks for it.

    Parameters
    ----------
    size, tile : int
        Side of the demo scene and of its tiles in pixels; the default makes a 2 x 2 tiling, so
        the halo exchange, the lattice's rounds and the every-pixel pass all run.
    parallel : bool
        Compile the region growing in a second process (False: all of it in this one).

    Returns
    -------
    float
        Seconds taken (compiling, or loading from the cache when it is already there).
    """
    from distributed import Client, LocalCluster

    from .demo import run_demo

    start = time.perf_counter()
    helper = None
    if parallel:
        helper = subprocess.Popen([sys.executable, "-m", "geocoder.warmup", "--part", "growth"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    else:
        warm_growth_kernels()
    try:
        warm_small_kernels()
        warm_field_kernels()
    finally:
        # the demo needs ``grow`` from the cache; if the helper failed, the demo compiles it
        if helper is not None:
            helper.wait()
    with warnings.catch_warnings(), tempfile.TemporaryDirectory(prefix="geocoder-warmup-") as directory, \
            LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster, set_as_default=False) as client:
        warnings.simplefilter("ignore")  # the demo's raw partner has no georeference, as it should not
        run_demo(size=size, tile=tile, directory=directory, client=client)
    return time.perf_counter() - start


def warm_small_kernels() -> None:
    """Run the interest operator, every resampling method and the correlation's patch sampling
    once on a 32 x 32 image (compiles them, or loads them from numba's cache): what a worker runs
    first on any job."""
    from .kernels.interest import detect
    from .kernels.resample import METHODS, sample, sample_affine_patches

    image = np.random.default_rng(0).normal(size=(32, 32)).astype(np.float32)
    for method in METHODS:
        sample(image, np.array([3.5]), np.array([4.25]), method=method)
    sample_affine_patches(image, np.array([8.5]), np.array([9.25]), np.eye(2)[None], np.zeros((1, 2)))
    detect(image, cell=16)


def _pair(size: int = 96, shift: tuple[float, float] = (0.3, 0.4)) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random texture (float32) and a copy shifted by ``shift`` (rows, columns)."""
    from scipy import ndimage

    noise = np.random.default_rng(1).normal(size=(size, size))
    base = ndimage.gaussian_filter(noise, 1.5).astype(np.float32)
    return base, ndimage.shift(base, shift, order=3, mode="nearest").astype(np.float32)


def warm_growth_kernels() -> None:
    """Grow matches from one seed on a 96 x 96 pair, on a lattice as the dense stage does (compiles
    the region growing's kernel, or loads it)."""
    from .kernels.alsc import F_A11, F_A22, F_GAIN, F_X, F_Y, NPARAMS
    from .match.grow import NFIELDS, UNVISITED, grow_window, seed_rows
    from .pipeline.dense import DenseOptions

    opts = DenseOptions()
    base, dist = _pair()
    h, w = base.shape
    k = opts.col_step
    start = np.zeros((1, NPARAMS))
    start[0, F_X], start[0, F_Y] = 48.0 - 0.4, 48.0 - 0.3
    start[0, F_A11], start[0, F_A22], start[0, F_GAIN] = 1.0, 1.0, 1.0
    params = np.full((h, -(-w // k), NFIELDS), np.nan)
    code = np.full((h, w), UNVISITED, dtype=np.int8)
    grow_window(base, dist, seed_rows(np.array([48]), np.array([48]), start), params, code, (8, h - 8, 30, w - 30),
                options=opts.growth_alsc, step=opts.step, lattice_origin=(0, 0), neighbours=opts.neighbours,
                max_tries=opts.max_tries, col_step=k, row_step=opts.lattice_rows, param_stride=k)


def warm_field_kernels() -> None:
    """Match every pixel of a 96 x 96 pair from a field and post-filter the result (compiles the
    every-pixel pass's kernels and the post-filter's, or loads them)."""
    from .match.densify import densify_window
    from .pipeline.dense import DenseOptions
    from .quality.postfilter import postfilter
    from .status import Status

    opts = DenseOptions()
    base, dist = _pair()
    h, w = base.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    res = densify_window(base, dist, cols - 0.4, rows - 0.3, np.ones((h, w), bool), (8, h - 8, 30, w - 30),
                         options=opts.alsc, iterations=opts.densify_iterations, tol=opts.densify_tol,
                         gradients=opts.densify_gradients)
    matched = res.code == 0
    status = np.where(matched, Status.MATCHED, Status.NO_TEXTURE).astype(np.uint8)
    postfilter(np.where(matched, res.x, np.nan).astype(np.float32), np.where(matched, res.y, np.nan).astype(np.float32),
               status)


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m geocoder.warmup", description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", choices=PARTS, help="compile only this part (what compile_kernels hands to a helper)")
    args = parser.parse_args(argv)
    if args.part == "growth":
        warm_growth_kernels()
        return
    print(f"geocoder kernels compiled (or found in numba's cache) in {compile_kernels():.0f} s")


if __name__ == "__main__":
    main()
