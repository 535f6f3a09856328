"""Register the real pairs of ../shared/data (README 'What belongs together', A-D); print a table.

There is no per-pixel truth for these: the table gives the coarse-alignment path, the tie
points and the robust RMS of their residuals against the global quadratic (in distorted
pixels), and the wall time on a local cluster of 2 worker processes.

Run:  python benchmarks/bench_real_pairs.py
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from distributed import Client, LocalCluster

import geocoder

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

PAIRS = [
    ("A: S2 2016-06-08 <- S2 2016-05-29", "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", "s2_arosics/tgt_S2A_20160529T153631_T33UUU_sub.tif", dict(nodata=0, dist_nodata=0)),
    ("B: S2 B4 10 m <- L8 B4 30 m", "baviaanskloof/sentinel2_b432_byte.tif", "baviaanskloof/landsat8_byte.tif", dict(band=1, dist_band=4)),
    ("C: NGI ortho 5 m <- S2 10 m", "baviaanskloof/ngi_rgb_byte_1.tif", "baviaanskloof/sentinel2_b432_byte.tif", dict(band=1, dist_band=1)),
    ("D: NGI ortho 1 <- NGI ortho 2", "baviaanskloof/ngi_rgb_byte_1.tif", "baviaanskloof/ngi_rgb_byte_2.tif", dict()),
]


def main() -> None:
    rows = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        for name, base, dist, kw in PAIRS:
            t0 = time.perf_counter()
            try:
                ds = geocoder.register(DATA / base, DATA / dist, client=c, tile=512, dense=False, **kw)
            except geocoder.GeocoderError as exc:
                rows.append((name, f"error: {exc}", "", "", "", "", ""))
                continue
            s = json.loads(ds.attrs["summary"])
            rows.append((name, s["coarse_method"], f"{s['base_points']} / {s['distorted_points']}", str(s["tiepoints"]),
                         str(s["inliers"]), f"{s['rms']:.3f}", f"{time.perf_counter() - t0:.1f}"))
    print("| pair | coarse alignment | interest points base / distorted | tie points | inliers | robust RMS px | time s |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
