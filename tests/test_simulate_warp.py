"""Tests of geocoder.simulate.warp and geocoder.simulate.texture."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
from scipy import ndimage

from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import (
    SyntheticPair,
    WarpField,
    invert,
    make_pair,
    seed_affine_experiment,
)


@pytest.fixture(scope="module")
def ortho() -> np.ndarray:
    """A 2-band synthetic scene large enough for a 256x256 base plus margins."""
    return synthetic_ortho((320, 320), seed=11, bands=2)


def _grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.indices(shape, dtype=np.float64)
    return xx, yy


def _smooth_function(xx: np.ndarray, yy: np.ndarray) -> np.ndarray:
    """Analytic, very smooth image (wavelengths >= 30 px, gradient <= ~16 / px)."""
    return (
        100.0
        + 40.0 * np.sin(2 * np.pi * xx / 41.0 + 0.3) * np.cos(2 * np.pi * yy / 53.0)
        + 30.0 * np.sin(2 * np.pi * (xx + 2 * yy) / 67.0)
        + 20.0 * np.cos(2 * np.pi * (3 * xx - yy) / 97.0)
    )


def _smooth_source(shape: tuple[int, int]) -> np.ndarray:
    yy, xx = np.indices(shape, dtype=np.float64)
    return _smooth_function(xx, yy)


# --------------------------------------------------------------- WarpField
def test_displacement_matches_formula() -> None:
    field = WarpField(
        affine=np.array([[0.01, -0.02, 1.5], [0.03, 0.005, -2.0]]),
        quadratic=np.array([[1e-4, -2e-4, 3e-4], [-1e-4, 5e-5, 2e-4]]),
        centre=(10.0, 20.0),
        turbulence_x=np.array([0.0, 1.0, 3.0]),
        turbulence_y=np.array([2.0, 0.0, -1.0]),
    )
    x = np.array([0.0, 10.0, 33.5, 7.0, 4.0])
    y = np.array([0.0, 0.5, 1.25, -3.0, 9.0])
    u, v = x - 10.0, y - 20.0
    tx = np.interp(y, [0, 1, 2], [0.0, 1.0, 3.0])
    ty = np.interp(y, [0, 1, 2], [2.0, 0.0, -1.0])
    ex = 0.01 * u - 0.02 * v + 1.5 + 1e-4 * u**2 - 2e-4 * u * v + 3e-4 * v**2 + tx
    ey = 0.03 * u + 0.005 * v - 2.0 - 1e-4 * u**2 + 5e-5 * u * v + 2e-4 * v**2 + ty
    dx, dy = field.displacement(x, y)
    np.testing.assert_allclose(dx, ex, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dy, ey, rtol=0, atol=1e-12)
    # clamped turbulence at both ends, broadcasting, float64
    assert field.turbulence_part(np.array([-5.0, 50.0]))[0].tolist() == [0.0, 3.0]
    bx, by = field.displacement(np.arange(4.0)[None, :], np.arange(3.0)[:, None])
    assert bx.shape == by.shape == (3, 4) and bx.dtype == np.float64
    # arrays are read-only copies
    with pytest.raises(ValueError):
        field.affine[0, 0] = 1.0


@pytest.mark.parametrize("shape", [(256, 320), (700, 500)])
@pytest.mark.parametrize("turbulence", [None, (1.0, 3.0)])
def test_random_field_budget_and_parts(shape: tuple[int, int], turbulence) -> None:
    field = WarpField.random(shape, seed=7, max_displacement=15.0, turbulence=turbulence)
    assert field.centre == ((shape[1] - 1) / 2, (shape[0] - 1) / 2)
    xx, yy = _grid(shape)
    dx, dy = field.displacement(xx, yy)
    total = np.hypot(dx, dy).max()
    assert total <= 15.0 + 1e-9
    assert total >= 8.0  # the budget is actually used
    # both the affine and the quadratic parts contribute several pixels
    ax, ay = field.affine_part(xx, yy)
    qx, qy = field.quadratic_part(xx, yy)
    assert np.hypot(ax, ay).max() >= 3.0
    assert np.hypot(qx, qy).max() >= 2.0
    # linear (rotation/scale/shear) part and shift are both present
    lin_x, lin_y = ax - field.affine[0, 2], ay - field.affine[1, 2]
    assert np.hypot(lin_x, lin_y).max() >= 1.0
    assert np.hypot(*field.affine[:, 2]) >= 1.0
    # invertible
    assert field.jacobian_bound(shape) < 0.5


def test_random_field_turbulence() -> None:
    shape = (600, 400)
    field = WarpField.random(shape, seed=3, turbulence=(1.0, 3.0), turbulence_scale=30.0)
    for t in (field.turbulence_x, field.turbulence_y):
        assert t.shape == (shape[0],)
        assert 1.0 - 1e-12 <= np.abs(t).max() <= 3.0 + 1e-12
        assert np.abs(np.diff(t)).max() < 0.2  # well below 1 px/line
        # it varies over tens of lines: many sign changes, but not line to line
        crossings = np.count_nonzero(np.diff(np.sign(t)) != 0)
        assert 3 <= crossings <= shape[0] / 10
    assert not np.allclose(field.turbulence_x, field.turbulence_y)
    none = WarpField.random(shape, seed=3)
    assert np.all(none.turbulence_x == 0) and np.all(none.turbulence_y == 0)
    with pytest.raises(ValueError):
        WarpField.random(shape, seed=3, max_displacement=2.0, turbulence=(3.0, 3.0))


def test_random_field_reproducible() -> None:
    a = WarpField.random((300, 200), seed=5, turbulence=(1, 3))
    b = WarpField.random((300, 200), seed=5, turbulence=(1, 3))
    c = WarpField.random((300, 200), seed=6, turbulence=(1, 3))
    for name in ("affine", "quadratic", "turbulence_x", "turbulence_y"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert not np.allclose(getattr(a, name), getattr(c, name))
    assert a.centre == b.centre


def test_random_field_affine_max() -> None:
    field = WarpField.random((256, 256), seed=1, affine_max=0.01)
    assert np.abs(field.affine[:, :2]).max() <= 0.01 + 1e-15
    xx, yy = _grid((256, 256))
    assert np.hypot(*field.displacement(xx, yy)).max() <= 15.0


def _assert_partials(field: WarpField, x: np.ndarray, y: np.ndarray, h: float = 1e-4) -> None:
    """The analytic partials agree with central differences (away from the turbulence's row kinks)."""
    gxx, gxy, gyx, gyy = field.partials(x, y)
    np.testing.assert_allclose(gxx, (field.displacement(x + h, y)[0] - field.displacement(x - h, y)[0]) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(gxy, (field.displacement(x, y + h)[0] - field.displacement(x, y - h)[0]) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(gyx, (field.displacement(x + h, y)[1] - field.displacement(x - h, y)[1]) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(gyy, (field.displacement(x, y + h)[1] - field.displacement(x, y - h)[1]) / (2 * h), atol=1e-7)


def test_jacobian_bound_is_a_bound() -> None:
    shape = (200, 150)
    field = WarpField.random(shape, seed=9, turbulence=(1, 3), max_displacement=12.0)
    xx, yy = _grid(shape)
    # finite differences between pixel centres (exact slopes of the turbulence)
    dx, dy = field.displacement(xx, yy)
    fd = max(
        np.abs(np.diff(dx, axis=1)).max(),
        np.abs(np.diff(dx, axis=0)).max(),
        np.abs(np.diff(dy, axis=1)).max(),
        np.abs(np.diff(dy, axis=0)).max(),
    )
    bound = field.jacobian_bound(shape)
    assert fd <= bound + 1e-6
    _assert_partials(field, xx[::7, ::7] + 0.3, yy[::7, ::7] + 0.4)


def test_relief_is_finer_than_a_line_and_leaves_the_rest_of_the_draw_alone() -> None:
    """A relief-like term (plane waves of tens of pixels, mostly across the lines) is drawn
    only when asked for: without it a seed gives the same field as before it existed; with
    it the displacement stays within its budget, the partials are its exact derivatives, the
    Jacobian bound holds, and the field inverts."""
    shape = (300, 260)
    plain = WarpField.random(shape, seed=9, turbulence=(1, 3), max_displacement=12.0)
    again = WarpField.random(shape, seed=9, turbulence=(1, 3), max_displacement=12.0, relief=None)
    for name in ("affine", "quadratic", "turbulence_x", "turbulence_y"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(again, name))
    assert plain.relief.shape == (0, 5)
    field = WarpField.random(shape, seed=9, turbulence=(1, 3), max_displacement=12.0, relief=(0.6, 40.0))
    assert field.relief.shape == (6, 5)
    np.testing.assert_array_equal(field.turbulence_x, plain.turbulence_x)
    xx, yy = _grid(shape)
    rx, ry = field.relief_part(xx, yy)
    assert 0.1 < np.abs(rx).max() <= 0.6 and np.abs(ry).max() < np.abs(rx).max()
    # it varies along a line over tens of pixels: a quadratic along each line leaves most of it
    resid = rx - np.stack([np.polyval(np.polyfit(xx[r], rx[r], 2), xx[r]) for r in range(shape[0])])
    assert resid.std() > 0.7 * rx.std()
    assert field.max_displacement(shape) <= 12.0 + 1e-9
    dx, dy = field.displacement(xx, yy)
    fd = max(np.abs(np.diff(d, axis=a)).max() for d in (dx, dy) for a in (0, 1))
    assert fd <= field.jacobian_bound(shape) + 1e-6
    _assert_partials(field, xx[::7, ::7] + 0.3, yy[::7, ::7] + 0.4)
    px, py = invert(field, xx + dx, yy + dy)
    assert np.abs(px - xx).max() < 1e-8 and np.abs(py - yy).max() < 1e-8
    with pytest.raises(ValueError, match="relief"):
        WarpField.random(shape, seed=9, relief=(-1.0, 40.0))


# --------------------------------------------------------------- invert
@pytest.mark.parametrize("turbulence", [None, (1.0, 3.0)])
def test_invert_roundtrip(turbulence) -> None:
    shape = (400, 300)
    field = WarpField.random(shape, seed=21, turbulence=turbulence)
    xx, yy = _grid(shape)
    rng = np.random.default_rng(0)
    x = xx + rng.uniform(-0.5, 0.5, shape)
    y = yy + rng.uniform(-0.5, 0.5, shape)
    dx, dy = field.displacement(x, y)
    px, py = invert(field, x + dx, y + dy)
    assert np.abs(px - x).max() < 1e-8
    assert np.abs(py - y).max() < 1e-8


def test_invert_nan_and_failure() -> None:
    field = WarpField.random((64, 64), seed=2)
    px, py = invert(field, np.array([np.nan, 10.0]), np.array([3.0, 5.0]))
    assert np.isnan(px[0]) and np.isnan(py[0]) and np.isfinite(px[1])
    # x + 0.01 (x - 0)^2 = q has no solution for q < -25: must raise
    folded = WarpField(
        affine=np.zeros((2, 3)),
        quadratic=np.array([[0.01, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        centre=(0.0, 0.0),
        turbulence_x=np.zeros(0),
        turbulence_y=np.zeros(0),
    )
    with pytest.raises(ValueError, match="converge"):
        invert(folded, np.array([-40.0]), np.array([0.0]))


# --------------------------------------------------------------- make_pair
def _resample_at_truth(
    pair: SyntheticPair, band: int = 0, edge: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Sample pair.distorted (cubic spline) at p + d(p) for every base pixel p.

    Returns the samples and the mask of base pixels whose p + d(p) lies at
    least ``edge`` pixels inside the distorted image.
    """
    h, w = pair.dx.shape
    xx, yy = _grid((h, w))
    qx, qy = xx + pair.dx, yy + pair.dy
    hd, wd = pair.distorted.shape[1:]
    img = pair.distorted[band].astype(np.float64)
    assert np.all(np.isfinite(img))
    sampled = ndimage.map_coordinates(img, [qy, qx], order=3, mode="nearest")
    interior = (qx >= edge) & (qx <= wd - 1 - edge) & (qy >= edge) & (qy <= hd - 1 - edge)
    return sampled, interior


def test_make_pair_truth_consistency_texture(ortho: np.ndarray) -> None:
    pair = make_pair(
        ortho, shape=(256, 256), seed=4, noise=0.0, gain=(1.0, 1.0), offset=0.0, turbulence=(1.0, 3.0)
    )
    assert pair.base.shape == pair.distorted.shape == (2, 256, 256)
    assert pair.base.dtype == pair.distorted.dtype == np.float32
    assert pair.dx.shape == pair.dy.shape == (256, 256) and pair.dx.dtype == np.float64
    np.testing.assert_array_equal(pair.base, ortho[:, 32:288, 32:288].astype(np.float32))
    # truth on the base grid is the field
    xx, yy = _grid((256, 256))
    np.testing.assert_array_equal(pair.dx, pair.field.displacement(xx, yy)[0])
    for band in range(2):
        sampled, interior = _resample_at_truth(pair, band)
        assert interior.mean() > 0.8
        err = (sampled - pair.base[band])[interior]
        # Interpolation-limited: the scene has texture down to ~2 px and is
        # resampled twice with cubic splines (render + check). On 0-255 grey
        # levels: RMS < 0.8 (base std ~40), 99th percentile < 3.5.
        assert np.sqrt(np.mean(err**2)) < 0.8
        assert np.percentile(np.abs(err), 99) < 3.5
    # a wrong sign of the truth would be far off
    bad = ndimage.map_coordinates(
        pair.distorted[0].astype(np.float64), [yy - pair.dy, xx - pair.dx], order=3, mode="nearest"
    )
    assert np.sqrt(np.mean((bad - pair.base[0]) ** 2)) > 10.0


def test_make_pair_truth_consistency_smooth() -> None:
    """With a very smooth source the truth is verified to ~1e-3 grey levels."""
    src = _smooth_source((260, 300))
    pair = make_pair(
        src,
        shape=(196, 236),
        seed=12,
        noise=0.0,
        gain=(1.0, 1.0),
        offset=0.0,
        turbulence=(1.0, 2.0),
        max_displacement=12.0,
    )
    assert pair.base.shape == (1, 196, 236)
    # the rendering itself is exact (float32-limited): distorted(q) == source(p + margin)
    # where p + d(p) = q
    qy, qx = np.indices((196, 236), dtype=np.float64)
    px, py = invert(pair.field, qx, qy)
    np.testing.assert_allclose(pair.distorted[0], _smooth_function(px + 32, py + 32), rtol=0, atol=2e-3)
    # and resampling the distorted image at p + d(p) gives the base back; the
    # error (< 0.1 grey level, i.e. < ~0.01 px) is the test's own cubic
    # resampling error (the IIR prefilter edge effect is kept out by edge=8)
    sampled, interior = _resample_at_truth(pair, edge=8)
    assert interior.mean() > 0.7
    err = (sampled - pair.base[0])[interior]
    assert np.abs(err).max() < 0.1
    assert np.sqrt(np.mean(err**2)) < 0.02
    # equivalently: the source at p + margin is what the distorted image shows
    np.testing.assert_allclose(pair.base[0], src[32:228, 32:268], rtol=0, atol=1e-4)


def test_make_pair_renders_a_given_field() -> None:
    """``warp=`` renders that field (the truth is its displacement) instead of a random draw."""
    src = _smooth_source((260, 300))
    warp = WarpField(affine=[[0.01, 0.0, 0.4], [0.0, -0.02, -0.3]], quadratic=[[2e-4, 0, 0], [0, 0, 1e-4]],
                     centre=(117.5, 97.5), turbulence_x=[], turbulence_y=[])
    pair = make_pair(src, shape=(196, 236), seed=12, noise=0.0, gain=(1.0, 1.0), offset=0.0, warp=warp)
    assert pair.field is warp
    rows, cols = np.indices((196, 236), dtype=np.float64)
    dx, dy = warp.displacement(cols, rows)
    np.testing.assert_array_equal(pair.dx, dx)
    np.testing.assert_array_equal(pair.dy, dy)
    px, py = invert(warp, cols, rows)  # the base position of every distorted pixel
    np.testing.assert_allclose(pair.distorted[0], _smooth_function(px + 32, py + 32), rtol=0, atol=2e-3)


def test_make_pair_nodata_and_shape(ortho: np.ndarray) -> None:
    src = ortho[0].astype(np.float64).copy()
    src[150:170, 140:160] = np.nan  # a hole inside the base area
    pair = make_pair(src, shape=(200, 200), seed=8, distorted_shape=(220, 180), noise=0.0)
    assert pair.distorted.shape == (1, 220, 180)
    assert np.isnan(pair.base[0, 118:138, 108:128]).all()
    # the hole appears (dilated by the spline support) in the distorted image
    xx, yy = _grid((200, 200))
    hole = ~np.isfinite(pair.base[0])
    qx = np.round(xx[hole] + pair.dx[hole]).astype(int)
    qy = np.round(yy[hole] + pair.dy[hole]).astype(int)
    ok = (qx >= 0) & (qx < 180) & (qy >= 0) & (qy < 220)
    assert ok.sum() > 100
    assert np.isnan(pair.distorted[0, qy[ok], qx[ok]]).all()
    nan_frac = np.isnan(pair.distorted).mean()
    assert 0.005 < nan_frac < 0.05  # the hole (+support), nothing else is lost


def test_make_pair_radiometry_and_seed(ortho: np.ndarray) -> None:
    kw = dict(shape=(256, 256), seed=31, noise=0.02, gain=(0.75, 1.25), offset=0.05)
    a = make_pair(ortho, **kw)
    b = make_pair(ortho, **kw)
    np.testing.assert_array_equal(a.distorted, b.distorted)
    np.testing.assert_array_equal(a.base, b.base)
    c = make_pair(ortho, **{**kw, "seed": 32})
    assert not np.allclose(a.dx, c.dx)
    clean = make_pair(ortho, **{**kw, "noise": 0.0, "gain": (1.0, 1.0), "offset": 0.0})
    np.testing.assert_array_equal(a.dx, clean.dx)  # same field
    base = clean.base[0].astype(np.float64)
    drange = np.subtract(*np.percentile(base, [99, 1]))
    # distorted = g * clean + off + noise  -> regression recovers g and off
    x = clean.distorted[0].ravel().astype(np.float64)
    y = a.distorted[0].ravel().astype(np.float64)
    g, off = np.polyfit(x, y, 1)
    assert 0.75 <= g <= 1.25
    assert abs(abs(off) - 0.05 * drange) < 0.01 * drange
    resid = y - (g * x + off)
    assert abs(resid.std() / drange - 0.02) < 0.002
    base_noise = (a.base[0] - clean.base[0]).astype(np.float64)
    assert abs(base_noise.std() / drange - 0.02) < 0.002
    assert abs(np.corrcoef(base_noise.ravel(), resid)[0, 1]) < 0.05  # independent


# --------------------------------------------------------------- seed paper
def test_seed_affine_experiment(ortho: np.ndarray) -> None:
    src01 = ortho[0] / 255.0  # not on the 0-255 scale: must be rescaled
    pair = seed_affine_experiment(src01, size=96, seed=5, bbar_max=0.15, noise_sigma=15.0)
    f = pair.field
    assert pair.base.shape == pair.distorted.shape == (1, 96, 96)
    bbar = f.affine[:, :2]
    assert np.abs(bbar).max() <= 0.15 and np.abs(bbar).max() > 0.01
    assert np.all(f.quadratic == 0)
    assert np.all(f.turbulence_x == 0) and np.all(f.turbulence_y == 0)
    assert f.centre == (47.5, 47.5)
    # displacement is exactly linear: d = bbar @ (p - c) + a
    xx, yy = _grid((96, 96))
    ex = bbar[0, 0] * (xx - 47.5) + bbar[0, 1] * (yy - 47.5) + f.affine[0, 2]
    ey = bbar[1, 0] * (xx - 47.5) + bbar[1, 1] * (yy - 47.5) + f.affine[1, 2]
    np.testing.assert_allclose(pair.dx, ex, atol=1e-12)
    np.testing.assert_allclose(pair.dy, ey, atol=1e-12)
    assert np.all(np.isfinite(pair.distorted))
    assert -60 < pair.base.min() and pair.base.max() < 320  # 0-255 scale plus noise

    # noise-free: the distorted window at p + d(p) shows the base window
    clean = seed_affine_experiment(src01, size=96, seed=5, bbar_max=0.15, noise_sigma=0.0)
    np.testing.assert_array_equal(clean.dx, pair.dx)
    qx, qy = xx + clean.dx, yy + clean.dy
    inside = (qx >= 2) & (qx <= 93) & (qy >= 2) & (qy <= 93)
    s = ndimage.map_coordinates(clean.distorted[0].astype(np.float64), [qy, qx], order=3)
    r = np.corrcoef(s[inside], clean.base[0][inside])[0, 1]
    assert r > 0.97  # smoothing acts in each window's own frame, so not exact


def test_seed_affine_experiment_random_bbar(ortho: np.ndarray) -> None:
    entries = np.concatenate(
        [seed_affine_experiment(ortho[0], size=64, seed=s, bbar_max=0.1).field.affine[:, :2].ravel() for s in range(8)]
    )
    assert np.abs(entries).max() <= 0.1
    assert (entries > 0).any() and (entries < 0).any()


# --------------------------------------------------------------- texture
def test_synthetic_ortho_deterministic_and_range() -> None:
    a = synthetic_ortho((256, 192), seed=1, bands=3)
    b = synthetic_ortho((256, 192), seed=1, bands=3)
    c = synthetic_ortho((256, 192), seed=2, bands=3)
    assert a.shape == (3, 256, 192) and a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).mean() > 10.0
    assert a.min() >= 0.0 and a.max() <= 255.0
    assert not np.allclose(a[0], a[1])  # bands differ


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_ortho_texture_everywhere(seed: int) -> None:
    img = synthetic_ortho((384, 384), seed=seed)[0].astype(np.float64)
    gy, gx = np.gradient(img)
    gmag = np.hypot(gx, gy)
    block_std = gmag.reshape(12, 32, 12, 32).std(axis=(1, 3))
    assert block_std.min() > 1.5  # grey levels / px, every 32x32 block
    # every 15x15 window has gradients in two directions (no aperture problem):
    # smallest eigenvalue of the mean structure tensor
    sxx = ndimage.uniform_filter(gx * gx, 15)[7:-7, 7:-7]
    syy = ndimage.uniform_filter(gy * gy, 15)[7:-7, 7:-7]
    sxy = ndimage.uniform_filter(gx * gy, 15)[7:-7, 7:-7]
    half_tr = (sxx + syy) / 2
    lmin = half_tr - np.sqrt(np.maximum(half_tr**2 - (sxx * syy - sxy**2), 0))
    assert lmin.min() > 2.0


def test_synthetic_ortho_not_periodic_and_matchable() -> None:
    img = synthetic_ortho((256, 256), seed=4)[0].astype(np.float64)
    # high-passed autocorrelation has no secondary peak (no repeated pattern)
    z = img - ndimage.gaussian_filter(img, 4.0)
    z -= z.mean()
    spec = np.fft.rfft2(z, s=(512, 512))
    ac = np.fft.irfft2(np.abs(spec) ** 2, s=(512, 512))
    ac /= ac[0, 0]
    yy, xx = np.indices(ac.shape)
    lag = np.hypot(np.minimum(yy, 512 - yy), np.minimum(xx, 512 - xx))
    assert ac[(lag > 8) & (lag < 128)].max() < 0.5
    # a 15x15 patch is found at its own place within a +-16 px search
    win = sliding_window_view(img, (15, 15))
    wstd = win.std(axis=(2, 3))
    rng = np.random.default_rng(0)
    r_ = 16
    for r, c in rng.integers(r_, 242 - r_, size=(25, 2)):
        p = img[r : r + 15, c : c + 15]
        p = (p - p.mean()) / p.std()
        sub = win[r - r_ : r + r_ + 1, c - r_ : c + r_ + 1]
        ncc = np.einsum("ijkl,kl->ij", sub, p) / 225.0 / wstd[r - r_ : r + r_ + 1, c - r_ : c + r_ + 1]
        assert np.unravel_index(np.argmax(ncc), ncc.shape) == (r_, r_)
