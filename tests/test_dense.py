"""Dense registration against per-pixel truth, on a real LocalCluster with Zarr on disk.

Real single-band images warped by affine + quadratic (up to 15 px) + scan-line turbulence
(1-3 px, changing over tens of lines), 2 % noise, gain 0.75-1.25 and an offset.
"""

import json

import numpy as np
import pytest
import xarray as xr
from pairs import real_pair

from geocoder import RegisterOptions, Status, register
from geocoder.quality.lines import LineOptions
from geocoder.testing import textured_overlap

pytestmark = [pytest.mark.cluster, pytest.mark.data]


def dense_figures(ds, pair):
    st = ds.status.values
    ex, ey = ds.dx.values - pair.dx, ds.dy.values - pair.dy
    err = np.hypot(ex, ey)
    m = st == Status.MATCHED
    good = m | (st == Status.FILLED)
    tex = textured_overlap(pair)
    ex_m, ey_m = ex[m], ey[m]
    sx, sy = ds.sigma_x.values[m], ds.sigma_y.values[m]
    return {
        "rmse": float(np.sqrt(np.mean(err[m] ** 2))),
        "rmse_x": float(np.sqrt(np.mean(ex_m**2))),
        "rmse_y": float(np.sqrt(np.mean(ey_m**2))),
        "textured": float(tex.mean()),
        "coverage": float((good & tex).sum() / tex.sum()),
        "unflagged_over_1px": int((err[good] > 1.0).sum()),
        "calib_x": float(np.sqrt(np.mean(ex[m] ** 2)) / np.sqrt(np.mean(sx**2))),
        "calib_y": float(np.sqrt(np.mean(ey[m] ** 2)) / np.sqrt(np.mean(sy**2))),
    }


@pytest.mark.parametrize("which", ["aerial"])
def test_dense_accuracy_coverage_calibration(shared_data, tmp_path, client, which):
    files = real_pair(shared_data, tmp_path, which=which, size=512, seed=21, turbulence=(1.0, 3.0))
    out = tmp_path / "dense.zarr"
    ds = register(files.base, files.distorted, out=out, tile=256, client=client)
    f = dense_figures(ds, files.pair)
    print(which, f, json.loads(ds.attrs["summary"])["status_counts"])
    assert f["rmse"] <= 0.1  # radial: sqrt(mean(ex^2 + ey^2))
    assert f["coverage"] >= 0.95
    assert f["unflagged_over_1px"] == 0
    # issue 14's goal; measured 1.06 / 1.05 (1.16 / 1.33 before the line fits counted the
    # matches' shared errors and the lines' departures)
    assert 0.8 <= f["calib_x"] <= 1.25 and 0.8 <= f["calib_y"] <= 1.25
    # the polynomial alone cannot follow the turbulence: the dense stage is what adds it
    poly = register(files.base, files.distorted, tile=256, client=client, dense=False)
    inside = poly.status.values != Status.OUTSIDE
    poly_rmse = np.sqrt(np.mean(((poly.dx.values - files.pair.dx) ** 2 + (poly.dy.values - files.pair.dy) ** 2)[inside]))
    assert poly_rmse > 5 * f["rmse"]
    # store layout: the quality arrays are there, status codes documented
    stored = xr.open_zarr(out, consolidated=False)
    for name in ("dx", "dy", "sigma_x", "sigma_y", "correlation", "status", "registered"):
        assert name in stored
    assert set(np.unique(stored.status.values)) <= {int(s) for s in Status}


def test_low_contrast_water_is_matched(shared_data, tmp_path, client):
    """Dark sea with a few bright specks (Landsat): templates of low correlation but precise
    shifts are matched, not left to the line estimates (issue 14's coverage)."""
    files = real_pair(shared_data, tmp_path, which="landsat", size=256, seed=24, turbulence=(1.0, 3.0))
    ds = register(files.base, files.distorted, tile=256, client=client)
    f = dense_figures(ds, files.pair)
    print(f)
    # measured: coverage 0.787 (0.734 when matches needed a correlation of 0.7), RMSE 0.070 px
    # (0.067), calibration 1.06 / 1.16; since matches off their line are flagged: 0.786, 0.069 px,
    # 1.04 / 1.14
    assert f["coverage"] >= 0.76
    assert f["rmse"] <= 0.09
    assert 0.8 <= f["calib_x"] <= 1.25 and 0.8 <= f["calib_y"] <= 1.25
    # a run of four matches one line off (1.1 px, sigma 0.08, row 49) was kept until the line
    # step tested every match against its line (geocoder.quality.line_fits.departures)
    assert f["unflagged_over_1px"] == 0


