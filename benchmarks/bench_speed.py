"""One-run speed and accuracy table: geocoder dense, geocoder --no-dense, OpenCV DIS, scikit-image ILK.

All methods run on the SAME generated pair, in one run, so their ratios are comparable on
a shared, noisy machine: a real crop of the Sentinel-2 reference image of
``../shared/data/s2_arosics`` (``--size`` square, 2048 by default; its north-west corner
holds part of the image's nodata wedge) warped by an airborne-like field (affine +
quadratic up to 15 px, scan-line turbulence 1-3 px, 2 % noise, gain and offset;
:func:`geocoder.simulate.warp.make_pair`).

Every geocoder configuration (dense / --no-dense, 1 and 2 local worker processes of one
thread each, and optionally the code of another git revision: ``--before-rev``) runs in a
fresh Python process: it starts its local cluster (timed apart), registers a small
warm-up pair (numba compiles or loads its cache in the workers), then the timed
``register(base, distorted, out=..., client=...)`` at that revision's default tile (this
tree's rows at ``--tile`` when given), ingest to Zarr included, the cluster already up. The flow codes get the
distorted image radiometrically normalised (mean/std) and run in this process (OpenCV uses
its own threads).

Columns: wall time; Mpx/s (base pixels per second); ratio of the wall time to DIS's;
RMSE against the truth over the method's matched pixels (geocoder dense: status
``matched``; --no-dense: every pixel the polynomial covers; flow codes: every pixel) and
over every pixel of the overlap (base and distorted both valid; geocoder then uses its
polynomial where it has no match); coverage (matched / overlap); share of overlap pixels
with an error above 1 px, and the median error over the overlap (the RMSE of the flow codes
is dominated by a few wild pixels along the nodata edge). A second table gives geocoder's
seconds per stage. ``--repeat N`` times each geocoder configuration N times in its process
and shows the fastest run.

Run:  pip install -e ".[bench]"
      python benchmarks/bench_speed.py [--size 2048] [--workers 1,2] [--skip-dense] [--skip-peers] [--full-growth]
                                       [--before-rev fff9652] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
S2_REF = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
SEED = 31
MARGIN = 32


# -- the pair ---------------------------------------------------------------------------------

def make_case(size: int, work: Path) -> dict:
    """Crop the S2 reference (bottom-right corner, nodata as NaN), warp it, write both GeoTIFFs."""
    import rasterio
    from rasterio.windows import Window

    from geocoder.scene import write_geotiff
    from geocoder.simulate.warp import make_pair

    n = size + 2 * MARGIN
    with rasterio.open(SHARED / S2_REF) as f:
        h, w = f.height, f.width
        if n > min(h, w):
            raise SystemExit(f"--size {size} too large for {S2_REF} ({w} x {h})")
        src = f.read(1, window=Window(w - n, h - n, n, n)).astype(np.float64)
    src[src == 0] = np.nan
    pair = make_pair(src, shape=(size, size), seed=SEED, margin=MARGIN, turbulence=(1.0, 3.0))
    work.mkdir(parents=True, exist_ok=True)
    write_geotiff(work / "base.tif", pair.base)
    write_geotiff(work / "dist.tif", pair.distorted)
    warm = make_pair(np.nan_to_num(src[:320, -320:], nan=np.nanmean(src)), shape=(256, 256), seed=SEED, margin=MARGIN)
    write_geotiff(work / "warm-base.tif", warm.base)
    write_geotiff(work / "warm-dist.tif", warm.distorted)
    return {"pair": pair, "base": work / "base.tif", "dist": work / "dist.tif"}


def overlap_mask(pair) -> np.ndarray:
    """Base pixels whose base value and true distorted position both hold data."""
    from geocoder.kernels.resample import sample

    h, w = pair.dx.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    seen = sample(pair.distorted[0], xs + pair.dx, ys + pair.dy, method="bilinear")
    return np.isfinite(pair.base[0]) & np.isfinite(seen)


def metrics(dx, dy, matched, pair, overlap) -> dict:
    e = np.hypot(dx - pair.dx, dy - pair.dy)
    have = overlap & np.isfinite(e)
    m = have & matched
    return {
        "rmse_matched": float(np.sqrt(np.mean(e[m] ** 2))) if m.any() else float("nan"),
        "rmse_all": float(np.sqrt(np.mean(e[have] ** 2))) if have.any() else float("nan"),
        "coverage": float(m.sum() / overlap.sum()),
        "gt1": float((e[have] > 1.0).sum() / overlap.sum()),
        "median": float(np.median(e[have])) if have.any() else float("nan"),
    }


# -- geocoder, in a fresh process -------------------------------------------------------------

def _child(args) -> None:
    """Run one geocoder configuration; write its fields (npz) and timings (json)."""
    import xarray as xr
    from distributed import Client

    import geocoder
    from geocoder import register
    from geocoder.pipeline.dense import DenseOptions
    from geocoder.pipeline.register import RegisterOptions
    from geocoder.runtime import local_cluster

    work = Path(args.child)
    dense = args.dense in ("yes", "full")
    # the opt-in region growing of every pixel (the default grows a lattice, then matches every pixel at once)
    options = RegisterOptions(matching=DenseOptions(col_step=1, halo=4)) if args.dense == "full" else None
    t0 = time.perf_counter()
    with local_cluster(args.nworkers) as cluster, Client(cluster) as client:
        t_cluster = time.perf_counter() - t0
        files = client.run(lambda: __import__("geocoder").__file__)
        register(work.parent / "warm-base.tif", work.parent / "warm-dist.tif", tile=128, client=client,
                 out=work / "warm.zarr", dense=dense, options=options)
        best = None
        for _ in range(args.repeat):  # the fastest of the repeats, with its own stage times
            shutil.rmtree(work / "out.zarr", ignore_errors=True)
            w0, c0 = client.run(_cpu), _cpu()
            t0 = time.perf_counter()
            ds = register(work.parent / "base.tif", work.parent / "dist.tif", tile=args.tile, client=client,
                          out=work / "out.zarr", dense=dense, options=options)
            wall = time.perf_counter() - t0
            w1, c1 = client.run(_cpu), _cpu()
            cpu = (c1 - c0, sum(w1[k] - w0[k] for k in w0))
            if best is None or wall < best[0]:
                best = (wall, json.loads(ds.attrs["summary"]), cpu)
    wall, summary, cpu = best
    out = xr.open_zarr(work / "out.zarr", consolidated=False, chunks=None)
    np.savez(work / "fields.npz", dx=out.dx.values, dy=out.dy.values, status=out.status.values)
    (work / "timing.json").write_text(json.dumps({
        "wall": wall, "cluster": t_cluster, "cpu": cpu, "seconds": summary["seconds"], "tiepoints": summary["tiepoints"],
        "module": geocoder.__file__, "worker_modules": sorted(set(files.values())),
    }))


def _cpu() -> float:
    """User + system CPU seconds of this process so far (all its threads)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_geocoder(work: Path, label: str, *, dense: bool | str, nworkers: int, pythonpath: str | None, repeat: int = 1,
                 tile: int | None = None) -> dict:
    d = work / label.replace(" ", "_").replace("/", "_")
    d.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(d), "--nworkers", str(nworkers),
           "--dense", dense if isinstance(dense, str) else ("yes" if dense else "no"), "--repeat", str(repeat),
           *(["--tile", str(tile)] if tile else [])]
    subprocess.run(cmd, env=env, check=True, cwd=work, stdout=subprocess.DEVNULL)
    info = json.loads((d / "timing.json").read_text())
    f = np.load(d / "fields.npz")
    info.update(dx=f["dx"], dy=f["dy"], status=f["status"])
    return info


