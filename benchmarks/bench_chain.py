"""Registration chains (seed 003 sec. 10): a 45 degree look onto nadir, directly and through a 30 degree look.

The airborne simulator renders three ASAS-like looks (nadir, 30 and 45 degrees forward tilt,
each with its own turbulence and noise) over the same real orthophoto (a crop of
``baviaanskloof/ngi_rgb_byte_1.tif``) and the same fractal DEM, for each relief asked for.
The truth of a nadir pixel is where the other look's sensor sees its ground point. Printed
per relief: the direct registration 45 -> nadir, the two legs (30 -> nadir, 45 -> 30) and
the chain ``register --via`` 45 -> 30 -> nadir, with

* coverage: matched pixels over the true overlap (nadir pixels the 45 degree look sees);
* RMSE of the matched pixels, along track (dy) and across (dx), and of every overlap pixel
  with a displacement, and the share of those more than 1 px off;
* calibration: RMSE / RMS(sigma) of the matched pixels per axis (1 = sigma right);
* the same RMSE on the pixels matched by both the direct and the chained registration.

    python benchmarks/bench_chain.py [--relief 30,80] [--size 600] [--rows 512] [--offset ROW,COL] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import rasterio
import xarray as xr
from affine import Affine
from distributed import Client, LocalCluster
from rasterio.windows import Window

import geocoder
from geocoder import Status
from geocoder.pipeline.simulate import load_sensor, simulate
from geocoder.scene import write_geotiff
from geocoder.simulate.terrain import fractal_dem

SHARED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")
NGI = "baviaanskloof/ngi_rgb_byte_1.tif"
LOOKS = ((0, 1), (30, 2), (45, 3))  # tilt in degrees, seed of turbulence and noise


def look_truth(base: str, distorted: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True ``d = p_distorted - p_base`` on the base look's grid and the true overlap."""
    b = xr.open_zarr(base, consolidated=False)
    dist = xr.open_zarr(distorted, consolidated=False)
    sensor = load_sensor(dist)
    gx, gy, gz = (b[k].values for k in ("ground_x", "ground_y", "ground_z"))
    row, col = sensor.ground_to_image(gx, gy, gz)
    ys, xs = np.mgrid[0 : gx.shape[0], 0 : gx.shape[1]]
    h, w = dist.sizes["y"], dist.sizes["x"]
    image = dist.image.values[0]
    inside = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
    ri, ci = np.clip(np.rint(row), 0, h - 1).astype(int), np.clip(np.rint(col), 0, w - 1).astype(int)
    overlap = inside & np.isfinite(image[ri, ci])
    return col - xs, row - ys, overlap


def scores(ds: xr.Dataset, truth) -> dict:
    tx, ty, overlap = truth
    status = ds.status.values
    dx, dy = ds.dx.values.astype(np.float64), ds.dy.values.astype(np.float64)
    matched = (status == Status.MATCHED) & overlap
    have = overlap & (status != Status.OUTSIDE) & np.isfinite(dx)
    ex, ey = dx - tx, dy - ty
    e = np.hypot(ex, ey)
    sx, sy = ds.sigma_x.values.astype(np.float64), ds.sigma_y.values.astype(np.float64)

    def rms(a):
        return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")

    return {
        "coverage": matched.sum() / overlap.sum(),
        "rmse": rms(e[matched]), "rmse_y": rms(ey[matched]), "rmse_x": rms(ex[matched]),
        "rmse_all": rms(e[have]), "gt1": float(np.mean(e[have] > 1.0)),
        "cal_x": rms(ex[matched]) / rms(sx[matched]), "cal_y": rms(ey[matched]) / rms(sy[matched]),
        "matched": matched, "e": e,
    }


