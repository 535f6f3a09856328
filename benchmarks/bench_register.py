"""Speed and accuracy of the polynomial registration; prints two tables.

Speed: a 2048 x 2048 synthetic pair (procedural ortho warped by affine + quadratic up to
15 px), with 1 and 2 local worker processes: interest points per second, correspondence
time, end-to-end time, peak memory per worker.

Accuracy: real images from ../shared/data warped by a known field (and the seed's sec. 4.5
experiment): tie points, their worst distance from the truth, RMSE of dx/dy.

Run:  python benchmarks/bench_register.py [--size 2048] [--skip-speed] [--skip-accuracy]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr
from bench_cluster import WorkerPeak  # the script's directory is on sys.path
from distributed import Client, LocalCluster

from geocoder import RegisterOptions, Status, register
from geocoder.pipeline.detect import InterestOptions
from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair, seed_affine_experiment

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
SHARED = ROOT.parent / "shared" / "data"


def _errors(out, pair, ds):
    tp = ds.attrs["tiepoints"] if out is None else xr.open_zarr(out, group="tiepoints", consolidated=False).compute()
    bx, by = tp.base_x.values, tp.base_y.values
    tx, ty = pair.field.displacement(bx, by)
    tperr = np.hypot(tp.dist_x.values - bx - tx, tp.dist_y.values - by - ty)
    inside = ds.status.values != Status.OUTSIDE
    d2 = (ds.dx.values - pair.dx) ** 2 + (ds.dy.values - pair.dy) ** 2
    return len(bx), float(tperr.max()), float(np.sqrt(d2[inside].mean())), float(inside.mean())


def speed(size: int, work: Path) -> None:
    margin = 48
    src = synthetic_ortho((size + 2 * margin, size + 2 * margin), seed=5)
    pair = make_pair(src, shape=(size, size), seed=5, margin=margin)
    write_geotiff(work / "b.tif", pair.base)
    write_geotiff(work / "d.tif", pair.distorted)
    rows = []
    for workers in (1, 2):
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
            register(work / "b.tif", work / "d.tif", tile=512, client=c, out=work / "warm.zarr", dense=False)  # compile numba in workers
            t0 = time.perf_counter()
            out = work / f"out{workers}.zarr"
            with WorkerPeak(list(c.run(os.getpid).values())) as mem:
                ds = register(work / "b.tif", work / "d.tif", tile=512, client=c, out=out, dense=False)
            total = time.perf_counter() - t0
            s = json.loads(ds.attrs["summary"])
            n, worst, rmse, _ = _errors(out, pair, ds)
            sec = s["seconds"]
            rows.append(
                (workers, (s["base_points"] + s["distorted_points"]) / sec["interest points"], sec["interest points"],
                 sec["correspondence"], sec["resampling"], total, size * size / total / 1e6, n, rmse, max(mem.peak.values()))
            )
    print(f"\nSpeed: {size} x {size} synthetic pair, tile 512, local worker processes (1 thread each)")
    print("| workers | interest pts/s | interest s | correspondence s | resampling s | end-to-end s | Mpx/s | tie points | RMSE px | peak worker MiB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print("| {} | {:.0f} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {:.2f} | {} | {:.4f} | {:.0f} |".format(*r))


def accuracy(work: Path) -> None:
    from pairs import real_pair

    rows = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        for which, size, tile in (("s2", 1024, 256), ("aerial", 576, 192)):
            for seed in (7, 8, 9):
                files = real_pair(SHARED, work / f"{which}{seed}", which=which, size=size, seed=seed)
                out = work / f"{which}{seed}.zarr"
                ds = register(files.base, files.distorted, out=out, tile=tile, client=c, dense=False)
                s = json.loads(ds.attrs["summary"])
                n, worst, rmse, cover = _errors(out, files.pair, ds)
                rows.append((f"{which} {size}px seed {seed}", float(np.hypot(files.pair.dx, files.pair.dy).max()), n, worst, s["rms"], rmse, cover))
        src = __import__("conftest").read_band(SHARED / "baviaanskloof/sentinel2_b432_byte.tif", 1, (300, 700, 200, 600))
        lo, hi = np.percentile(src, [1, 99])
        src = np.clip((src - lo) / (hi - lo), 0, 1) * 255
        for seed in range(1, 6):
            pair = seed_affine_experiment(src, size=128, seed=seed)
            write_geotiff(work / f"sb{seed}.tif", pair.base)
            write_geotiff(work / f"sd{seed}.tif", pair.distorted)
            opts = RegisterOptions(interest=InterestOptions(cell=32), min_tiepoints=6)
            ds = register(work / f"sb{seed}.tif", work / f"sd{seed}.tif", tile=128, order=1, client=c, options=opts, dense=False)
            s = json.loads(ds.attrs["summary"])
            n, worst, rmse, cover = _errors(None, pair, ds)
            rows.append((f"seed 4.5 affine 128px seed {seed}", float(np.hypot(pair.dx, pair.dy).max()), n, worst, s["rms"], rmse, cover))
    print("\nAccuracy against truth (polynomial registration; quadratic truth, or affine for the seed's experiment)")
    print("| case | max truth px | tie points | worst tie pt px | robust RMS px | dx/dy RMSE px | coverage |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print("| {} | {:.1f} | {} | {:.3f} | {:.3f} | {:.4f} | {:.1%} |".format(*r))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        if not args.skip_speed:
            speed(args.size, Path(d))
        if not args.skip_accuracy:
            accuracy(Path(d))


if __name__ == "__main__":
    main()
