"""The built-in demo: a synthetic scene, a warped partner with known truth, registered."""

from __future__ import annotations

import os

import numpy as np
from affine import Affine

from .outputs import claim_directory
from .pipeline.register import RegisterSummary, register
from .scene import write_geotiff
from .simulate.texture import synthetic_ortho
from .simulate.warp import make_pair


def run_demo(*, size: int = 1024, seed: int = 0, directory: str = "geocoder-demo", tile: int | None = None,
             scheduler: str | None = None, client=None) -> list[str]:
    """Make ``base.tif`` (georeferenced) and ``distorted.tif`` (raw, warped by an affine +
    quadratic field of up to 15 px, new noise, gain and offset), register them, and
    report the error of the displacement field against the known truth.

    ``directory`` must be new, empty or an earlier demo's (nothing else is written into).
    ``tile`` goes to :func:`geocoder.register` (None: the option ``tile``, 512 unless set).
    Returns the lines to print.
    """
    directory = claim_directory(directory, product="demo")
    margin = 48
    source = synthetic_ortho((size + 2 * margin, size + 2 * margin), seed=seed)
    pair = make_pair(source, shape=(size, size), seed=seed, max_displacement=15.0, margin=margin)
    base_path = os.path.join(directory, "base.tif")
    dist_path = os.path.join(directory, "distorted.tif")
    out = os.path.join(directory, "registered.zarr")
    transform = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 4000000.0)
    write_geotiff(base_path, pair.base, transform=transform, crs="EPSG:32633")
    write_geotiff(dist_path, pair.distorted)
    ds = register(base_path, dist_path, out=out, tile=tile, scheduler=scheduler, client=client, overwrite=True)
    import json

    summary = RegisterSummary(**json.loads(ds.attrs["summary"]))
    dx, dy = ds.dx.values, ds.dy.values
    inside = ds.status.values > 0
    err = np.hypot(dx - pair.dx, dy - pair.dy)[inside]
    tp = __import__("xarray").open_zarr(out, group="tiepoints", consolidated=False)
    bx, by = tp.base_x.values, tp.base_y.values
    tx, ty = pair.field.displacement(bx, by)
    tperr = np.hypot(tp.dist_x.values - bx - tx, tp.dist_y.values - by - ty)
    return [
        f"demo scene: {size} x {size} px, seed {seed}; truth |d| up to {np.hypot(pair.dx, pair.dy).max():.1f} px",
        *summary.lines(),
        f"tie points against truth: RMS {np.sqrt(np.mean(tperr**2)):.3f} px, max {tperr.max():.3f} px",
        f"displacement field against truth: RMSE {np.sqrt(np.mean(err**2)):.4f} px, max {err.max():.4f} px over {inside.mean():.1%} of the base",
        f"wrote {out} (registered, dx, dy, status, tiepoints)",
    ]
