"""Dense field quality over many cases (issue 14): accuracy per status, coverage, calibration, hole filling.

Every case is a real image (Sentinel-2, Landsat 7, two aerial photographs from ../shared/data)
or the demo's synthetic texture, cut and warped by the simulator (affine + quadratic up to
15 px, scan-line turbulence of the given strength or none, on two cases a relief-like
displacement that varies along the lines over 30-225 px, 2 % noise, gain and offset), so
every pixel has a known true displacement. Each case is registered twice on one local
cluster: with full region growing (``DenseOptions(col_step=1, halo=4)``, the dense default
until issue 12's lattice + every-pixel pass) and with today's default. Printed per case and
mode: RMSE, share of the overlap and share off by more than 1 px per status (matched,
filled, estimated, the rest) and over the whole overlap; coverage of the textured overlap
(:func:`geocoder.testing.textured_overlap`); calibration RMSE / RMS(sigma) per axis on matched
pixels; wall time; and the global polynomial's own RMSE on the matched pixels (on a smooth
case, what the dense field should be no noisier than).

A change to the line fits must also be measured on the relief cases and on a real field
(``bench_error_analysis.py``, or ``tests/test_error_analysis.py``): without relief the
simulator's fields are a shift per line plus a smooth field, and pooling the lines' shifts
and departures across the lines, which those cases reward, left sigma optimistic (1.6 / 2.2)
on a real field with finer structure.

Then seed 003 sec. 10's check of hole filling (:func:`geocoder.testing.hole_check`), on each
case registered with the default options but without the line step (the field the line step
receives): in scan lines that are at least 90 % matched, a stretch of L matched pixels is
removed (one per line, at a random place with matches on both sides), the post-filter fills
what it can (holes up to its ``max_gap``) and the line step (the pipeline's own, on Dask) takes
the rest; the table gives, per hole length and status given, the RMS difference of the values
from the removed matches and from the truth, and the calibration of their sigma.
``--no-holes`` skips it.

Usage::

    python benchmarks/bench_dense_cases.py [--cases s2-1024,aerial-512,...] [--workers 2] [--no-holes] [--modes full,default,no-line-fit,col32,row2,tol0.05,it1,mi8,tries1,passes1,sigma0.25,rho0.6,sigma0.25rho0.6,dep0]
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"


@dataclass(frozen=True)
class Case:
    name: str
    path: str | None  # None: the demo's synthetic texture
    origin: tuple[int, int]
    size: int
    seed: int
    turbulence: tuple[float, float] | None
    relief: tuple[float, float] | None = None  # (peak px, wavelength px): structure finer than a line


CASES = {c.name: c for c in (
    Case("s2-1024", "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", (300, 1100), 1024, 22, (1.0, 3.0)),
    Case("s2-2048-strong", "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", (300, 100), 2048, 31, (2.0, 4.0)),
    Case("s2-1024-smooth", "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", (1300, 1100), 1024, 23, None),
    Case("landsat7-576", "landsat7_rasterio/RGB.byte.tif", (20, 60), 576, 24, (1.0, 3.0)),
    Case("aerial-512", "baviaanskloof/ngi_rgb_byte_1.tif", (60, 107), 512, 21, (1.0, 3.0)),
    Case("aerial2-512-mild", "baviaanskloof/3324c_2015_1004_05_0182_RGB.tif", (300, 16), 512, 25, (0.5, 1.5)),
    Case("demo-1024-smooth", None, (0, 0), 1024, 0, None),
    # relief-like structure along the lines (0.5 px peak), finer than any line fit: of wavelengths
    # near the template's width (mostly averaged away by it) and near three times it
    Case("s2-1024-relief60", "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", (300, 1100), 1024, 22, (1.0, 3.0),
         relief=(0.5, 60.0)),
    Case("s2-1024-relief150", "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", (300, 1100), 1024, 22, (1.0, 3.0),
         relief=(0.5, 150.0)),
)}



def make_case(case: Case, work: Path):
    """Write the pair's two GeoTIFFs; return (base path, distorted path, SyntheticPair)."""
    import rasterio
    from affine import Affine

    from geocoder.scene import write_geotiff
    from geocoder.simulate.texture import synthetic_ortho
    from geocoder.simulate.warp import make_pair

    margin = 48
    if case.path is None:
        src = synthetic_ortho((case.size + 2 * margin,) * 2, seed=case.seed)
        pair = make_pair(src, shape=(case.size, case.size), seed=case.seed, max_displacement=15.0, margin=margin)
        transform, crs = Affine(2, 0, 500000, 0, -2, 4000000), "EPSG:32633"
    else:
        r0, c0 = case.origin
        n = case.size + 2 * margin
        with rasterio.open(SHARED / case.path) as f:
            src = f.read(1, window=((r0, r0 + n), (c0, c0 + n))).astype(np.float32)
            nodata = f.nodata
            transform, crs = f.transform * Affine.translation(c0 + margin, r0 + margin), f.crs
        if not transform.is_rectilinear:  # a rotated georeference: the case is about the pixels
            transform, crs = Affine.identity(), None
        if src.shape != (n, n):
            raise SystemExit(f"{case.name}: crop {src.shape} out of {case.path}")
        if nodata is not None:
            src[src == nodata] = np.nan
        pair = make_pair(src, shape=(case.size, case.size), seed=case.seed, margin=margin, turbulence=case.turbulence,
                         relief=case.relief)
    base, dist = work / f"{case.name}-base.tif", work / f"{case.name}-dist.tif"
    write_geotiff(base, pair.base, transform=transform, crs=crs)
    write_geotiff(dist, pair.distorted)
    return base, dist, pair