def test_dense_does_not_depend_on_tiling(shared_data, tmp_path, client):
    files = real_pair(shared_data, tmp_path, which="s2", size=1024, seed=22, turbulence=(1.0, 3.0))
    # one tile (no halo exchange at all) against 16 tiles of 256 (the most exchange)
    runs = {t: register(files.base, files.distorted, tile=t, client=client) for t in (256, 1024)}
    ref = runs[1024]
    for t in (256,):
        other = runs[t]
        same = (other.status.values == ref.status.values).mean()
        both = (other.status.values == Status.MATCHED) & (ref.status.values == Status.MATCHED)
        delta = np.hypot(other.dx.values - ref.dx.values, other.dy.values - ref.dy.values)[both]
        print(t, same, delta.max(), np.percentile(delta, [99, 99.9, 99.99]), (delta > 0.01).sum(), delta.size)
        assert same >= 0.995
        assert delta.max() <= 0.01
    # unmatched pixels of a line with matches take the polynomial plus the line's mean
    # residual within the span of its matches, and beyond it (the line's ends: the template's
    # margin) the mean residual near that end (issue 14); here the turbulence is a shift per line
    st, truth = ref.status.values, files.pair
    err = np.hypot(ref.dx.values - truth.dx, ref.dy.values - truth.dy)
    est, inside = st == Status.ESTIMATED, st != Status.OUTSIDE
    both_est = est & (runs[256].status.values == Status.ESTIMATED)
    est_delta = np.hypot(runs[256].dx.values - ref.dx.values, runs[256].dy.values - ref.dy.values)[both_est]
    print("estimated", est.mean(), np.sqrt(np.mean(err[est] ** 2)), "all", np.sqrt(np.mean(err[inside] ** 2)),
          "> 1 px", (err[inside] > 1.0).mean(), "between tilings", est_delta.max(), np.percentile(est_delta, [99, 99.9, 99.99]),
          (est_delta > 0.01).sum(), est_delta.size)
    # measured 18.0 % of the base at 0.051 px, all 0.104 px with 0.42 % > 1 px (before the line
    # ends: 9.7 % at 0.036 px, all 0.274 px with 2.6 % > 1 px; the polynomial alone: 0.481); since
    # the every-pixel pass starts across gaps of 512 px: 14.0 % at 0.042 px, all 0.049 px, 0.04 % > 1 px;
    # and past the lines' ends along their chords: 13.6 % at 0.043 px, all 0.044 px
    assert est.mean() > 0.1
    assert np.sqrt(np.mean(err[est] ** 2)) <= 0.1 and (err[est] > 1.0).sum() == 0
    assert np.sqrt(np.mean(err[inside] ** 2)) <= 0.15 and (err[inside] > 1.0).mean() <= 0.005
    # the estimates follow the matches they average and the sigmas that weigh them, which differ
    # between the tilings by up to 0.0064 px (above): measured 99.9th percentile 0.016 px, max 0.022,
    # against the estimates' own error of 0.049 px RMSE (with the smooth part along the lines: 0.011
    # and 0.041)
    assert np.percentile(est_delta, 99.9) <= 0.02 and est_delta.max() <= 0.05
    ex, ey = (ref.dx.values - truth.dx)[est], (ref.dy.values - truth.dy)[est]
    ratios = [np.sqrt(np.mean(e**2)) / np.sqrt(np.mean(s**2)) for e, s in ((ex, ref.sigma_x.values[est]),
                                                                            (ey, ref.sigma_y.values[est]))]
    print("estimated: RMSE / RMS(sigma) x, y", ratios)
    # never optimistic; pessimistic at most twofold (measured 0.60 in x: the line's spread beyond the
    # matches' own sigma, which is itself optimistic, RMSE / sigma 1.16-1.33 on matches)
    assert all(0.5 <= r <= 1.5 for r in ratios)
    # filled pixels (short gaps beside rejected matches) take their line's fit: measured 2.5 % of
    # the base at 0.029 px (the post-filter's interpolation of the raw matches beside them: 0.135)
    fil = st == Status.FILLED
    known = fil & np.isfinite(ref.sigma_x.values) & np.isfinite(ref.sigma_y.values)
    ex, ey = (ref.dx.values - truth.dx)[known], (ref.dy.values - truth.dy)[known]
    ratios = [np.sqrt(np.mean(e**2)) / np.sqrt(np.mean(s**2)) for e, s in ((ex, ref.sigma_x.values[known]),
                                                                            (ey, ref.sigma_y.values[known]))]
    print("filled", fil.mean(), np.sqrt(np.mean(err[fil] ** 2)), "with a sigma", known.sum() / fil.sum(), "RMSE / RMS(sigma)", ratios)
    assert fil.mean() > 0.01 and np.sqrt(np.mean(err[fil] ** 2)) <= 0.05
    assert known.sum() == fil.sum() and all(0.5 <= r <= 1.5 for r in ratios)


