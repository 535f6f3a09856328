"""How far one round of the every-pixel pass moves a pixel toward the truth, and what a curved field leaves (issue 14).

The every-pixel pass (:func:`geocoder.kernels.fieldlsq.field_lsq`, ``gradients="template"``)
samples the image on the field smoothed over the template's box and moves every pixel to that
smoothed field plus its template's shift. The shift is a least-squares fit whose design is the
base template's slopes (central differences), which carry the base image's noise: a noisy
regressor attenuates the fit (errors in variables), so one round takes back only a share
``lambda ~ S / (S + N)`` of an error of the start (``S``: the slopes' energy, ``N``: their
noise's, ``sigma^2 / 2`` per pixel for central differences), and the rest stays.

On a crop of the Sentinel-2 scene warped by a known affine field (no noise but the one added,
starts on the truth, 320 x 320, tile region away from the edges) this prints:

* per noise level (fraction of the crop's grey-value range, as ``make_pair``'s ``noise``, added
  to both images): the ratio of the slopes' noise variance to their mean energy over the crop in
  x and y; the share ``N / (S + N)`` a template's own slopes predict, averaged over the templates
  (low-texture templates lose most); and the share of a 0.2 px offset of the start that is left
  after 1, 2 and 3 rounds (``1 - lambda`` per round for a smooth error);
* the matches' mean error that changes sign with a curvature of the field along the lines
  (``+-curvature`` per px, both axes): a box mean carries half the curvature times the box's
  second moment (217 px^2 for 51 columns), which the attenuated shifts take back only in part,
  so the rounds settle on ``(1 - lambda) / lambda`` of it.

Usage::

    python benchmarks/bench_attenuation.py [--noise 0,0.005,0.01,0.02] [--curvature 2e-4]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
S2 = ROOT.parent / "shared" / "data" / "s2_arosics" / "ref_S2A_20160608T153121_T33UUU_sub.tif"
SIZE, MARGIN = 320, 32
REGION = (60, SIZE - 60, 110, SIZE - 110)
AFFINE = [[0.011, 0.004, 0.37], [0.013, -0.006, -0.29]]


def _crop() -> np.ndarray:
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(S2) as f:
        return f.read(1, window=Window(1100, 300, SIZE + 2 * MARGIN, SIZE + 2 * MARGIN)).astype(np.float64)


def _pair(src: np.ndarray, noise: float, curvature: float = 0.0):
    from geocoder.simulate.warp import WarpField, make_pair

    warp = WarpField(affine=AFFINE, quadratic=[[curvature, 0, 0], [curvature, 0, 0]],
                     centre=((SIZE - 1) / 2, (SIZE - 1) / 2), turbulence_x=[], turbulence_y=[])
    pair = make_pair(src, shape=(SIZE, SIZE), seed=5, margin=MARGIN, noise=noise, gain=(1.0, 1.0), offset=0.0, warp=warp)
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    return pair, xs + pair.dx, ys + pair.dy


def main() -> None:
    from geocoder.kernels.fieldlsq import field_lsq

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", default="0,0.005,0.01,0.02")
    ap.add_argument("--curvature", type=float, default=2e-4)
    args = ap.parse_args()
    src = _crop()
    clean, _, _ = _pair(src, 0.0)
    gy, gx = np.gradient(clean.base[0].astype(np.float64))
    sl = (slice(REGION[0], REGION[1]), slice(REGION[2], REGION[3]))
    p1, p99 = np.percentile(clean.base[0], [1, 99])
    every = np.ones((SIZE, SIZE), bool)
    offset = 0.2
    from scipy.ndimage import uniform_filter

    # each template's own slopes' energy (51 x 7 box)
    sxx, syy = (uniform_filter(g * g, size=(7, 51))[sl] for g in (gx, gy))
    print("| noise | slopes' noise / mean energy, x / y | N / (S + N) per template, mean, x / y |"
          " start offset left after 1 round, x / y | after 2 | after 3 |"
          f" mean error from a curvature of +-{args.curvature:g} / px, x / y (2 rounds) | box mean's bias |")
    print("|---:|---|---|---|---|---|---|---:|")
    for noise in (float(v) for v in args.noise.split(",")):
        pair, tx, ty = _pair(src, noise)
        base, dist = pair.base[0], pair.distorted[0]
        var = (noise * (p99 - p1)) ** 2 / 2.0
        row = (f"| {noise:g} | {var / np.mean(gx[sl] ** 2):.2f} / {var / np.mean(gy[sl] ** 2):.2f} | "
               f"{np.mean(var / (sxx + var)):.2f} / {np.mean(var / (syy + var)):.2f} |")
        for rounds in (1, 2, 3):
            on = field_lsq(base, dist, tx, ty, every, REGION, iterations=rounds, tol=10.0)
            off = field_lsq(base, dist, tx + offset, ty + offset, every, REGION, iterations=rounds, tol=10.0)
            ok = (on.code == 0) & (off.code == 0)
            row += f" {np.mean((off.x - on.x)[ok]) / offset:.2f} / {np.mean((off.y - on.y)[ok]) / offset:.2f} |"
        means = []
        for sign in (1.0, -1.0):
            pair, tx, ty = _pair(src, noise, sign * args.curvature)
            res = field_lsq(pair.base[0], pair.distorted[0], tx, ty, every, REGION, iterations=2)
            ok = res.code == 0
            means.append((np.mean((res.x - tx[sl])[ok]), np.mean((res.y - ty[sl])[ok])))
        half = 0.5 * np.subtract(*means)
        row += f" {half[0]:+.4f} / {half[1]:+.4f} | {0.5 * 2 * args.curvature * (51 ** 2 - 1) / 12:.4f} |"
        print(row, flush=True)


if __name__ == "__main__":
    main()