def make_looks(d: str, relief: float, size: int, rows: int, client, offset=None) -> dict[int, str]:
    with rasterio.open(os.path.join(SHARED, NGI)) as f:
        r0, c0 = offset or ((f.height - size) // 2, (f.width - size) // 2)
        img = f.read(1, window=Window(c0, r0, size, size))
        transform, crs = f.transform * Affine.translation(c0, r0), f.crs.to_wkt()
    write_geotiff(f"{d}/ortho.tif", img, transform=transform, crs=crs, nodata=0)
    write_geotiff(f"{d}/dem.tif", fractal_dem((size // 4, size // 4), seed=7, relief=relief).astype(np.float32),
                  transform=transform * Affine.scale(4), crs=crs)
    paths = {}
    for tilt, seed in LOOKS:
        paths[tilt] = f"{d}/look{tilt}.zarr"
        simulate("airborne", f"{d}/ortho.tif", dem=f"{d}/dem.tif", out=paths[tilt], sensor="asas", tilt_deg=tilt,
                 rows=rows, seed=seed, turbulence_deg=0.05, tile=256, client=client)
    return paths


def run_case(relief: float, size: int, rows: int, client, work: str, offset=None) -> list[tuple[str, dict, float]]:
    d = tempfile.mkdtemp(prefix=f"relief{relief:g}-", dir=work)
    looks = make_looks(d, relief, size, rows, client, offset)
    out = []
    for name, (b, dist, via) in {
        "direct 45 -> nadir": (0, 45, None),
        "leg 30 -> nadir": (0, 30, None),
        "leg 45 -> 30": (30, 45, None),
        "chain 45 -> 30 -> nadir (--via)": (0, 45, 30),
    }.items():
        t0 = time.perf_counter()
        try:
            ds = geocoder.register(looks[b], looks[dist], via=None if via is None else looks[via],
                                   out=f"{d}/{b}_{dist}_{via}.zarr", tile=256, client=client)
        except geocoder.GeocoderError as exc:  # a failed registration is a result of the table
            out.append((name, {"failed": str(exc).split(": ", 1)[-1]}, time.perf_counter() - t0))
            continue
        seconds = time.perf_counter() - t0
        out.append((name, scores(ds, look_truth(looks[b], looks[dist])), seconds))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--relief", default="30,80", help="DEM relief(s) in metres, comma-separated")
    p.add_argument("--size", type=int, default=600, help="side of the ortho crop (5 m pixels)")
    p.add_argument("--rows", type=int, default=512, help="scan lines of every look (2 m apart)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--offset", default=None,
                   help="row,col of the crop's corner in the ortho (default: centred)")
    a = p.parse_args()
    offset = tuple(int(v) for v in a.offset.split(",")) if a.offset else None
    rows_out = []
    with tempfile.TemporaryDirectory(prefix="bench-chain-") as work, \
            LocalCluster(n_workers=a.workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        for relief in (float(r) for r in a.relief.split(",")):
            rows_out.append((relief, run_case(relief, a.size, a.rows, client, work, offset)))
    print(f"\nASAS-like looks, 512 x {a.rows} px, ortho crop {a.size}^2 px at 5 m, {a.workers} workers\n")
    print("| relief m | registration | coverage | RMSE matched px | along (dy) | across (dx) | RMSE overlap px "
          "| > 1 px | RMSE/RMS(sigma) dx | dy | wall s |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for relief, results in rows_out:
        for name, s, sec in results:
            if "failed" in s:
                print(f"| {relief:g} | {name} | failed: {s['failed']} | | | | | | | | {sec:.1f} |")
                continue
            print(f"| {relief:g} | {name} | {s['coverage']:.1%} | {s['rmse']:.3f} | {s['rmse_y']:.3f} | {s['rmse_x']:.3f} | "
                  f"{s['rmse_all']:.3f} | {s['gt1']:.1%} | {s['cal_x']:.2f} | {s['cal_y']:.2f} | {sec:.1f} |")
    print("\nOn the pixels matched by both the direct and the chained registration:\n")
    print("| relief m | pixels | RMSE direct px | RMSE chain px |")
    print("|---:|---:|---:|---:|")
    for relief, results in rows_out:
        direct, chain = results[0][1], results[-1][1]
        if "failed" in direct or "failed" in chain:
            print(f"| {relief:g} | (a registration failed) | | |")
            continue
        both = direct["matched"] & chain["matched"]
        rmse = [float(np.sqrt(np.mean(r["e"][both] ** 2))) for r in (direct, chain)]
        print(f"| {relief:g} | {int(both.sum())} | {rmse[0]:.3f} | {rmse[1]:.3f} |")


if __name__ == "__main__":
    main()
