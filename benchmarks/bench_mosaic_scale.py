"""Mosaic at scale: an N x N block of small scenes end to end, time per stage and worker memory.

The block is made as in ``bench_mosaic.py`` (:mod:`geocoder.simulate.block` over a crop of the
real Sentinel-2 image in ../shared/data: rotation, scale, a quadratic term, gain, offset and
noise per scene, 20 % overlap along the strips, 60 % sidelap) with control on every scene.
Printed: scenes, overlapping pairs, tie and ground points, seconds per stage (from the
mosaic's summary), wall time, the peak resident memory of each worker process (its
high-water mark, read from the kernel at the end), and the geometric error of the mosaic
against the truth (RMSE and max over every output pixel, output pixels).

Every scene carries an approximate georeference (the affine nearest its true mapping, shifted
by up to 4 px, as a navigation system gives it) unless ``--no-georeference``: then each scene
is searched for on the whole reference, which fails for scenes much smaller than the reference.

Run:  python benchmarks/bench_mosaic_scale.py [--grid 10] [--size 192] [--workers 2] [--no-georeference]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from distributed import Client, LocalCluster

from geocoder.mosaic import mosaic
from geocoder.quality.accuracy import mosaic_errors
from geocoder.scene import write_geotiff
from geocoder.simulate.block import block_layout, render

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
S2 = DATA / "s2_arosics" / "ref_S2A_20160608T153121_T33UUU_sub.tif"


def _peak_rss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _affine_fit(scene, size: int) -> rasterio.Affine:
    """The affine scene pixel -> ortho pixel nearest the scene's true mapping (least squares)."""
    ys, xs = np.mgrid[0:size:16, 0:size:16].astype(np.float64)
    ox, oy = scene.to_ortho(xs, ys)
    design = np.column_stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    (a, b, c), (d, e, f) = np.linalg.lstsq(design, np.column_stack([ox.ravel(), oy.ravel()]), rcond=None)[0].T
    # rasterio's Affine maps pixel corners; the fit maps pixel centres
    return rasterio.Affine(a, b, c - 0.5 * (a + b) + 0.5, d, e, f - 0.5 * (d + e) + 0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=10, help="scenes per side")
    ap.add_argument("--size", type=int, default=192, help="scene side (px)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile", type=int, default=256)
    ap.add_argument("--no-georeference", action="store_true",
                    help="scenes without any georeference (each is searched for on the whole reference)")
    args = ap.parse_args()
    n, size = args.grid, args.size
    work = Path(tempfile.mkdtemp(prefix="bench-mosaic-scale-"))
    with rasterio.open(S2) as src:
        full = src.read(1).astype(np.float32)
        t = src.transform
    scenes = block_layout(n, n, size=size, overlap=(0.2, 0.6), origin=(40.0, 40.0), seed=5)
    height = int(max(s.row0 for s in scenes) + 1.2 * size + 80)
    width = int(max(s.col0 for s in scenes) + 1.2 * size + 80)
    # the first crop (from the top, flush right) clear of the image's no-data wedge in the west
    c0 = full.shape[1] - width - 8
    r0 = next((r for r in range(0, full.shape[0] - height, 25) if c0 >= 0 and (full[r : r + height, c0 : c0 + width] > 0).all()), None)
    if r0 is None:
        raise SystemExit(f"a {n} x {n} block of {size} px scenes needs {height} x {width} px of valid image; use a smaller --size")
    ortho = full[r0 : r0 + height, c0 : c0 + width]
    transform = t * rasterio.Affine.translation(c0, r0)
    write_geotiff(work / "ortho.tif", ortho, transform=transform, crs="EPSG:32633")
    paths = []
    rng = np.random.default_rng(7)
    for k, s in enumerate(scenes):
        paths.append(work / f"scene{k:03d}.tif")
        georef = {}
        if not args.no_georeference:
            # an approximate georeference, as a navigation system or a provider gives it: the
            # affine nearest the scene's true mapping, off by up to 4 ortho pixels
            a = _affine_fit(s, size) * rasterio.Affine.translation(*rng.uniform(-4, 4, 2))
            georef = {"transform": transform * a, "crs": "EPSG:32633"}
        write_geotiff(paths[-1], render(ortho, s, seed=k), **georef)
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        t0 = time.perf_counter()
        ds = mosaic(paths, reference=work / "ortho.tif", out=work / "mosaic.zarr", tile=args.tile, client=c, show_progress=True)
        wall = time.perf_counter() - t0
        peaks = c.run(_peak_rss_mib)
    placed = [paths.index(Path(q)) for q in json.loads(ds.attrs["scenes"])]
    own, seam = mosaic_errors(ds, [scenes[k].to_ortho for k in placed], [(size, size)] * len(placed), transform)
    own = own[np.isfinite(own)]
    s = json.loads(ds.attrs["summary"])
    ties = sum(p["ties"] for p in s["pairs"])
    print(f"\nMosaic scale: {n} x {n} = {len(scenes)} scenes of {size}² px over a {height} x {width} Sentinel-2 crop, "
          f"tile {args.tile}, {args.workers} workers")
    print("| scenes | placed | pairs | tie points | ground points by rays | mosaic px | wall s | "
          + " | ".join(f"{k} s" for k in s["seconds"]) + " | worker peak MiB | RMSE px | max px | seam RMS px |")
    print("|" + "---:|" * (10 + len(s["seconds"])))
    print(f"| {len(scenes)} | {len(scenes) - len(s['left_out'])} | {len(s['pairs'])} | {ties} | {s['rays']} | "
          f"{s['shape'][0]} x {s['shape'][1]} | {wall:.1f} | " + " | ".join(f"{v:.1f}" for v in s["seconds"].values())
          + f" | {', '.join(f'{v:.0f}' for v in peaks.values())} | {np.sqrt(np.mean(own**2)):.3f} | {own.max():.3f} | "
          f"{np.sqrt(np.mean(seam**2)):.3f} |")
    for k, why in s["left_out"].items():
        print(f"left out: scene {k}: {why}")


if __name__ == "__main__":
    main()
