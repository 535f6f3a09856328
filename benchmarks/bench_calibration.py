"""Where the matched pixels' sigma comes from after the line step, against their error (issue 14).

The matches leave the every-pixel pass with a sigma of their own; the line step
(:func:`geocoder.quality.line_fits.shrink_block`, in :func:`geocoder.pipeline.lines.line_field`)
shrinks each toward its line's fit by ``keep = tau2 / (tau2 + s^2)`` (``tau2``: how far the line
departs from its fit beyond the matches' noise) and gives it the sigma

    sigma^2 = min(keep^2 (s^2 + tau2) + (1 - keep)^2 (v_fit + tau2), s^2 + tau2)

(``v_fit``: the variance of the shrunk fit at the pixel). For every case of
``bench_dense_cases.py`` this registers the pair with the line step off (the field it receives),
applies the pipeline's own line fits and shrinkage to it in this process (fitted over the whole
scene at once, as the pipeline's tile sums add up to), and prints per axis:

* the raw matches: RMSE, RMS sigma, calibration (RMSE / RMS sigma);
* after the shrinkage: the same, and each term of ``sigma^2`` (RMS over the matched pixels):
  ``keep^2 s^2`` (the match's own noise kept), ``keep^2 tau2`` (the line's departure counted as
  the kept match's error), ``(1 - keep)^2 v_fit`` and ``(1 - keep)^2 tau2``; the mean ``keep``
  and the share of rows with ``tau2 > 0``;
* the fit alone (``keep = 0``): its RMSE against the truth and ``sqrt(mean v_fit)``;
* the raw errors' correlation along the lines (sum of their autocorrelation over lags -119..119,
  row means removed: the number of neighbouring matches that share one's error, which the
  line fits take to be the template's length) and across them (lags -7..7, the template's
  height by the same assumption).

With ``--check`` each case is also registered with the default options and the calibration of
its matched pixels printed beside the one computed here (they agree when the replay is exact).

Usage::

    python benchmarks/bench_calibration.py [--cases demo-1024-smooth,s2-1024-relief150,...] [--workers 2] [--check]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(v)))) if v.size else float("nan")


def _correlation_length(e: np.ndarray, lags: int, axis: int) -> float:
    """``1 + 2 sum_k rho(k)`` (k = 1 .. lags) of ``e`` along ``axis``, NaN where unknown."""
    v0 = np.nanmean(e * e)
    total = 1.0
    for k in range(1, lags + 1):
        a = e[:, k:] * e[:, :-k] if axis == 1 else e[k:, :] * e[:-k, :]
        total += 2.0 * np.nanmean(a) / v0
    return float(total)


def decompose(raw, pair, options) -> dict:
    """The line step's shrinkage replayed on ``raw`` (a registration without it), per axis."""
    from geocoder import Status
    from geocoder.kernels.polynomial import PolyMap
    from geocoder.pipeline.resample import poly_grid
    from geocoder.quality.line_fits import fit_sums, fit_table, line_coordinate, line_fits, shrink_block

    h, w = raw.status.shape
    mapping = PolyMap.from_dict(json.loads(raw.attrs["mapping"]))
    px, py = poly_grid(mapping, (0, h), (0, w), 0), poly_grid(mapping, (0, h), (0, w), 1)
    matched = raw.status.values == Status.MATCHED
    dx, dy, sx, sy = (raw[k].values.astype(np.float64) for k in ("dx", "dy", "sigma_x", "sigma_y"))
    alsc, lines = options.matching.alsc, options.lines
    correlation = 2 * alsc.radius + 1
    fits = line_fits(fit_sums(dx - px, dy - py, sx, sy, matched, col0=0, width=w), order=lines.fit_order,
                     min_count=max(lines.min_count, 2 * correlation), correlation=correlation,
                     line_correlation=2 * alsc.ry + 1)
    table = fit_table(fits)
    u = line_coordinate(np.arange(w), w)
    ox, oy, osx, osy = shrink_block(dx, dy, px, py, matched, sx, sy, u, table)
    out = {}
    for a, (d, p, s, o, so, truth) in enumerate(((dx, px, sx, ox, osx, pair.dx), (dy, py, sy, oy, osy, pair.dy))):
        m = matched & np.isfinite(truth) & np.isfinite(s) & fits.ok[:, None]
        c = table[:, 1 + 3 * a : 4 + 3 * a]
        fit = c[:, :1] + c[:, 1:2] * u + c[:, 2:3] * u**2
        lev = fits.lev[a]
        v_fit = np.minimum(sum(lev[:, k : k + 1] * u**k for k in range(5)), (fits.spread_x, fits.spread_y)[a][:, None])
        tau2 = np.broadcast_to((fits.tau2_x, fits.tau2_y)[a][:, None], (h, w))
        s2 = s * s
        keep = tau2 / np.maximum(tau2 + s2, 1e-300)
        err = np.where(m, d - truth, np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # rows without a match
            err -= np.nanmean(err, axis=1, keepdims=True)
        out["xy"[a]] = {
            "raw": (_rms((d - truth)[m]), _rms(s[m])),
            "shrunk": (_rms((o - truth)[m]), _rms(so[m])),
            "terms": tuple(_rms(np.sqrt(t[m])) for t in (keep**2 * s2, keep**2 * tau2, (1 - keep) ** 2 * v_fit,
                                                          (1 - keep) ** 2 * tau2)),
            "keep": float(keep[m].mean()),
            "rows_departing": float(np.mean((fits.tau2_x, fits.tau2_y)[a][fits.ok] > 0)),
            "fit": (_rms((p + fit - truth)[m]), float(np.sqrt(np.mean(v_fit[m])))),
            "along": _correlation_length(err, 119, 1),
            "across": _correlation_length(err, 7, 0),
        }
    return out


def main() -> None:
    import bench_dense_cases as cases
    from distributed import Client

    from geocoder import Status, register
    from geocoder.pipeline.register import RegisterOptions
    from geocoder.quality.lines import LineOptions
    from geocoder.runtime import local_cluster

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(cases.CASES))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--check", action="store_true", help="also register with the line step and compare")
    args = ap.parse_args()
    rows, checks = [], {}
    options = RegisterOptions()
    with tempfile.TemporaryDirectory(prefix="bench-calibration-") as tmp, local_cluster(args.workers) as cluster, \
            Client(cluster) as client:
        work = Path(tmp)
        for name in args.cases.split(","):
            base, dist, pair = cases.make_case(cases.CASES[name], work)
            raw = register(base, dist, out=work / f"{name}-raw.zarr", tile=args.tile, client=client, show_progress=False,
                           options=RegisterOptions(lines=LineOptions(enabled=False))).load()
            rows.append((name, decompose(raw, pair, options)))
            if args.check:
                ds = register(base, dist, out=work / f"{name}.zarr", tile=args.tile, client=client, show_progress=False).load()
                m = ds.status.values == Status.MATCHED
                checks[name] = [_rms((ds[d].values - t)[m & np.isfinite(t)]) / _rms(ds[s].values[m & np.isfinite(t)])
                                for d, s, t in (("dx", "sigma_x", pair.dx), ("dy", "sigma_y", pair.dy))]
            print(name, json.dumps(rows[-1][1]), file=sys.stderr, flush=True)
    print("\n| case | axis | raw: RMSE / RMS sigma = cal | shrunk: RMSE / RMS sigma = cal | sigma terms: keep² s², keep² tau2, "
          "(1-keep)² v_fit, (1-keep)² tau2 | mean keep | rows tau2 > 0 | fit alone: RMSE / sqrt v_fit | correlation along / across"
          + (" | pipeline cal |" if args.check else " |"))
    print("|---|---|---|---|---|---:|---:|---|---|" + ("---|" if args.check else ""))
    for name, r in rows:
        for a in "xy":
            f = r[a]
            (e0, s0), (e1, s1) = f["raw"], f["shrunk"]
            terms = ", ".join(f"{t:.4f}" for t in f["terms"])
            line = (f"| {name} | {a} | {e0:.4f} / {s0:.4f} = {e0 / s0:.2f} | {e1:.4f} / {s1:.4f} = {e1 / s1:.2f} | {terms} | "
                    f"{f['keep']:.3f} | {f['rows_departing']:.0%} | {f['fit'][0]:.4f} / {f['fit'][1]:.4f} | "
                    f"{f['along']:.1f} / {f['across']:.1f} |")
            if args.check:
                line += f" {checks[name]['xy'.index(a)]:.2f} |"
            print(line)


if __name__ == "__main__":
    main()
