"""Tests of the multispectral matchers (seed 003 sec. 11): geocoder.kernels.alsc_bands and
geocoder.kernels.fieldlsq_bands, against their one-band forms and against the truth of a
real crop warped by a known field, with one band made flat."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from conftest import read_band
from scipy.ndimage import gaussian_filter

from geocoder.kernels.alsc import NFIELDS, AlscOptions, alsc_point, samples
from geocoder.kernels.alsc_bands import alsc_point_bands, band_scales
from geocoder.kernels.fieldlsq import field_lsq
from geocoder.kernels.fieldlsq_bands import field_lsq_bands
from geocoder.simulate.warp import make_pair

AERIAL = "baviaanskloof/ngi_rgb_byte_1.tif"
SIZE = 320
REGION = (40, SIZE - 40, 90, SIZE - 90)
OPTS = AlscOptions(radius=25, radius_y=3, max_shift=0.5, max_sigma=0.1, tol=1e-3, max_iter=30)


@pytest.fixture(scope="module")
def case(shared_data):
    """The aerial RGB crop, band 1 flat (blurred, sigma 8 px) over the left half, warped with
    turbulence; every band scaled to unit noise; a start near the truth for every pixel."""
    margin = 32
    n = SIZE + 2 * margin
    src = np.stack([read_band(shared_data / AERIAL, b, (60, 60 + n, 107, 107 + n)) for b in (1, 2, 3)])
    src[0, :, : n // 2] = gaussian_filter(src[0], 8.0)[:, : n // 2]
    pair = make_pair(src, shape=(SIZE, SIZE), seed=21, margin=margin, turbulence=(1.0, 3.0))
    sb, sd = band_scales(pair.base), band_scales(pair.distorted)
    base = ((pair.base - sb[:, :1, None]) / sb[:, 1:, None]).astype(np.float32)
    dist = ((pair.distorted - sd[:, :1, None]) / sd[:, 1:, None]).astype(np.float32)
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    tx, ty = xs + pair.dx, ys + pair.dy
    rng = np.random.default_rng(0)
    x0 = tx + 0.05 * np.sin(xs / 40.0) + 0.02 * rng.standard_normal((SIZE, 1))
    y0 = ty + 0.04 * np.cos(ys / 9.0 + xs / 70.0) + 0.02 * rng.standard_normal((SIZE, 1))
    return base, dist, tx, ty, x0, y0


def test_band_scales_give_unit_noise():
    rng = np.random.default_rng(3)
    smooth = gaussian_filter(rng.normal(size=(400, 400)), 6) * 400
    stack = np.stack([smooth + rng.normal(0, 2.0, smooth.shape), 3 * smooth + 50 + rng.normal(0, 0.5, smooth.shape)])
    scales = band_scales(stack)
    # the noise of each band, not its contrast (band 2 has 3x the contrast of band 1 and a quarter of its noise)
    np.testing.assert_allclose(scales[:, 1], [2.0, 0.5], rtol=0.1)


@numba.njit
def _points_bands(base, table, cols, rows, init, out, codes, radius, radius_y, tol):
    for i in range(cols.shape[0]):
        codes[i] = alsc_point_bands(base, table, cols[i], rows[i], init[i], out[i], radius, radius_y, False, 30, tol,
                                    0.5, 0.7, 0.1, 0.5)


@numba.njit
def _points(base, table, cols, rows, init, out, codes, radius, radius_y, tol):
    for i in range(cols.shape[0]):
        codes[i] = alsc_point(base, table, cols[i], rows[i], init[i], out[i], radius, radius_y, False, 30, tol, 0.5,
                              0.7, 0.1, 0.5)


def _lattice(case, bands):
    """Lattice matches (every 16th column, every 4th row of the region) on ``bands``."""
    base, dist, tx, ty, x0, y0 = case
    rows, cols = (a.ravel() for a in np.mgrid[REGION[0]:REGION[1]:4, REGION[2]:REGION[3]:16])
    init = np.zeros((rows.size, 8))
    init[:, 0], init[:, 1] = x0[rows, cols], y0[rows, cols]
    init[:, 2] = init[:, 5] = init[:, 7] = 1.0
    b, d = np.ascontiguousarray(base[bands]), np.ascontiguousarray(dist[bands])
    out = np.empty((rows.size, NFIELDS))
    codes = np.empty(rows.size, np.int64)
    _points_bands(b, samples(d), cols, rows, init, out, codes, 25, 3, 1e-3)
    return rows, cols, init, out, codes


def test_one_band_is_alsc_point(case):
    rows, cols, init, out, codes = _lattice(case, [1])
    base, dist = case[0], case[1]
    ref = np.empty_like(out)
    ref_codes = np.empty_like(codes)
    _points(base[1], samples(dist[1]), cols, rows, init, ref, ref_codes, 25, 3, 1e-3)
    assert (codes == ref_codes).all()
    np.testing.assert_allclose(out[:, :11], ref[:, :11], rtol=1e-8, atol=1e-8, equal_nan=True)


def test_the_other_bands_carry_a_flat_band(case):
    """Left half: band 1 alone has no texture and fails; with bands 2 and 3 the template matches,
    as accurately as on the textured bands alone."""
    tx, ty = case[2], case[3]
    left = None
    results = {}
    for name, bands in (("flat", [0]), ("textured", [1, 2]), ("all", [0, 1, 2])):
        rows, cols, _, out, codes = _lattice(case, bands)
        left = cols < SIZE // 2 - 30
        ok = (codes == 0) & left
        err = np.hypot(out[:, 0] - tx[rows, cols], out[:, 1] - ty[rows, cols])[ok]
        results[name] = (ok.sum() / left.sum(), np.sqrt(np.mean(err**2)) if err.size else np.nan)
    print(results)
    assert results["flat"][0] < 0.1
    assert results["all"][0] > 0.9
    assert results["all"][0] >= results["textured"][0] - 0.02
    assert results["all"][1] < 0.1
    assert results["all"][1] <= 1.1 * results["textured"][1]


def test_field_one_band_is_field_lsq(case):
    base, dist, tx, ty, x0, y0 = case
    eligible = np.ones((SIZE, SIZE), bool)
    one = field_lsq_bands(base[1:2], dist[1:2], x0, y0, eligible, REGION, iterations=2)
    ref = field_lsq(base[1], dist[1], x0, y0, eligible, REGION, iterations=2)
    assert (one.code == ref.code).all()
    for name in ("x", "y", "sigma_x", "sigma_y", "rho"):
        np.testing.assert_allclose(getattr(one, name), getattr(ref, name), rtol=1e-7, atol=1e-9, equal_nan=True)


def test_field_on_all_bands_against_truth(case):
    """Every pixel: the left half (band 1 flat) matched on all bands as well as the right half,
    sigma calibrated; band 1 alone covers a quarter of it (measured 28 %, all bands 100 %)."""
    base, dist, tx, ty, x0, y0 = case
    eligible = np.ones((SIZE, SIZE), bool)
    sl = (slice(REGION[0], REGION[1]), slice(REGION[2], REGION[3]))
    left = (np.arange(REGION[2], REGION[3]) < SIZE // 2 - 30)[None, :]
    alone = field_lsq(base[0], dist[0], x0, y0, eligible, REGION, iterations=2)
    res = field_lsq_bands(base, dist, x0, y0, eligible, REGION, iterations=2)
    ok = res.code == 0
    ex, ey = res.x - tx[sl], res.y - ty[sl]
    cover = (ok & left).sum() / (np.ones_like(ok) & left).sum()
    print("left coverage: band 1", ((alone.code == 0) & left).mean() / left.mean(), "all bands", cover)
    alone_cover = ((alone.code == 0) & left).sum() / (np.ones_like(ok) & left).sum()
    assert cover > 0.8 and cover > alone_cover + 0.4
    assert np.sqrt(np.mean(ex[ok] ** 2 + ey[ok] ** 2)) < 0.08
    assert np.hypot(ex, ey)[ok].max() < 0.6
    for e, s in ((ex, res.sigma_x), (ey, res.sigma_y)):
        ratio = np.sqrt(np.mean(e[ok] ** 2)) / np.sqrt(np.mean(s[ok] ** 2))
        print("calibration", ratio)
        assert 0.67 <= ratio <= 1.5, ratio