def test_dense_lattice_fill_against_truth(shared_data, tmp_path, client):
    """Opt-in lattice growth (every 4th column) plus the fill between: as accurate as full matching."""
    from geocoder.pipeline.dense import DenseOptions
    from geocoder.pipeline.register import RegisterOptions

    files = real_pair(shared_data, tmp_path, which="aerial", size=512, seed=21, turbulence=(1.0, 3.0))
    full_growth = RegisterOptions(matching=DenseOptions(col_step=1, halo=4))
    full = dense_figures(register(files.base, files.distorted, tile=256, client=client, options=full_growth), files.pair)
    options = RegisterOptions(matching=DenseOptions(col_step=4, densify="step"))
    ds = register(files.base, files.distorted, tile=256, client=client, options=options)
    f = dense_figures(ds, files.pair)
    print("full", full, "lattice+fill", f, json.loads(ds.attrs["summary"])["status_counts"])
    assert f["rmse"] <= 0.1
    assert f["rmse"] <= full["rmse"] + 0.005
    assert f["coverage"] >= 0.95
    assert f["coverage"] >= full["coverage"] - 0.002
    assert f["unflagged_over_1px"] == 0
    assert 0.67 <= f["calib_x"] <= 1.5 and 0.67 <= f["calib_y"] <= 1.5
    # the tiles' fill passes read their neighbours' lattice columns: the same with one tile
    one = register(files.base, files.distorted, tile=512, client=client, options=options)
    both = (one.status.values == Status.MATCHED) & (ds.status.values == Status.MATCHED)
    assert (one.status.values == ds.status.values).mean() >= 0.995
    delta = np.hypot(one.dx.values - ds.dx.values, one.dy.values - ds.dy.values)[both]
    print("tiles 512 vs 256:", delta.max(), np.percentile(delta, [99, 99.9]), (delta > 0.01).sum(), delta.size)
    assert np.percentile(delta, 99.9) <= 0.01


def test_dense_lattice_field_against_truth(shared_data, tmp_path, client):
    """Opt-in lattice growth (every 16th column), every pixel then matched at once from window
    sums (geocoder.match.densify): as accurate as ALSC, sigma calibrated, no unflagged error
    over 1 px, and the same field for any tiling."""
    from geocoder.pipeline.dense import DenseOptions
    from geocoder.pipeline.register import RegisterOptions

    files = real_pair(shared_data, tmp_path, which="aerial", size=512, seed=21, turbulence=(1.0, 3.0))
    options = RegisterOptions(matching=DenseOptions(col_step=16, halo=16, densify="field"))
    ds = register(files.base, files.distorted, tile=256, client=client, options=options)
    f = dense_figures(ds, files.pair)
    print("lattice 16 + field", f, json.loads(ds.attrs["summary"])["status_counts"])
    assert f["rmse"] <= 0.07
    assert f["coverage"] >= 0.95
    assert f["unflagged_over_1px"] == 0
    assert 0.67 <= f["calib_x"] <= 1.5 and 0.67 <= f["calib_y"] <= 1.5
    one = register(files.base, files.distorted, tile=512, client=client, options=options)
    both = (one.status.values == Status.MATCHED) & (ds.status.values == Status.MATCHED)
    delta = np.hypot(one.dx.values - ds.dx.values, one.dy.values - ds.dy.values)[both]
    print("tiles 512 vs 256:", delta.max(), (delta > 0.01).sum(), delta.size)
    assert (one.status.values == ds.status.values).mean() >= 0.999
    assert delta.max() <= 0.01