# -- the flow codes ---------------------------------------------------------------------------

def _normalise(base, moving):
    m = (moving - np.nanmean(moving)) / np.nanstd(moving) * np.nanstd(base) + np.nanmean(base)
    return np.where(np.isfinite(m), m, np.nanmean(base))


def run_dis(base, moving):
    import cv2

    lo, hi = np.nanpercentile(base, [0.5, 99.5])

    def u8(a):
        return np.clip((np.nan_to_num(a, nan=lo) - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)

    t0 = time.perf_counter()
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(u8(base), u8(_normalise(base, moving)), None)
    return flow[..., 0].astype(np.float64), flow[..., 1].astype(np.float64), time.perf_counter() - t0


def run_ilk(base, moving):
    from skimage.registration import optical_flow_ilk

    t0 = time.perf_counter()
    v, u = optical_flow_ilk(np.nan_to_num(base, nan=np.nanmean(base)), _normalise(base, moving), radius=7, num_warp=10)
    return u, v, time.perf_counter() - t0


# -- the table --------------------------------------------------------------------------------

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--workers", default="1,2", help="local worker counts, comma separated")
    ap.add_argument("--skip-dense", action="store_true", help="no geocoder dense rows (the slow ones)")
    ap.add_argument("--skip-peers", action="store_true", help="no OpenCV / scikit-image rows")
    ap.add_argument("--full-growth", action="store_true",
                    help="also the opt-in dense mode: region growing of every pixel (DenseOptions(col_step=1))")
    ap.add_argument("--before-rev", default=None, help="also run the geocoder rows with this git revision's code")
    ap.add_argument("--repeat", type=int, default=1, help="timed geocoder runs per configuration (the fastest is shown)")
    ap.add_argument("--tile", type=int, default=None, help="register's tile for this tree's rows (default: its default; --before-rev rows keep theirs)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--nworkers", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--dense", default="no", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args)
        return
    from geocoder.status import Status

    workers = [int(w) for w in args.workers.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench-speed-") as tmp:
        work = Path(tmp)
        case = make_case(args.size, work)
        pair = case["pair"]
        overlap = overlap_mask(pair)
        npx = args.size * args.size
        trees = [("after", None)]
        if args.before_rev:
            before = work / "before-src"
            before.mkdir()
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.before_rev], check=True, capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
            trees.insert(0, (f"before ({args.before_rev})", str(before)))
        rows, stages = [], []
        peers = {}
        if not args.skip_peers:
            base, moving = pair.base[0].astype(np.float64), pair.distorted[0].astype(np.float64)
            for name, fn in (("OpenCV DIS (medium preset)", run_dis), ("scikit-image optical_flow_ilk (r=7)", run_ilk)):
                try:
                    fx, fy, t = fn(base, moving)
                except ImportError as exc:
                    print(f"{name}: not installed ({exc.name})", file=sys.stderr)
                    continue
                peers[name] = (t, metrics(fx, fy, np.ones_like(overlap), pair, overlap))
        modes = ([("dense", True)] if not args.skip_dense else []) + [("--no-dense", False)]
        if args.full_growth:
            modes.insert(0, ("dense, full region growing", "full"))
        for tree, path in trees:
            for mode, dense in modes:
                for n in workers:
                    label = f"geocoder {mode}, {n} worker{'s' if n > 1 else ''}, {tree}"
                    print(f"running {label} ...", file=sys.stderr, flush=True)
                    if dense == "full" and path is not None:
                        continue  # the before tree's default
                    info = run_geocoder(work, label, dense=dense, nworkers=n, pythonpath=path, repeat=args.repeat,
                                        tile=args.tile if path is None else None)
                    if path is not None and not all(m.startswith(path) for m in [info["module"], *info["worker_modules"]]):
                        raise SystemExit(f"{label}: geocoder imported from {info['module']} / {info['worker_modules']}, not {path}")
                    st = info["status"]
                    matched = st == Status.MATCHED if dense else st != Status.OUTSIDE
                    rows.append((label, info["wall"], metrics(info["dx"], info["dy"], matched, pair, overlap), info["cluster"]))
                    stages.append((label, info["seconds"], info["wall"], info["cluster"], info["tiepoints"], info["cpu"]))
        dis_t = peers.get("OpenCV DIS (medium preset)", (float("nan"),))[0]
        rows += [(name, t, m, float("nan")) for name, (t, m) in peers.items()]
        print(f"\nOne run, {args.size} x {args.size} crop of {S2_REF} warped by an airborne-like field "
              f"(affine + quadratic <= 15 px, turbulence 1-3 px, 2 % noise, gain/offset), seed {SEED}; "
              f"overlap {overlap.mean():.1%} of the base; {os.cpu_count()} cores")
        if args.repeat > 1:
            print(f"geocoder: fastest of {args.repeat} timed runs per configuration")
        print("| method | wall s | Mpx/s | x DIS time | RMSE matched px | RMSE overlap px | median overlap px | coverage | > 1 px | cluster start s |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for label, t, m, tc in rows:
            print(f"| {label} | {t:.2f} | {npx / t / 1e6:.2f} | {t / dis_t:.2f} | {m['rmse_matched']:.3f} | {m['rmse_all']:.3f} | {m['median']:.3f} | "
                  f"{m['coverage']:.1%} | {m['gt1']:.2%} | {tc:.1f} |")
        names = []
        for _, sec, *_ in stages:
            names += [k for k in sec if k not in names]
        print("\ngeocoder seconds per stage (register() wall time; cluster start not included), and the CPU")
        print("seconds the run used in the client process (client + scheduler + coarse alignment) and the workers")
        print("| run | " + " | ".join(names) + " | sum of stages | wall | CPU client | CPU workers | tie points |")
        print("|---|" + "---:|" * (len(names) + 5))
        for label, sec, wall, _, ntp, cpu in stages:
            print(f"| {label} | " + " | ".join(f"{sec.get(k, float('nan')):.2f}" for k in names)
                  + f" | {sum(sec.values()):.2f} | {wall:.2f} | {cpu[0]:.2f} | {cpu[1]:.2f} | {ntp} |")


if __name__ == "__main__":
    main()
