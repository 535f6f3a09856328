"""Multispectral against single-band dense matching (seed 003 sec. 11; issue 15).

Real multi-band crops of ``../shared/data`` (the aerial RGB and the Landsat 7 RGB) warped by
an airborne-like field (affine + quadratic + scan-line turbulence, 2 % noise, gain and offset
per band; :func:`geocoder.simulate.warp.make_pair`), each registered with the default dense
matching on band 1 alone and on bands 1, 2, 3 at once (``register(..., bands=(1, 2, 3))``).
The "weak" cases are the same crops with band 1 made flat over the left half of the source
(Gaussian blur, sigma 8 px, before the warp): no texture in one band there, texture in the
others, the case the multispectral matcher is for.

Columns: wall time; coverage = matched or filled pixels / overlap, over the whole overlap and
over its left and right halves; RMSE against the truth over those pixels; the calibration
RMSE / RMS(sigma) in x and y over the matched pixels; share of the overlap off by more than
1 px among them.

Run:  python benchmarks/bench_bands.py [--cases aerial-512,aerial-512-weak,landsat7-576,landsat7-576-weak]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"


@dataclass(frozen=True)
class Case:
    name: str
    path: str
    origin: tuple[int, int]
    size: int
    seed: int
    weak: bool


CASES = {c.name: c for c in (
    Case("aerial-512", "baviaanskloof/ngi_rgb_byte_1.tif", (60, 107), 512, 21, False),
    Case("aerial-512-weak", "baviaanskloof/ngi_rgb_byte_1.tif", (60, 107), 512, 21, True),
    Case("landsat7-576", "landsat7_rasterio/RGB.byte.tif", (20, 60), 576, 24, False),
    Case("landsat7-576-weak", "landsat7_rasterio/RGB.byte.tif", (20, 60), 576, 24, True),
)}


def make_case(case: Case, work: Path):
    """Write the pair's two 3-band GeoTIFFs; return (base path, distorted path, SyntheticPair)."""
    import rasterio
    from scipy.ndimage import gaussian_filter

    from geocoder.scene import write_geotiff
    from geocoder.simulate.warp import make_pair

    margin = 48
    r0, c0 = case.origin
    n = case.size + 2 * margin
    with rasterio.open(SHARED / case.path) as f:
        src = f.read([1, 2, 3], window=((r0, r0 + n), (c0, c0 + n))).astype(np.float32)
        nodata = f.nodata
    if nodata is not None:
        src[src == nodata] = np.nan
    if case.weak:  # band 1 without texture over the left half
        half = n // 2
        src[0, :, :half] = gaussian_filter(src[0], 8.0)[:, :half]
    pair = make_pair(src, shape=(case.size, case.size), seed=case.seed, margin=margin, turbulence=(1.0, 3.0))
    base, dist = work / f"{case.name}-base.tif", work / f"{case.name}-dist.tif"
    write_geotiff(base, pair.base)
    write_geotiff(dist, pair.distorted)
    return base, dist, pair


def figures(ds, pair) -> dict:
    from geocoder import Status

    st = ds.status.values
    ex, ey = ds.dx.values - pair.dx, ds.dy.values - pair.dy
    err = np.hypot(ex, ey)
    inside = (st != Status.OUTSIDE) & np.isfinite(pair.dx)
    good = ((st == Status.MATCHED) | (st == Status.FILLED)) & inside
    matched = (st == Status.MATCHED) & inside
    w = st.shape[1]
    out = {}
    for name, cols in (("all", slice(None)), ("left", slice(0, w // 2)), ("right", slice(w // 2, None))):
        g, i = good[:, cols], inside[:, cols]
        out[f"coverage_{name}"] = float(g.sum() / max(i.sum(), 1))
        out[f"rmse_{name}"] = float(np.sqrt(np.mean(err[:, cols][g] ** 2))) if g.any() else float("nan")
    out["calibration"] = tuple(
        float(np.sqrt(np.mean(e[matched] ** 2)) / np.sqrt(np.mean(s[matched] ** 2)))
        for e, s in ((ex, ds.sigma_x.values), (ey, ds.sigma_y.values))
    )
    out["over_1px"] = float((err[good] > 1.0).sum() / max(inside.sum(), 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    from distributed import Client

    from geocoder import register
    from geocoder.runtime import local_cluster

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-bands-") as tmp, local_cluster(args.workers) as cluster, \
            Client(cluster) as client:
        work = Path(tmp)
        # numba compiles (or loads) the kernels of both forms in the workers before anything is timed
        warm = Case("warm-up", CASES["aerial-512"].path, (60, 107), 192, 1, False)
        wbase, wdist, _ = make_case(warm, work)
        for bands in (None, (1, 2, 3)):
            register(wbase, wdist, tile=128, client=client, bands=bands, show_progress=False)
        for name in args.cases.split(","):
            base, dist, pair = make_case(CASES[name], work)
            for label, bands in (("band 1", None), ("bands 1,2,3", (1, 2, 3))):
                t0 = time.perf_counter()
                ds = register(base, dist, tile=256, client=client, bands=bands, show_progress=False)
                wall = time.perf_counter() - t0
                f = figures(ds, pair)
                rows.append((name, label, wall, f))
                print(f"{name} {label}: {wall:.1f} s {json.dumps(f)}", file=sys.stderr, flush=True)
    print(f"\n{args.workers} workers, tile 256, default dense matching, one run each")
    print("| case | matched on | wall s | coverage all / left / right | RMSE all / left / right px "
          "| calibration x / y | > 1 px |")
    print("|---|---|---:|---|---|---|---:|")
    for name, label, wall, f in rows:
        print(f"| {name} | {label} | {wall:.1f} | {f['coverage_all']:.1%} / {f['coverage_left']:.1%} / "
              f"{f['coverage_right']:.1%} | {f['rmse_all']:.3f} / {f['rmse_left']:.3f} / {f['rmse_right']:.3f} | "
              f"{f['calibration'][0]:.2f} / {f['calibration'][1]:.2f} | {f['over_1px']:.2%} |")


if __name__ == "__main__":
    main()