def test_where_the_polynomial_explains_the_field_the_line_fits_take_the_noise_off(shared_data, tmp_path, client):
    """Issue 14: a smooth field (affine + quadratic, no turbulence) is what the global polynomial
    models; the matches shrunk toward their lines' fits are less noisy than the matches
    alone, and their sigma tells how far off they are. Measured (512^2 S2, 53 % textured): 0.096 px
    without the fits, 0.0136 with them (calibration 0.96 / 0.77); before the every-pixel pass
    sampled with Lanczos-3, 0.1005 and 0.022 (1.10 / 0.92; before the lines' spreads had to
    pass a test, 0.025, 1.10 / 0.86); before the rows' departures were
    shrunk toward their trend 0.041 (0.88 / 1.00), before the lines' slopes were 0.062 (1.19 /
    1.32)). The polynomial itself: 0.0086, so the goal of being no noisier than the polynomial is
    not reached on this case (it is on issue 14's smooth 1024^2 S2 case, 0.003 px against 0.006)."""
    files = real_pair(shared_data, tmp_path, which="s2", size=512, seed=5)
    ds = register(files.base, files.distorted, tile=256, client=client)
    off = register(files.base, files.distorted, tile=256, client=client,
                   options=RegisterOptions(lines=LineOptions(fit_order=-1)))
    f, f_off = dense_figures(ds, files.pair), dense_figures(off, files.pair)
    print(f, f_off)
    # only values and sigmas change, but for the matches flagged as off their line: tested against
    # the line's fit in one run and against the line's shift in the other (measured: 14 matches of
    # 0.32-0.41 px error flagged with the fits, 19 others without; 33 pixels of 262,144)
    differ = ds.status.values != off.status.values
    assert differ.mean() < 1e-3
    assert set(np.unique(ds.status.values[differ])) | set(np.unique(off.status.values[differ])) <= {
        Status.MATCHED, Status.ESTIMATED}
    assert f["rmse"] <= 0.3 * f_off["rmse"]  # measured 0.24
    # one smooth scene's calibration is a draw: over fifteen (S2 512^2 seeds 1-8, 1024^2 1-3,
    # aerial 512^2 1-4) 0.43-1.58 per scene, 0.91 / 0.96 pooled; this one 0.96 / 0.77
    assert 0.67 <= f["calib_x"] <= 1.5 and 0.67 <= f["calib_y"] <= 1.5
    assert f["unflagged_over_1px"] == 0


def test_holes_cut_into_well_matched_lines_are_filled_by_length(shared_data, tmp_path, client):
    """Seed 003 sec. 10's check of hole filling (issue 14): stretches of 4-128 matches removed
    from the well-matched lines of a registered field (S2 512^2, turbulence 1-3 px), filled
    again by the post-filter (up to its 24 px) or estimated by the line step; their values
    against the truth and the removed matches, by hole length."""
    from geocoder.testing import hole_check

    files = real_pair(shared_data, tmp_path, which="s2", size=512, seed=22, turbulence=(1.0, 3.0))
    ds = register(files.base, files.distorted, tile=256, client=client,
                  options=RegisterOptions(lines=LineOptions(enabled=False)))
    rows = hole_check(ds, files.pair.dx, files.pair.dy, str(tmp_path / "holes"))
    for r in rows:
        print(r)
    by = {(r["length"], r["by"]): r for r in rows}
    for length in (4, 8, 16, 24, 32, 64, 128):
        way, other = ("filled", "estimated") if length <= 24 else ("estimated", "filled")
        r = by[length, way]
        # measured 15 lines (45 when the every-pixel pass sampled bilinearly: it accepted the matches
        # of 29 more lines at 0.09 px sigma whose y error was 0.12 px)
        assert r["pixels"] >= 12 * length and by[length, other]["pixels"] == 0
        # measured: filled 0.044-0.050 px, estimated 0.045-0.052 px; the removed raw matches
        # themselves are ~0.1 px off the values (their own noise, which the fills average away)
        assert r["rmse"] <= 0.07 and r["over_1px"] == 0
        # measured: filled 1.07-1.20 (x), 1.33-1.58 (y); estimated 0.92-1.05, 1.28-1.47. The 15 lines
        # are four runs of neighbouring lines, so a length's calibration is a draw: over the holes'
        # seeds 0-5, y 1.12-1.68 (and 1.08-1.70 with the lattice converged to 0.005 px, which drew
        # 1.24-1.45 here); x 0.76-1.34 (in the 40 lines of the bilinear sample: 0.81-0.91 / 0.84-0.90)
        cx, cy = r["calibration"]
        assert 0.7 <= cx <= 1.5 and 0.7 <= cy <= 1.75
    with pytest.raises(ValueError, match="without the line step"):  # a field with estimates has been through it
        hole_check(ds.assign(status=xr.full_like(ds.status, Status.ESTIMATED)), files.pair.dx, files.pair.dy,
                   str(tmp_path / "again"))
