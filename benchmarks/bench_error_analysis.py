"""Seed 003's error analysis on real pairs with no truth (issue 15, item 4); prints two tables.

Seed 003 (sec. 14 a) proposes to measure the registration's true accuracy by distorting an
orthoimage with the displacement field a real registration produced and registering it
back. For every real pair of ../shared/data (README 'What belongs together', A-D, as
``benchmarks/bench_real_pairs.py`` registers them):

1. the pair is registered (dense, default options): its field ``d`` on the base grid, as
   registered (every status but ``outside``), with the accuracy it claims (``sigma_x``,
   ``sigma_y``) and the grey-level residual of its matched pixels (std of base minus the
   registered image after a least-squares gain and offset);
2. the base band itself is distorted by ``d`` (:func:`geocoder.testing.distort_by_field`:
   Newton inversion of ``p + d(p) = q`` on the real distorted grid, one cubic resampling),
   low-pass filtered first when the field shrinks the image (pairs B and C: 30 m and 10 m
   distorted grids over a 10 m and 5 m base), and written as a GeoTIFF with the real
   distorted image's georeference, so the new pair's true field is exactly ``d``;
3. the new pair is registered back with :func:`geocoder.register` and the recovered field is
   compared with ``d`` (:func:`geocoder.testing.field_errors`), on base pixels where ``d`` is
   one-to-one, in two variants: ``clean`` (the only noise is the base's own, shared by both
   images) and ``noise`` (Gaussian noise added to the distorted image so that the pair's
   grey-level residual equals the real pair's: the seed's variant).

Table 1 per pair and variant: the real registration's matched share of its overlap and its
claimed RMS sigma; the real field's roughness (RMS of ``d`` minus its mean over the 51 x 7
template, on the real matched pixels: what no template can recover); per status of the new
registration its share of the overlap, RMSE and share off by more than 1 px; the matched
pixels' RMSE per axis, against ``d`` and against ``d`` averaged over the template; the new
registration's RMS sigma and its calibration RMSE / RMS(sigma) per axis; the same RMSE over
the RMS sigma the real registration claimed. Table 2 splits the
matched pixels by texture class: terciles of the base's gradient energy over the template.

Usage::

    python benchmarks/bench_error_analysis.py [--pairs A,B,C,D] [--workers 2] [--tile 512]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi
from bench_real_pairs import DATA, PAIRS

#: Rows x columns of the dense template (``DenseOptions`` default: 51 x 7, long along the line).
TEMPLATE = (7, 51)


def antialias(image: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, float]:
    """Low-pass ``image`` when the field shrinks it (distorted pixel larger than a base pixel).

    The scale is ``1 / sqrt(det(I + grad d))`` of the field's mean gradient; a Gaussian of
    ``0.5 sqrt(s^2 - 1)`` px (the extra blur of a pixel ``s`` times larger) is applied with NaN
    as nodata (normalised convolution). Returns the image and ``s``.
    """
    grads = [np.nanmedian(g) for g in (*np.gradient(dx)[::-1], *np.gradient(dy)[::-1])]
    det = (1 + grads[0]) * (1 + grads[3]) - grads[1] * grads[2]
    scale = 1.0 / np.sqrt(det)
    if scale < 1.2:
        return image, float(scale)
    sigma = 0.5 * np.sqrt(scale**2 - 1.0)
    valid = np.isfinite(image)
    num = ndi.gaussian_filter(np.where(valid, image, 0.0), sigma)
    den = ndi.gaussian_filter(valid.astype(np.float64), sigma)
    return np.where(valid, num / np.maximum(den, 1e-6), np.nan), float(scale)


def texture_classes(image: np.ndarray, evaluated: np.ndarray) -> dict[str, np.ndarray]:
    """Terciles of the gradient energy over the template (``mean |grad|^2``) on ``evaluated``."""
    gy, gx = np.gradient(np.nan_to_num(image.astype(np.float64)))
    energy = ndi.uniform_filter(gx**2 + gy**2, TEMPLATE)
    lo, hi = np.percentile(energy[evaluated], [100 / 3, 200 / 3])
    return {"low": evaluated & (energy < lo), "mid": evaluated & (energy >= lo) & (energy < hi),
            "high": evaluated & (energy >= hi)}


def run_pair(client, work: Path, name: str, base_rel: str, dist_rel: str, kw: dict, *, tile: int, seed: int) -> list[dict]:
    """Register the real pair, build its synthetic twins, register them; one figures dict per variant."""
    import rasterio

    import geocoder
    from geocoder.kernels.resample import sample
    from geocoder.scene import write_geotiff
    from geocoder.status import Status
    from geocoder.testing import distort_by_field, field_errors, residual_noise, template_mean

    tag = name.split(":")[0]
    band, dist_band = kw.get("band", 1), kw.get("dist_band", kw.get("band", 1))
    t0 = time.perf_counter()
    real = geocoder.register(DATA / base_rel, DATA / dist_rel, out=work / f"{tag}-real.zarr", client=client, tile=tile,
                             show_progress=False, **kw)
    t_real = time.perf_counter() - t0
    st = real.status.values
    dx = np.where(st != Status.OUTSIDE, real.dx.values.astype(np.float64), np.nan)
    dy = np.where(st != Status.OUTSIDE, real.dy.values.astype(np.float64), np.nan)
    rm = st == Status.MATCHED
    base = geocoder.open_scene(DATA / base_rel, nodata=kw.get("nodata")).isel(band=band - 1).values.astype(np.float64)
    registered = real.registered.isel(band=dist_band - 1).values
    real_noise = residual_noise(base, registered, rm)
    with rasterio.open(DATA / dist_rel) as f:
        dist_shape, dist_transform, dist_crs = (f.height, f.width), f.transform, f.crs
    hf = [template_mean(a) - a for a in (dx, dy)]
    claimed = {"matched_share": float(rm.sum() / (st != Status.OUTSIDE).sum()),
               "rms_sigma": tuple(float(np.sqrt(np.mean(s.values[rm].astype(np.float64) ** 2))) for s in (real.sigma_x, real.sigma_y)),
               "roughness": tuple(float(np.sqrt(np.nanmean(h[rm] ** 2))) for h in hf),
               "tiepoint_rms": json.loads(real.attrs["summary"])["rms"], "noise": real_noise, "seconds": t_real}
    print(f"{tag} real: {t_real:.1f} s, {json.dumps(claimed)}", file=sys.stderr, flush=True)

    source, scale = antialias(base, dx, dy)
    clean, truth_ok = distort_by_field(source, dx, dy, dist_shape, method="cubic")
    ys, xs = np.mgrid[0 : dx.shape[0], 0 : dx.shape[1]].astype(np.float64)
    back = sample(clean, xs + dx, ys + dy, method="bilinear")
    own_noise = residual_noise(base, back, rm & truth_ok)
    added = float(np.sqrt(max(real_noise**2 - own_noise**2, 0.0)))
    rng = np.random.default_rng(seed)
    variants = {"clean": clean, "noise": (clean + rng.normal(0.0, added, clean.shape)).astype(np.float32)}
    rows = []
    for variant, image in variants.items():
        path = work / f"{tag}-{variant}.tif"
        write_geotiff(path, image, transform=dist_transform, crs=dist_crs)
        t0 = time.perf_counter()
        syn = geocoder.register(DATA / base_rel, path, out=work / f"{tag}-{variant}.zarr", client=client, tile=tile,
                                show_progress=False, band=band, dist_band=1, nodata=kw.get("nodata"))
        wall = time.perf_counter() - t0
        f = field_errors(syn, dx, dy, truth_ok)
        sm = syn.status.values == Status.MATCHED
        ev = truth_ok & (syn.status.values != Status.OUTSIDE) & np.isfinite(dx)
        tx, ty = template_mean(dx), template_mean(dy)
        f["rmse_smoothed"] = tuple(float(np.sqrt(np.nanmean((syn[v].values[sm & ev] - t[sm & ev]) ** 2)))
                                   for v, t in (("dx", tx), ("dy", ty)))
        f["texture"] = {}
        for cls, m in texture_classes(base, ev).items():
            g = field_errors(syn, dx, dy, m)
            f["texture"][cls] = (g["groups"]["matched"][0], g["groups"]["matched"][1], g["calibration"])
        f.update(pair=name, variant=variant, claimed=claimed, scale=scale, added_noise=added if variant == "noise" else 0.0,
                 own_noise=own_noise, seconds=wall)
        print(f"{tag} {variant}: {wall:.1f} s, {json.dumps(f, default=str)}", file=sys.stderr, flush=True)
        rows.append(f)
    return rows


def print_tables(rows: list[dict]) -> None:
    """The two markdown tables."""
    def cell(g):
        share, rmse, over = g
        return f"{share:.1%}, {rmse:.3f}, {over:.2%}" if share > 0 else "–"

    print("\n| pair | variant | real residual / added noise DN | real: matched share, claimed RMS σ x / y px "
          "| real field roughness x / y px | matched: share, RMSE, > 1 px | filled | estimated | rest "
          "| all overlap: RMSE, > 1 px | matched RMSE x / y px | vs truth over template x / y px "
          "| RMS σ x / y px | calibration x / y | matched RMSE / real claimed σ x / y | wall s |")
    print("|---|---|---:|---|---|---|---|---|---|---|---|---|---|---|---|---:|")
    for f in rows:
        c, g = f["claimed"], f["groups"]
        print(f"| {f['pair']} | {f['variant']} | {c['noise']:.1f} / {f['added_noise']:.1f} "
              f"| {c['matched_share']:.1%}, {c['rms_sigma'][0]:.3f} / {c['rms_sigma'][1]:.3f} "
              f"| {c['roughness'][0]:.3f} / {c['roughness'][1]:.3f} "
              f"| {cell(g['matched'])} | {cell(g['filled'])} | {cell(g['estimated'])} | {cell(g['rest'])} "
              f"| {g['all'][1]:.3f}, {g['all'][2]:.2%} | {f['rmse_xy'][0]:.3f} / {f['rmse_xy'][1]:.3f} "
              f"| {f['rmse_smoothed'][0]:.3f} / {f['rmse_smoothed'][1]:.3f} "
              f"| {f['rms_sigma'][0]:.3f} / {f['rms_sigma'][1]:.3f} "
              f"| {f['calibration'][0]:.2f} / {f['calibration'][1]:.2f} "
              f"| {f['rmse_xy'][0] / c['rms_sigma'][0]:.2f} / {f['rmse_xy'][1] / c['rms_sigma'][1]:.2f} | {f['seconds']:.1f} |")
    print("\nBy texture class (terciles of the base's gradient energy over the 51 x 7 template), matched pixels:")
    print("| pair | variant | class | matched share of the class | RMSE px | calibration x / y |")
    print("|---|---|---|---:|---:|---|")
    for f in rows:
        for cls, (share, rmse, cal) in f["texture"].items():
            print(f"| {f['pair']} | {f['variant']} | {cls} | {share:.1%} | {rmse:.3f} | {cal[0]:.2f} / {cal[1]:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", default="A,B,C,D", help="letters of bench_real_pairs.PAIRS")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from distributed import Client

    from geocoder.runtime import local_cluster

    wanted = set(args.pairs.split(","))
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-error-analysis-") as tmp, local_cluster(args.workers) as cluster, \
            Client(cluster) as client:
        for name, base, dist, kw in PAIRS:
            if name.split(":")[0] in wanted:
                rows += run_pair(client, Path(tmp), name, base, dist, kw, tile=args.tile, seed=args.seed)
    print_tables(rows)


if __name__ == "__main__":
    main()
