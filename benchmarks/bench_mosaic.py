"""Mosaic accuracy against truth: single scenes vs the block, full vs sparse control; seams; balance.

A 3 x 3 block of scenes (20 % overlap along the strips, 60 % sidelap) over a crop of the real
Sentinel-2 image in ../shared/data, each scene rotated, scaled, bent by a quadratic term and
re-exposed (gain, offset, noise) with a known mapping to the ortho
(:mod:`geocoder.simulate.block`). Rows of the table:

- each scene on the reference alone (a mosaic of one scene, run once per scene);
- the block with control on every scene;
- the block with control on the four corner scenes only (sparse control), and the single
  scenes with that control (the others cannot be placed at all).

Columns: geometric error of every output pixel against the truth (RMSE, max, in output
pixels), scenes placed, RMS disagreement of neighbouring scenes wherever
both see a pixel, the grey-value step at the tie points before/after balancing, wall time.

A second table compares the seams (control on every scene): nearest each scene's centre
(``seams="centre"``) against the least-cost cut (``seams="least-cost"``), on the block as it is
and on the block with a few bright objects that each scene sees alone (cars, small clouds: 3
blobs of about 24 x 16 px per scene, +3 standard deviations of the ortho). Columns: grey-value
step along the seams (RMS difference of the two balanced scenes at every seam pixel, from the
mosaic's summary), geometric mismatch along the seams against the truth (RMS and max of
``|T_a(model_a(p)) - T_b(model_b(p))|`` at every seam pixel), the mosaic's geometric RMSE
against the truth, its grey-value RMSE against the ortho, wall time.

A third table (``--turbulence``) takes airborne strips instead: the same 3 x 3 layout
(``--turbulence-size`` px scenes), every scene's scan lines shifted by roll and pitch (up to
1.5 px, changing over tens of lines, :class:`~geocoder.simulate.block.BlockScene`), which no
polynomial follows. Rows: control on the 4 corner scenes without and with dense refinement
(``dense=True``: the corners against the reference, the others, in rounds, against their
refined neighbours), and control on every scene with dense refinement (every scene against
the reference). Columns: RMSE and max against the truth at every valid output pixel (output
px; at the positions the mosaic sampled, dense fields included), RMS disagreement of
neighbouring scenes wherever both see a pixel, how each scene was refined, wall time.

Run:  python benchmarks/bench_mosaic.py [--size 384] [--workers 2] [--seams-only]
      python benchmarks/bench_mosaic.py --turbulence [--turbulence-size 256]
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


def write_block(work: Path, scenes: list, size: int, name: str) -> tuple[np.ndarray, rasterio.Affine, list[Path]]:
    """The reference (a Sentinel-2 crop east of its no-data wedge, ``ortho.tif``) and the block's
    scenes rendered from it (``{name}{k}.tif``, no georeference) in ``work``; the crop, its
    transform and the scenes' paths."""
    with rasterio.open(S2) as src:
        full = src.read(1).astype(np.float32)
        t = src.transform
    r0, c0 = 300, 900
    extent = int(max(max(s.row0, s.col0) for s in scenes) + 1.2 * size + 80)
    ortho = full[r0 : r0 + extent, c0 : c0 + extent]
    transform = t * rasterio.Affine.translation(c0, r0)
    write_geotiff(work / "ortho.tif", ortho, transform=transform, crs="EPSG:32633")
    paths = []
    for k, s in enumerate(scenes):
        paths.append(work / f"{name}{k}.tif")
        write_geotiff(paths[-1], render(ortho, s, seed=k))
    return ortho, transform, paths


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seams-only", action="store_true", help="only the seam table")
    ap.add_argument("--turbulence", action="store_true", help="only the table of turbulent strips")
    ap.add_argument("--turbulence-size", type=int, default=256)
    args = ap.parse_args()
    if args.turbulence:
        turbulent_strips(args.turbulence_size, args.workers)
        return
    size = args.size
    work = Path(tempfile.mkdtemp(prefix="bench-mosaic-"))
    scenes = block_layout(3, 3, size=size, overlap=(0.2, 0.6), origin=(40.0, 40.0), seed=5)
    ortho, transform, paths = write_block(work, scenes, size, "scene")
    extent = ortho.shape[0]
    corners = [0, 2, 6, 8]
    rows = []

    def evaluate(name, dss, seconds):
        own_all, seam_all, steps, placed = [], [], [], 0
        for ds, ks in dss:
            placed += len(json.loads(ds.attrs["scenes"]))
            own, seam = mosaic_errors(ds, [scenes[k].to_ortho for k in ks], [(size, size)] * len(ks), transform)
            own_all.append(own[np.isfinite(own)])
            seam_all.append(seam)
            st = json.loads(ds.attrs["summary"]).get("seam_step") or [np.nan, np.nan]
            steps.append(st)
        own = np.concatenate(own_all)
        seam = np.concatenate(seam_all) if len(dss) == 1 else np.array([])
        rows.append((name, float(np.sqrt(np.mean(own**2))), float(own.max()), f"{placed} / {len(scenes)}",
                     float(np.sqrt(np.mean(seam**2))) if seam.size else float("nan"),
                     steps[0][0] if len(dss) == 1 else float("nan"), steps[0][1] if len(dss) == 1 else float("nan"), seconds))

    # the same block with objects each scene sees alone
    rng = np.random.default_rng(11)
    obj_paths = []
    for k, s in enumerate(scenes):
        img = render(ortho, s, seed=k)
        for _ in range(3):
            r, q = rng.integers(20, size - 40, 2)
            img[r : r + 16, q : q + 24] += 3.0 * float(ortho.std())
        obj_paths.append(work / f"objects{k}.tif")
        write_geotiff(obj_paths[-1], img)
    seam_rows = []

    def seam_row(name, mode, ds, seconds):
        from geocoder.mosaic import load_models
        from geocoder.mosaic.diagnostics import seam_errors
        from geocoder.scene import world_to_pixel

        ks = [int(p.rsplit("scene", 1)[-1].rsplit("objects", 1)[-1].split(".")[0]) for p in json.loads(ds.attrs["scenes"])]
        own, _ = mosaic_errors(ds, [scenes[k].to_ortho for k in ks], [(size, size)] * len(ks), transform)
        own = own[np.isfinite(own)]
        mism = seam_errors(ds.source.values, ds.rio.transform(), load_models(ds), [scenes[k].to_ortho for k in ks],
                           [(size, size)] * len(ks))
        ex, ny = np.meshgrid(ds.x.values, ds.y.values)
        gx, gy = (np.rint(v).astype(int) for v in world_to_pixel(transform, ex, ny))
        covered = ds.source.values != 65535
        grey = (ds.mosaic.values[0] - ortho[np.clip(gy, 0, extent - 1), np.clip(gx, 0, extent - 1)])[covered]
        s = json.loads(ds.attrs["summary"])
        seam_rows.append((name, mode, s["seam_grey_step"], float(np.sqrt(np.mean(mism**2))), float(mism.max()), mism.size,
                          float(np.sqrt(np.mean(own**2))), float(np.sqrt(np.nanmean(grey**2))), seconds))

    with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        for name, ps in (("block", paths), ("block + objects", obj_paths)):
            for mode in ("centre", "least-cost"):
                t0 = time.perf_counter()
                ds = mosaic(ps, reference=work / "ortho.tif", tile=256, client=c, seams=mode)
                seam_row(name, mode, ds, time.perf_counter() - t0)
        print(f"\nSeams: 3 x 3 block of {size}² scenes, control on every scene, feather 8 px; {args.workers} workers")
        print("| scenes | seams | grey step along seams | seam mismatch RMS px | max px | seam px | RMSE px | "
              "grey RMSE vs ortho | wall s |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
        for name, mode, step, mrms, mmax, n, rmse, grey, sec in seam_rows:
            print(f"| {name} | {mode} | {step:.1f} | {mrms:.3f} | {mmax:.3f} | {n} | {rmse:.3f} | {grey:.1f} | {sec:.1f} |")
        if args.seams_only:
            return
        t0 = time.perf_counter()
        ds = mosaic(paths, reference=work / "ortho.tif", tile=256, client=c)
        evaluate("block, control on every scene", [(ds, list(range(9)))], time.perf_counter() - t0)
        t0 = time.perf_counter()
        singles = [(mosaic([p], reference=work / "ortho.tif", tile=256, client=c), [k]) for k, p in enumerate(paths)]
        evaluate("each scene alone on the reference", singles, time.perf_counter() - t0)
        t0 = time.perf_counter()
        ds = mosaic(paths, reference=work / "ortho.tif", tile=256, client=c, control_scenes=corners)
        evaluate("block, control on the 4 corner scenes", [(ds, list(range(9)))], time.perf_counter() - t0)
        evaluate("corner scenes alone (the others unplaced)", [singles[k] for k in corners], 0.0)
        s = json.loads(ds.attrs["summary"])
    print(f"\nMosaic: 3 x 3 block of {size}² scenes over a {extent}² Sentinel-2 crop (10 m), 20 % overlap, 60 % sidelap; "
          f"{args.workers} workers; ground points by rays {s['rays']}")
    print("| configuration | RMSE px | max px | scenes placed | seam RMS px | grey step before | after | wall s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, rmse, mx, cov, seam, b, a, sec in rows:
        print(f"| {name} | {rmse:.3f} | {mx:.3f} | {cov} | {seam:.3f} | {b:.1f} | {a:.1f} | {sec:.1f} |")


def turbulent_strips(size: int, workers: int) -> None:
    """The table of turbulent airborne strips, sparse control, without and with dense refinement."""
    from dataclasses import replace

    from geocoder.mosaic import scene_positions

    work = Path(tempfile.mkdtemp(prefix="bench-mosaic-turbulence-"))
    scenes = [replace(s, turbulence_px=1.5, turbulence_seed=k)
              for k, s in enumerate(block_layout(3, 3, size=size, overlap=(0.2, 0.6), origin=(40.0, 40.0), seed=5))]
    ortho, transform, paths = write_block(work, scenes, size, "strip")
    extent = ortho.shape[0]
    corners = [0, 2, 6, 8]
    rows = []
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, Client(cl) as c:
        for name, control, dense in (("corner control, adjusted models", corners, False),
                                     ("corner control, dense refinement", corners, True),
                                     ("control on every scene, dense refinement", None, True)):
            out = work / f"{len(rows)}.zarr"
            t0 = time.perf_counter()
            ds = mosaic(paths, reference=work / "ortho.tif", out=out, tile=256, client=c, control_scenes=control, dense=dense)
            sec = time.perf_counter() - t0
            ks = [int(p.rsplit("strip", 1)[-1].split(".")[0]) for p in json.loads(ds.attrs["scenes"])]
            own, seam = mosaic_errors(ds, [scenes[k].to_ortho for k in ks], [(size, size)] * len(ks), transform,
                                      positions=scene_positions(ds, out))
            own = own[np.isfinite(own)]
            how = json.loads(ds.attrs["summary"]).get("dense_refined") or ["-"] * len(ks)
            rows.append((name, float(np.sqrt(np.mean(own**2))), float(own.max()), own.size,
                         float(np.sqrt(np.mean(seam**2))), "; ".join(f"{k}: {h}" for k, h in zip(ks, how)), sec))
    print(f"\nTurbulent strips: 3 x 3 block of {size}² airborne scenes (scan-line turbulence up to 1.5 px) over a "
          f"{extent}² Sentinel-2 crop, 20 % overlap, 60 % sidelap; {workers} workers")
    print("| configuration | RMSE px | max px | valid px | seam RMS px | refined (scene: how) | wall s |")
    print("|---|---:|---:|---:|---:|---|---:|")
    for name, rmse, mx, n, seam, how, sec in rows:
        print(f"| {name} | {rmse:.3f} | {mx:.3f} | {n} | {seam:.3f} | {how} | {sec:.1f} |")


if __name__ == "__main__":
    main()
