"""Dense registration: speed with 1 and 2 workers, and accuracy against other optical-flow codes.

Speed: a 2048 x 2048 pair (procedural ortho warped by affine + quadratic up to 15 px, scan-
line turbulence 1-3 px, 2 % noise, gain and offset) registered with 1 and 2 local worker
processes: pixels matched per second by the dense stage, end-to-end time, peak memory per
worker, RMSE against the truth.

Comparison on the same pair (and on real crops of ../shared/data warped the same way):
geocoder's polynomial only, geocoder dense, scikit-image ``optical_flow_ilk`` and OpenCV's DIS
optical flow (both on the raw pair and on the pair pre-warped by geocoder's polynomial),
RMSE over the textured overlap and wall time.

Run:  pip install -e ".[bench]" scikit-image opencv-python-headless
      python benchmarks/bench_dense.py [--size 2048] [--skip-speed] [--skip-compare]
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
from distributed import Client, LocalCluster

from geocoder import Status, register
from geocoder.kernels.polynomial import PolyMap
from geocoder.kernels.resample import sample
from geocoder.pipeline.dense import DenseOptions
from geocoder.pipeline.register import RegisterOptions
from geocoder.scene import write_geotiff
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "benchmarks")]
SHARED = ROOT.parent / "shared" / "data"

from bench_cluster import WorkerPeak  # noqa: E402
from test_dense import textured_overlap  # noqa: E402


def synthetic_case(size: int, work: Path):
    margin = 48
    src = synthetic_ortho((size + 2 * margin, size + 2 * margin), seed=11)
    pair = make_pair(src, shape=(size, size), seed=11, margin=margin, turbulence=(1.0, 3.0))
    work.mkdir(parents=True, exist_ok=True)
    write_geotiff(work / "b.tif", pair.base)
    write_geotiff(work / "d.tif", pair.distorted)
    return work / "b.tif", work / "d.tif", pair


def rmse(dx, dy, pair, mask):
    e2 = (dx - pair.dx) ** 2 + (dy - pair.dy) ** 2
    ok = mask & np.isfinite(e2)
    return float(np.sqrt(e2[ok].mean())), float(ok.sum() / mask.sum())


def speed(size: int, work: Path, col_steps: tuple[int, ...] = (1,)) -> None:
    b, d, pair = synthetic_case(size, work / "speed")
    wb, wd, _ = synthetic_case(256, work / "warm")
    rows = []
    for workers in (1, 2):
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
            for col_step in col_steps:
                options = RegisterOptions(matching=DenseOptions(col_step=col_step))
                register(wb, wd, tile=128, client=c, options=options)  # warm-up: numba compiles (or loads) in the workers
                t0 = time.perf_counter()
                with WorkerPeak(list(c.run(os.getpid).values())) as mem:
                    ds = register(b, d, tile=512, client=c, out=work / f"speed{workers}-{col_step}.zarr", options=options)
                total = time.perf_counter() - t0
                s = json.loads(ds.attrs["summary"])
                st = ds.status.values
                matched = int((st == Status.MATCHED).sum())
                m = st == Status.MATCHED
                err = np.hypot(ds.dx.values - pair.dx, ds.dy.values - pair.dy)[m]
                rows.append((workers, col_step, matched / s["seconds"]["dense matching"], s["seconds"]["dense matching"], total,
                             matched / st.size, float(np.sqrt((err**2).mean())), float((err > 1).mean()), s["dense_rounds"],
                             max(mem.peak.values())))
    print(f"\nDense speed: {size} x {size} pair, tile 512, template 51 x 7, local worker processes (1 thread each)")
    print("| workers | col_step | matched px/s | dense stage s | end-to-end s | matched | RMSE px | > 1 px | rounds | peak worker MiB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print("| {} | {} | {:.0f} | {:.1f} | {:.1f} | {:.1%} | {:.4f} | {:.2%} | {} | {:.0f} |".format(*r))


def _prewarp(pair, mapping: PolyMap):
    h, w = pair.dx.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = mapping(xs, ys)
    return sample(pair.distorted[0], px, py, method="cubic"), px, py


def _compose(mapping: PolyMap, flow_x, flow_y):
    """d(p) = P(p + f(p)) - p for a flow f measured against the pre-warped image."""
    h, w = flow_x.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = mapping(xs + flow_x, ys + flow_y)
    return px - xs, py - ys


def _normalise(base, moving):
    """Global linear radiometric match (mean and std) of ``moving`` to ``base``.

    Both flow codes assume brightness constancy, which the cases' gain and offset break;
    geocoder's matcher estimates gain and offset itself.
    """
    m = (moving - np.nanmean(moving)) / np.nanstd(moving) * np.nanstd(base) + np.nanmean(base)
    return np.where(np.isfinite(m), m, np.nanmean(base))


def _ilk(base, moving):
    from skimage.registration import optical_flow_ilk

    v, u = optical_flow_ilk(np.nan_to_num(base), _normalise(base, moving), radius=7, num_warp=10)
    return u, v


def _dis(base, moving):
    import cv2

    lo, hi = np.nanpercentile(base, [0.5, 99.5])

    def u8(a):
        return np.clip((np.nan_to_num(a, nan=lo) - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(u8(base), u8(_normalise(base, moving)), None)
    return flow[..., 0].astype(np.float64), flow[..., 1].astype(np.float64)


def compare(work: Path, size: int) -> None:
    from pairs import real_pair

    cases = []
    b, d, pair = synthetic_case(size, work / "cmp")
    cases.append((f"synthetic {size}px", b, d, pair, 512))
    for which, n in (("aerial", 512), ("s2", 512)):
        f = real_pair(SHARED, work / which, which=which, size=n, seed=21, turbulence=(1.0, 3.0))
        cases.append((f"{which} {n}px", f.base, f.distorted, f.pair, 256))
    rows = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        for name, b, d, pair, tile in cases:
            mask = textured_overlap(pair)
            t0 = time.perf_counter()
            poly = register(b, d, tile=tile, client=c, dense=False)
            t_poly = time.perf_counter() - t0
            rows.append((name, "geocoder polynomial only", *rmse(poly.dx.values, poly.dy.values, pair, mask), t_poly))
            t0 = time.perf_counter()
            dense = register(b, d, tile=tile, client=c)
            t_dense = time.perf_counter() - t0
            good = np.isin(dense.status.values, (Status.MATCHED, Status.FILLED))
            dx = np.where(good, dense.dx.values, np.nan)
            dy = np.where(good, dense.dy.values, np.nan)
            rows.append((name, "geocoder dense (matched + filled)", *rmse(dx, dy, pair, mask), t_dense))
            mapping = PolyMap.from_dict(json.loads(poly.attrs["mapping"]))
            base = pair.base[0]
            warped, _, _ = _prewarp(pair, mapping)
            dist = pair.distorted[0]
            same_grid = dist.shape == base.shape
            for label, fn in (("scikit-image optical_flow_ilk (r=7)", _ilk), ("OpenCV DIS (medium preset)", _dis)):
                try:
                    if same_grid:
                        t0 = time.perf_counter()
                        fx, fy = fn(base, dist)
                        rows.append((name, label + ", raw pair", *rmse(fx, fy, pair, mask), time.perf_counter() - t0))
                    t0 = time.perf_counter()
                    fx, fy = fn(base, warped)
                    dx, dy = _compose(mapping, fx, fy)
                    rows.append((name, label + ", after geocoder's polynomial", *rmse(dx, dy, pair, mask), time.perf_counter() - t0 + t_poly))
                except ImportError as exc:
                    rows.append((name, f"{label}: not installed ({exc.name})", float("nan"), 0.0, 0.0))
    print("\nDense accuracy against truth over the textured overlap (Cramer-Rao bound of the 51 x 7 template <= 0.1 px);")
    print("the flow codes get the distorted image radiometrically normalised (mean/std) first")
    print("| case | method | RMSE px | coverage | time s |")
    print("|---|---|---:|---:|---:|")
    for r in rows:
        print("| {} | {} | {:.3f} | {:.1%} | {:.1f} |".format(*r))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-compare", action="store_true")
    ap.add_argument("--col-steps", default="1", help="comma-separated DenseOptions.col_step values for the speed table")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        if not args.skip_speed:
            speed(args.size, Path(d), tuple(int(v) for v in args.col_steps.split(",")))
        if not args.skip_compare:
            compare(Path(d), args.size)


if __name__ == "__main__":
    main()
