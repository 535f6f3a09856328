"""Mosaic sensor models against truth: polynomial / line scanner / RPC, on flat ground and over relief.

A ``grid x grid`` block of push-broom scenes (:func:`geocoder.simulate.linescanner_block.line_scanner_block`)
over a crop of the real Sentinel-2 image in ../shared/data (10 m) and a fractal DEM, every
scene rolled 0.35 rad off nadir (alternate columns from opposite sides), carrying its
navigation (position ~15 m and attitude ~1e-5 rad off the truth) as a line-scanner tag and as
RPCs. Two blocks: flat ground (a DEM of zeros) and ``--relief`` metres of relief (pixels
displaced by up to ``0.37 relief / 10`` px, differently in neighbouring scenes). Every mosaic
gets the DEM (``dem=``); control on every scene.

Columns: geometric error of every output pixel against the truth (RMSE, max; output pixels:
the scene position the mosaic sampled, through the true ray onto the true DEM, against the
pixel), the geometric mismatch of the two scenes along the seamlines (RMS; both scenes'
positions of every seam pixel through their true rays), sigma0 of the block adjustment, wall
time of the mosaic call.

Run:  python benchmarks/bench_mosaic_models.py [--size 256] [--grid 2] [--relief 300] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from distributed import Client, LocalCluster

from geocoder.mosaic import load_models, mosaic, scene_positions
from geocoder.mosaic.diagnostics import seam_errors
from geocoder.quality.accuracy import mosaic_errors
from geocoder.simulate.linescanner_block import line_scanner_block

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
S2 = DATA / "s2_arosics" / "ref_S2A_20160608T153121_T33UUU_sub.tif"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--grid", type=int, default=2)
    ap.add_argument("--relief", type=float, default=300.0)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    size, grid = args.size, args.grid
    ext = int(size * (0.6 * (grid - 1) + 1.6)) + 64
    with rasterio.open(S2) as src:
        r0, c0 = 300, 900  # east of the no-data wedge
        ortho = src.read(1, window=((r0, r0 + ext), (c0, c0 + ext))).astype(np.float32)
        transform = src.transform * Affine.translation(c0, r0)
        crs = src.crs.to_wkt()
    rows = []
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, \
            Client(cl) as c:
        for block, relief in (("flat", 0.0), (f"relief {args.relief:g} m", args.relief)):
            work = Path(tempfile.mkdtemp(prefix="bench-mosaic-models-"))
            scenes, paths, ortho_path, dem_path = line_scanner_block(work, ortho, transform, crs, relief=relief, size=size,
                                                                      grid=grid)
            for kind in ("polynomial", "linescanner", "rpc"):
                out = work / f"{kind}.zarr"
                t0 = time.perf_counter()
                ds = mosaic(paths, reference=ortho_path, out=out, tile=128, client=c, model=kind, dem=dem_path)
                seconds = time.perf_counter() - t0
                names = json.loads(ds.attrs["scenes"])
                mine = [scenes[int(Path(p).stem.removeprefix("scene"))] for p in names]
                truths = [s.to_ortho for s in mine]
                own, _ = mosaic_errors(ds, truths, [(size, size)] * len(mine), transform, positions=scene_positions(ds, out))
                own = own[np.isfinite(own)]
                seam = seam_errors(ds.source.values, ds.rio.transform(), load_models(ds), truths, [(size, size)] * len(mine),
                                   heights=ds.height.values)
                s = json.loads(ds.attrs["summary"])
                rows.append((block, kind, float(np.sqrt(np.mean(own**2))), float(own.max()),
                             float(np.sqrt(np.mean(seam**2))) if seam.size else float("nan"), seam.size,
                             f"{len(names)} / {len(paths)}", s["sigma0"], seconds))
    print(f"\nMosaic models: {grid} x {grid} block of {size}² push-broom scenes rolled +-0.35 rad over a {ext}² "
          f"Sentinel-2 crop (10 m) and a fractal DEM; control on every scene; {args.workers} workers")
    print("| block | model | RMSE px | max px | seam mismatch RMS px | seam px | scenes | sigma0 | wall s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for block, kind, rmse, mx, seam, n, placed, sigma0, sec in rows:
        print(f"| {block} | {kind} | {rmse:.3f} | {mx:.3f} | {seam:.3f} | {n} | {placed} | {sigma0:.2f} | {sec:.1f} |")


if __name__ == "__main__":
    main()
