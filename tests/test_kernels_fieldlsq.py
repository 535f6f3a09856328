"""Tests of geocoder.kernels.fieldlsq (least squares of every pixel from window sums) and
geocoder.match.densify (starts from the lattice), against the truth of a known warp of a
real Sentinel-2 crop and against the per-template numpy reference."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import read_band

from geocoder.kernels import fieldlsq, window_sums
from geocoder.kernels.alsc import AlscOptions, alsc
from geocoder.kernels.fieldlsq import field_lsq, template_solution_reference
from geocoder.kernels.resample import LANCZOS_TABLE
from geocoder.match.densify import lattice_start, rows_between
from geocoder.simulate.warp import make_pair

S2 = "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif"
LANDSAT = "landsat7_rasterio/RGB.byte.tif"
SIZE = 320
REGION = (40, SIZE - 40, 90, SIZE - 90)
OPTS = AlscOptions(radius=25, radius_y=3, max_shift=0.5, max_sigma=0.1, tol=2e-4, max_iter=30)


def _warped(path, origin: tuple[int, int]):
    """A real crop warped by affine + quadratic + scan-line turbulence, and a start near the truth."""
    margin = 32
    r0, c0 = origin
    src = read_band(path, 1, (r0, r0 + SIZE + 2 * margin, c0, c0 + SIZE + 2 * margin))
    pair = make_pair(src, shape=(SIZE, SIZE), seed=21, margin=margin, turbulence=(1.0, 3.0))
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    tx, ty = xs + pair.dx, ys + pair.dy
    rng = np.random.default_rng(0)
    # smooth error along the lines plus an independent error per line (as between lattice matches)
    x0 = tx + 0.05 * np.sin(xs / 40.0) + 0.02 * rng.standard_normal((SIZE, 1))
    y0 = ty + 0.04 * np.cos(ys / 9.0 + xs / 70.0) + 0.02 * rng.standard_normal((SIZE, 1))
    return pair, tx, ty, x0, y0


@pytest.fixture(scope="module")
def case(shared_data):
    return _warped(shared_data / S2, (300, 1100))


def _errors(res, tx, ty, region=REGION):
    sl = (slice(region[0], region[1]), slice(region[2], region[3]))
    return res.x - tx[sl], res.y - ty[sl]


@pytest.mark.parametrize("gradients", ["template", "image"])
def test_every_pixel_against_truth_and_alsc(case, gradients):
    """As accurate as ALSC on the same pixels from the same starts, and sigma calibrated."""
    pair, tx, ty, x0, y0 = case
    base, dist = pair.base[0], pair.distorted[0]
    res = field_lsq(base, dist, x0, y0, np.ones((SIZE, SIZE), bool), REGION, gradients=gradients)
    ex, ey = _errors(res, tx, ty)
    ok = res.code == 0
    assert ok.mean() > 0.5
    rmse = np.sqrt(np.mean(ex[ok] ** 2 + ey[ok] ** 2))
    assert rmse < 0.1
    assert np.hypot(ex, ey)[ok].max() < 0.6
    for e, s in ((ex, res.sigma_x), (ey, res.sigma_y)):
        ratio = np.sqrt(np.mean(e[ok] ** 2)) / np.sqrt(np.mean(s[ok] ** 2))
        assert 0.67 <= ratio <= 1.5
    # ALSC from the same starts on a sample of pixels
    rng = np.random.default_rng(1)
    rows = rng.integers(REGION[0], REGION[1], 1500)
    cols = rng.integers(REGION[2], REGION[3], 1500)
    init = np.zeros((rows.size, 8))
    init[:, 0], init[:, 1] = x0[rows, cols], y0[rows, cols]
    init[:, 2] = init[:, 5] = init[:, 7] = 1.0
    ref = alsc(base, dist, cols, rows, init, options=OPTS)
    both = (ref.exit == 0) & ok[rows - REGION[0], cols - REGION[2]]
    assert both.mean() > 0.4
    e_alsc = np.hypot(ref.x - tx[rows, cols], ref.y - ty[rows, cols])[both]
    e_field = np.hypot(ex, ey)[rows - REGION[0], cols - REGION[2]][both]
    print(gradients, "field", np.sqrt(np.mean(e_field**2)), "alsc", np.sqrt(np.mean(e_alsc**2)))
    assert np.sqrt(np.mean(e_field**2)) <= 1.05 * np.sqrt(np.mean(e_alsc**2))


def test_sharp_texture_is_matched_as_precisely_as_its_noise_allows(shared_data):
    """A Landsat crop (300 m pixels: texture at the pixel scale): the template's pass samples
    the image with Lanczos-3, so the texture a bilinear sample smooths away is not left in the
    residuals (bilinear: RMSE y 0.051 px on this pair, 83 % accepted; Lanczos-3: 0.039 px, 87 %)."""
    pair, tx, ty, x0, y0 = _warped(shared_data / LANDSAT, (20, 60))
    res = field_lsq(pair.base[0], pair.distorted[0], x0, y0, np.ones((SIZE, SIZE), bool), REGION)
    ex, ey = _errors(res, tx, ty)
    ok = res.code == 0
    assert ok.mean() > 0.85
    assert np.sqrt(np.mean(ex[ok] ** 2)) < 0.036
    assert np.sqrt(np.mean(ey[ok] ** 2)) < 0.043
    for e, s in ((ex, res.sigma_x), (ey, res.sigma_y)):
        assert 0.67 <= np.sqrt(np.mean(e[ok] ** 2)) / np.sqrt(np.mean(s[ok] ** 2)) <= 1.5


def test_lanczos_samples_against_the_kernel_and_the_nodata_rules():
    """The table of weights (linear between 4,096 fractions) against Lanczos-3 itself; pixel
    values exactly at integer positions; NaN where a tap is outside the image or NaN."""
    rng = np.random.default_rng(5)
    img = rng.normal(100.0, 30.0, size=(40, 50))
    img[30, 40] = np.nan
    h, w = img.shape
    x = rng.uniform(-1.0, w, (60, 60))
    y = rng.uniform(-1.0, h, (60, 60))
    x[:5], y[:5] = np.round(x[:5]), np.round(y[:5])  # integer positions
    out = np.full(x.shape, -1.0)
    window_sums._sample_lanczos(img, x, y, np.array([0, 60, 0, 60]), LANCZOS_TABLE, out)
    ix, iy = np.floor(x).astype(int), np.floor(y).astype(int)
    inside = (x >= 2) & (x < w - 3) & (y >= 2) & (y < h - 3)
    assert np.isnan(out[~inside]).all()
    taps = np.arange(-2, 4)

    def weights(f):
        wt = np.sinc(f[:, None] - taps) * np.sinc((f[:, None] - taps) / 3.0)
        return wt / wt.sum(axis=1, keepdims=True)

    r, c = np.nonzero(inside)
    wx, wy = weights(x[r, c] - ix[r, c]), weights(y[r, c] - iy[r, c])
    patch = img[(iy[r, c, None, None] + taps[None, :, None]), (ix[r, c, None, None] + taps[None, None, :])]
    ref = np.einsum("pj,pi,pji->p", wy, wx, patch)
    np.testing.assert_array_equal(np.isnan(out[r, c]), np.isnan(ref))
    good = np.isfinite(ref)
    assert good.sum() > 1500 and (~good).sum() > 10  # the NaN pixel's taps are NaN
    # weights within 2.6e-8 of the kernel: a sample within 1e-6 of the taps' spread
    np.testing.assert_allclose(out[r, c][good], ref[good], atol=1e-6 * 30.0)
    at_pixel = inside[:5] & np.isfinite(out[:5])
    np.testing.assert_allclose(out[:5][at_pixel], img[iy[:5][at_pixel], ix[:5][at_pixel]], rtol=1e-12)


def test_kernel_solution_equals_design_matrix_reference(case):
    """The window sums (prefix sums along rows, running sums down, algebraic centring) give
    the least-squares solution of each template's own design matrix."""
    pair, tx, ty, x0, y0 = case
    base = pair.base[0].astype(np.float64)
    dist = pair.distorted[0].astype(np.float64)
    t = (base - base.mean()) / base.std()
    d = (dist - np.nanmean(dist)) / np.nanstd(dist)
    h, w = t.shape
    iw, gx, gy = (np.full((h, w), np.nan) for _ in range(3))
    whole = np.array([0, h, 0, w], dtype=np.int64)
    window_sums._warp(d, x0, y0, whole, iw, gx, gy)
    sol = np.full((8, h, w), np.nan)
    stats = np.full((5, h, w), np.nan)
    qx, qy = 3.7, -1.2  # any reference: the centring is exact
    region = np.array(REGION, dtype=np.int64)
    fieldlsq._solve_window(t, iw, gx, gy, gx, gy, x0, y0, qx, qy, np.ones((h, w), bool), region, 25, 3, 1.0,
                           True, False, sol, stats)
    for r, c in [(40, 90), (100, 150), (279, 229), (200, 100)]:
        ref = template_solution_reference(t, iw, gx, gy, x0, y0, r, c, 25, 3)
        np.testing.assert_allclose(sol[:, r, c], ref, rtol=1e-6, atol=1e-9)
    # the template's gradients: the design [g_T, u g_T, v g_T, I, 1] regressing T, no centring
    tgy, tgx = np.gradient(t)
    fieldlsq._solve_window(t, iw, tgx, tgy, iw, iw, x0, y0, 0.0, 0.0, np.ones((h, w), bool), region, 25, 3, 1.0,
                           True, True, sol, stats)
    v, u = (a.ravel().astype(float) for a in np.mgrid[-3:4, -25:26])
    for r, c in [(40, 90), (100, 150), (279, 229), (200, 100)]:
        sl = (slice(r - 3, r + 4), slice(c - 25, c + 26))
        gxs, gys, ts, ivs = (a[sl].ravel() for a in (tgx, tgy, t, iw))
        a = np.column_stack([gxs, gys, u * gxs, v * gxs, u * gys, v * gys, ivs, np.ones_like(ts)])
        theta = np.linalg.lstsq(a, ts, rcond=None)[0]
        np.testing.assert_allclose(sol[:, r, c], theta, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("gradients, reach", [("template", 2), ("image", 1)])
def test_result_depends_only_on_its_halo(case, gradients, reach):
    """After n rounds a pixel depends on starts within n template half-sizes only (2n with the
    template's gradients: the box mean, then the template): a window cut to that halo gives the
    same result (what makes the dense field independent of the tiling)."""
    pair, tx, ty, x0, y0 = case
    base, dist = pair.base[0], pair.distorted[0]
    n = 2
    core = (120, 180, 130, 190)
    res = field_lsq(base, dist, x0, y0, np.ones((SIZE, SIZE), bool), core, iterations=n, gradients=gradients)
    k = reach * n
    r0, r1, c0, c1 = core[0] - k * 3 - 1, core[1] + k * 3 + 1, core[2] - k * 25 - 1, core[3] + k * 25 + 1
    sub = (slice(r0, r1), slice(c0, c1))
    # the distorted window is the same array; only the base window and the starts are cut
    cut = field_lsq(base[sub], dist, x0[sub], y0[sub], np.ones((r1 - r0, c1 - c0), bool),
                    (core[0] - r0, core[1] - r0, core[2] - c0, core[3] - c0), iterations=n, gradients=gradients)
    assert (cut.code == res.code).all()
    ok = res.code == 0
    assert ok.mean() > 0.5
    # the grey-value normalisation differs between the windows: equal to round-off
    np.testing.assert_allclose(cut.x[ok], res.x[ok], atol=1e-6)
    np.testing.assert_allclose(cut.y[ok], res.y[ok], atol=1e-6)


@pytest.mark.parametrize("gradients", ["template", "image"])
def test_untrusted_pixels_are_not_matched_nor_used(case, gradients):
    pair, tx, ty, x0, y0 = case
    eligible = np.ones((SIZE, SIZE), bool)
    eligible[150:160, 150:250] = False
    bad_x = x0.copy()
    bad_x[150:160, 150:250] += 5.0  # wrong starts that must not enter any template
    res = field_lsq(pair.base[0], pair.distorted[0], bad_x, y0, eligible, REGION, gradients=gradients)
    ref = field_lsq(pair.base[0], pair.distorted[0], x0, y0, eligible, REGION, gradients=gradients)
    hole = (slice(150 - REGION[0], 160 - REGION[0]), slice(150 - REGION[2], 230 - REGION[2]))
    assert (res.code[hole] == -1).all()
    np.testing.assert_array_equal(res.code, ref.code)
    ok = res.code == 0
    np.testing.assert_allclose(res.x[ok], ref.x[ok], atol=1e-9)


def test_lattice_start_interpolates_along_lines():
    h, w = 3, 40
    xs = np.tile(np.arange(w, dtype=float), (h, 1))
    x = xs + 2.0 + 0.01 * xs  # the field along a line: 2 + 0.01 x
    y = np.full((h, w), 5.0)
    a11 = np.full((h, w), 1.01)
    a21 = np.zeros((h, w))
    matched = np.zeros((h, w), bool)
    matched[0, [0, 8, 24]] = True  # column 16 failed: 8 .. 24 bridged
    matched[1, [32]] = True  # one match: extended by its affine
    x0, y0, started = lattice_start(x, y, a11, a21, matched, max_gap=16, max_extend=4)
    assert started[0, :29].all() and not started[0, 29:].any()  # the run ends at 24, extended by 4
    np.testing.assert_allclose(x0[0, :29], x[0, :29])
    assert started[1, 28:37].all() and not started[1, :28].any() and not started[1, 37:].any()
    np.testing.assert_allclose(x0[1, 28:37], x[1, 28:37])
    assert not started[2].any()
    x0, _, started = lattice_start(x, y, a11, a21, matched, max_gap=8, max_extend=0)
    assert not started[0, 9:24].any()


def test_rows_between_the_lattice_rows_start_from_both_sides_or_the_one_there_is():
    h, w, step = 9, 5, 3
    first = 4  # global rows 4..12: lattice rows 6, 9, 12 at array rows 2, 5, 8
    rows = np.arange(first, first + h, dtype=float)[:, None]
    x = np.where(rows % step == 0, 10.0 + 0.5 * rows + np.zeros(w), np.nan)
    y = np.where(rows % step == 0, 2.0 * rows + np.zeros(w), np.nan)
    started = np.isfinite(x)
    started[5, 3] = False  # row 9 failed at column 3: rows 7, 8 take row 6's, rows 10, 11 row 12's
    x[5, 3] = np.nan
    x0, y0, st = rows_between(x, y, started, first, step, height=13)
    # array rows 0, 1 (global 4, 5): the lattice row above (3) is outside the arrays, not started
    assert not st[:2].any() and np.isnan(x0[:2]).all()
    # between two started lattice rows: linear across the lines
    np.testing.assert_allclose(x0[2:, :3], 10.0 + 0.5 * rows[2:] + np.zeros((7, 3)))
    np.testing.assert_allclose(y0[6:8, 4], 2.0 * rows[6:8, 0])
    np.testing.assert_allclose(x0[3:5, 3], x[2, 3])  # the displacement of the one there is
    np.testing.assert_allclose(x0[6:8, 3], x[8, 3])
    np.testing.assert_allclose(y0[3:5, 3], y[2, 3] + [1.0, 2.0])
    np.testing.assert_allclose(y0[6:8, 3], y[8, 3] - [2.0, 1.0])
    assert not st[5, 3] and np.isnan(x0[5, 3])  # a lattice row keeps its own verdict
    assert st[2:].sum() == 7 * w - 1
    # the scene's last rows past its last lattice row take that row's start
    x0, _, st = rows_between(x[:7], y[:7], started[:7], first, step, height=11)
    assert st[6, :3].all() and not st[6, 3] and np.allclose(x0[6, :3], x[5, :3])
    assert rows_between(x, y, started, first, 1, height=13)[0] is x  # every row on the lattice


def test_lattice_start_carries_a_long_run_along_its_chord_as_far_as_its_curvature_allows():
    from geocoder.match.densify import CHORD_SPAN, CHORD_TOL, MIN_EXTEND

    h, w = 2, 1400
    cols = np.arange(w, dtype=float)
    curv = 4e-6  # px / px^2: a quadratic along the line, as the global polynomial's error
    x = np.tile(cols + 0.01 * cols + 0.5 * curv * (cols - 200.0) ** 2, (h, 1))
    y = np.tile(np.full(w, 3.0), (h, 1))
    a11 = np.full((h, w), 1.01)  # a wrong local slope: the chord's is used where the run tells it
    a21 = np.zeros((h, w))
    matched = np.zeros((h, w), bool)
    matched[0, 0 : 200 + 1 : 16] = True  # a run of 13 matches, two spans of 64 px and more
    matched[1, [0, 16]] = True  # a short run: the affine, MIN_EXTEND px
    x0, _, started = lattice_start(x, y, a11, a21, matched, max_gap=64, max_extend=1000)
    reach = int(np.flatnonzero(started[0])[-1]) - 192
    d = CHORD_SPAN  # the chord from the end match to the match CHORD_SPAN inside
    want = 0.5 * (np.sqrt(d * d + 8 * CHORD_TOL / curv) - d)
    assert abs(reach - want) <= 0.1 * want and reach > 2 * MIN_EXTEND
    past = slice(193, 192 + reach + 1)
    assert np.abs(x0[0, past] - x[0, past]).max() <= CHORD_TOL * 1.05
    assert started[1].sum() == 17 + MIN_EXTEND
    np.testing.assert_allclose(x0[1, 17 : 17 + MIN_EXTEND], x[1, 16] + 1.01 * np.arange(1, MIN_EXTEND + 1))


def test_ldl_solve8_against_numpy():
    rng = np.random.default_rng(3)
    for _ in range(20):
        a = rng.normal(size=(30, 8)) * np.logspace(0, 3, 8)  # badly scaled columns, as the moments
        nmat = a.T @ a
        rhs = rng.normal(size=8)
        sol = np.full(8, np.nan)
        ok, d6, d7, l76 = window_sums._ldl_solve8(nmat, rhs, sol, True)
        assert ok
        np.testing.assert_allclose(sol, np.linalg.solve(nmat, rhs), rtol=1e-8)
        inv = np.linalg.inv(nmat)[6:, 6:]
        np.testing.assert_allclose([1 / d6 + l76**2 / d7, -l76 / d7, 1 / d7], [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-8)
        part = np.full(8, np.nan)
        window_sums._ldl_solve8(nmat, rhs, part, False)
        np.testing.assert_allclose(part[4:], sol[4:], rtol=1e-12)
    singular = np.ones((8, 8))
    assert not window_sums._ldl_solve8(singular, np.ones(8), np.empty(8), True)[0]