def figures(ds, pair) -> dict:
    """Per-status accuracy, coverage of the textured overlap and calibration against the truth."""
    from geocoder import Status
    from geocoder.testing import textured_overlap

    st = ds.status.values
    ex, ey = ds.dx.values - pair.dx, ds.dy.values - pair.dy
    err = np.hypot(ex, ey)
    inside = (st != Status.OUTSIDE) & np.isfinite(pair.dx)
    out = {}
    groups = {
        "matched": st == Status.MATCHED, "filled": st == Status.FILLED, "estimated": st == Status.ESTIMATED,
        "rest": inside & ~np.isin(st, [Status.MATCHED, Status.FILLED, Status.ESTIMATED]), "all": inside,
    }
    for name, m in groups.items():
        m = m & inside
        e = err[m]
        out[name] = (float(m.sum() / inside.sum()), float(np.sqrt(np.mean(e**2))) if e.size else np.nan,
                     float(np.mean(e > 1.0)) if e.size else np.nan)
    m = groups["matched"] & inside
    good = (groups["matched"] | groups["filled"]) & inside
    tex = textured_overlap(pair) & inside
    out["coverage"] = float((good & tex).sum() / max(tex.sum(), 1))
    out["rmse_good"] = float(np.sqrt(np.mean(err[good] ** 2)))
    # the global polynomial alone on the matched pixels: where it explains the field (a smooth
    # case), the dense field should be no noisier than it (issue 14)
    from geocoder.kernels.polynomial import PolyMap

    mapping = PolyMap.from_dict(json.loads(ds.attrs["mapping"]))
    rows, cols = np.nonzero(m)
    px, py = mapping(cols.astype(np.float64), rows.astype(np.float64))
    out["rmse_polynomial"] = float(np.sqrt(np.mean((px - cols - pair.dx[m]) ** 2 + (py - rows - pair.dy[m]) ** 2)))
    out["calibration"] = tuple(
        float(np.sqrt(np.mean(e[m] ** 2)) / np.sqrt(np.mean(s[m] ** 2))) for e, s in ((ex, ds.sigma_x.values), (ey, ds.sigma_y.values))
    )
    known = np.isfinite(ds.sigma_x.values) & np.isfinite(ds.sigma_y.values)
    for name in ("estimated", "filled"):
        sel = groups[name] & inside & known
        out[f"calibration_{name}"] = tuple(
            float(np.sqrt(np.mean(e[sel] ** 2)) / np.sqrt(np.mean(s[sel] ** 2))) if sel.any() else np.nan
            for e, s in ((ex, ds.sigma_x.values), (ey, ds.sigma_y.values))
        )
    filled = groups["filled"] & inside
    out["filled_without_sigma"] = int((filled & ~known).sum())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--modes", default="full,default")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--no-holes", action="store_true", help="skip the hole check")
    args = ap.parse_args()
    from distributed import Client

    from geocoder import register
    from geocoder.pipeline.dense import DenseOptions
    from geocoder.pipeline.register import RegisterOptions
    from geocoder.quality.lines import LineOptions
    from geocoder.runtime import local_cluster
    from geocoder.testing import hole_check

    modes = {"full": RegisterOptions(matching=DenseOptions(col_step=1, halo=4)), "default": None,
             "no-line-fit": RegisterOptions(lines=LineOptions(fit_order=-1))}
    for mode in args.modes.split(","):  # "colN": the lattice on every N-th column (halo N); "tolX": lattice_tol X; "itN": densify rounds
        if re.fullmatch(r"col\d+", mode):
            n = int(mode[3:])
            modes[mode] = RegisterOptions(matching=DenseOptions(col_step=n, halo=max(n, 16)))
        elif m := re.fullmatch(r"row(\d+)(?:tol([0-9.]+))?", mode):  # "rowN[tolX]": the lattice on every N-th row
            tol = {"lattice_tol": float(m[2])} if m[2] else {}
            modes[mode] = RegisterOptions(matching=DenseOptions(row_step=int(m[1]), **tol))
        elif re.fullmatch(r"tol[0-9.]+", mode):
            modes[mode] = RegisterOptions(matching=DenseOptions(lattice_tol=float(mode[3:])))
        elif re.fullmatch(r"it\d+", mode):  # "itN": N resampling rounds of the every-pixel pass
            modes[mode] = RegisterOptions(matching=DenseOptions(densify_iterations=int(mode[2:])))
        elif re.fullmatch(r"mi\d+", mode):  # "miN": at most N Gauss-Newton updates per lattice match
            alsc = DenseOptions().alsc
            modes[mode] = RegisterOptions(matching=DenseOptions(alsc=replace(alsc, max_iter=int(mode[2:]))))
        elif re.fullmatch(r"ext\d+", mode):  # "extN": the every-pixel pass starts N px past a line's last lattice match
            modes[mode] = RegisterOptions(matching=DenseOptions(densify_extend=int(mode[3:])))
        elif re.fullmatch(r"gap\d+", mode):  # "gapN": ... and across gaps of the lattice up to N px
            modes[mode] = RegisterOptions(matching=DenseOptions(densify_gap=int(mode[3:])))
        elif re.fullmatch(r"dep[0-9.]+", mode):  # "depK": matches K sigma off their line flagged (0: never)
            modes[mode] = RegisterOptions(lines=LineOptions(max_departure=float(mode[3:])))
        elif m := re.fullmatch(r"(?:sigma([0-9.]+))?(?:rho([0-9.]+))?", mode):  # "sigmaXrhoY": accepted up to sigma
            # X px, from correlation Y (lattice and every pixel); either may be left out
            alsc = DenseOptions().alsc
            alsc = replace(alsc, **({"max_sigma": float(m[1])} if m[1] else {}), **({"min_rho": float(m[2])} if m[2] else {}))
            modes[mode] = RegisterOptions(matching=DenseOptions(alsc=alsc))
        elif re.fullmatch(r"tries\d+", mode):  # "triesN": attempts per lattice pixel
            modes[mode] = RegisterOptions(matching=DenseOptions(max_tries=int(mode[5:])))
        elif re.fullmatch(r"passes\d+", mode):  # "passesN": correspondence passes (tie points for the polynomial)
            modes[mode] = RegisterOptions(passes=int(mode[6:]))
    table, holes = [], []
    with tempfile.TemporaryDirectory(prefix="bench-dense-cases-") as tmp, local_cluster(args.workers) as cluster, \
            Client(cluster) as client:
        work = Path(tmp)
        for name in args.cases.split(","):
            case = CASES[name]
            base, dist, pair = make_case(case, work)
            for mode in args.modes.split(","):
                out = work / f"{name}-{mode}.zarr"
                t0 = time.perf_counter()
                ds = register(base, dist, out=out, tile=args.tile, client=client, options=modes[mode], show_progress=False)
                wall = time.perf_counter() - t0
                f = figures(ds, pair)
                table.append((name, mode, wall, f))
                print(f"{name} {mode}: {wall:.1f} s, {json.dumps(f)}", file=sys.stderr, flush=True)
                shutil.rmtree(out, ignore_errors=True)
            if not args.no_holes:  # the default's field before the line step, for the hole check
                out = work / f"{name}-before-lines.zarr"
                ds = register(base, dist, out=out, tile=args.tile, client=client, show_progress=False,
                              options=RegisterOptions(lines=LineOptions(enabled=False)))
                holes += [(name, r) for r in hole_check(ds, pair.dx, pair.dy, str(work / f"{name}-holes"), seed=case.seed)]
                shutil.rmtree(out, ignore_errors=True)
    print("\n| case | mode | wall s | coverage of textured overlap | RMSE matched+filled | calibration x / y "
          "| matched: share, RMSE, > 1 px | filled | calibration filled x / y | estimated | calibration estimated x / y | rest "
          "| all overlap: RMSE, > 1 px | polynomial alone on the matched pixels: RMSE |")
    print("|---|---|---:|---:|---:|---|---|---|---|---|---|---|---|---:|")
    for name, mode, wall, f in table:
        def cell(k):
            share, rmse, over = f[k]
            return f"{share:.1%}, {rmse:.3f}, {over:.2%}" if share > 0 else "–"
        print(f"| {name} | {mode} | {wall:.1f} | {f['coverage']:.1%} | {f['rmse_good']:.3f} | "
              f"{f['calibration'][0]:.2f} / {f['calibration'][1]:.2f} | {cell('matched')} | {cell('filled')} | "
              f"{f['calibration_filled'][0]:.2f} / {f['calibration_filled'][1]:.2f} | "
              f"{cell('estimated')} | {f['calibration_estimated'][0]:.2f} / {f['calibration_estimated'][1]:.2f} | {cell('rest')} | {f['all'][1]:.3f}, {f['all'][2]:.2%} | {f['rmse_polynomial']:.3f} |")
    print("\nHole filling (seed 003 sec. 10, geocoder.testing.hole_check): stretches of L matches removed from lines >= 90 %"
          " matched in the default's field before the line step, then the post-filter (holes <= its max_gap) and the line step")
    print("| case | L px | by | pixels | RMS vs removed matches px | RMSE vs truth px | > 1 px vs truth | calibration x / y |")
    print("|---|---:|---|---:|---:|---:|---:|---|")
    for name, r in holes:
        if r["pixels"]:
            print(f"| {name} | {r['length']} | {r['by']} | {r['pixels']} | {r['rms_vs_match']:.3f} | {r['rmse']:.3f} | "
                  f"{r['over_1px']:.2%} | {r['calibration'][0]:.2f} / {r['calibration'][1]:.2f} |")


if __name__ == "__main__":
    main()
