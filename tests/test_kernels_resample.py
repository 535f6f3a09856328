"""Tests of geocoder.kernels.resample."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from geocoder.kernels.resample import METHODS, sample, sample_affine_patches, sample_reference, window_for

HALF = {"nearest": 0, "bilinear": 1, "cubic": 2, "lanczos": 3}


def _image(shape: tuple[int, ...], *, seed: int, dtype: type = np.float32) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=shape).astype(dtype)


def _points(n: int, height: int, width: int, *, seed: int, margin: float = 2.0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-margin, width - 1 + margin, n)
    y = rng.uniform(-margin, height - 1 + margin, n)
    return x, y


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numba_matches_reference(method: str, dtype: type) -> None:
    image = _image((2, 23, 31), seed=1, dtype=dtype)
    image[0, 5, 7] = np.nan
    image[1, 15:17, 20] = np.nan
    x, y = _points(4000, 23, 31, seed=2)
    # Exact integers and half-integers exercise the zero-weight/rounding rules.
    x[:300] = np.round(x[:300])
    y[150:450] = np.round(y[150:450] * 2) / 2
    x[-1] = np.nan
    y[-2] = np.inf
    x, y = x.reshape(40, 100), y.reshape(40, 100)
    got = sample(image, x, y, method=method)
    ref = sample_reference(image, x, y, method=method)
    assert got.dtype == np.float32 and got.shape == (2, 40, 100)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)
    # Both valid and invalid samples are exercised.
    assert 0.1 < np.isnan(got).mean() < 0.9


def test_bilinear_matches_scipy_map_coordinates() -> None:
    image = _image((30, 40), seed=3, dtype=np.float64)
    x, y = _points(2000, 30, 40, seed=4, margin=0.0)
    got = sample(image, x, y, method="bilinear")
    expected = ndimage.map_coordinates(image, [y, x], order=1)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_integer_positions_reproduce_pixels(method: str) -> None:
    image = _image((3, 12, 17), seed=5)
    yy, xx = np.mgrid[0:12, 0:17].astype(np.float64)
    got = sample(image, xx, yy, method=method)
    # Exact, including the border rows/columns (zero-weight taps are not needed).
    np.testing.assert_array_equal(got, image)


@pytest.mark.parametrize("method", ["bilinear", "cubic", "lanczos"])
def test_linear_ramp(method: str) -> None:
    height, width = 20, 25
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    ramp = 0.7 * xx - 1.3 * yy + 5.0
    m = HALF[method]
    rng = np.random.default_rng(6)
    x = rng.uniform(m, width - 1 - m, 500)
    y = rng.uniform(m, height - 1 - m, 500)
    got = sample(ramp, x, y, method=method)
    expected = 0.7 * x - 1.3 * y + 5.0
    assert not np.isnan(got).any()
    if method == "lanczos":
        # Normalised Lanczos-3 does not reproduce linear functions exactly: its
        # first moment error is below 0.02 pixel, times the slope.
        np.testing.assert_allclose(got, expected, atol=0.02 * (0.7 + 1.3))
    else:
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("method", METHODS)
def test_nan_poisons_only_its_taps(method: str) -> None:
    height, width = 30, 30
    image = _image((height, width), seed=7, dtype=np.float64)
    r, c = 15, 12
    image[r, c] = np.nan
    x, y = _points(5000, height, width, seed=8, margin=0.0)
    got = sample(image, x, y, method=method)
    clean = image.copy()
    clean[r, c] = 0.0
    got_clean = sample(clean, x, y, method=method)
    # Points whose taps (with non-zero weight) include (r, c).
    if method == "nearest":
        touches = (np.floor(x + 0.5) == c) & (np.floor(y + 0.5) == r)
    else:
        h = HALF[method]
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        tx = (c >= x0 - (h - 1)) & (c <= x0 + h) & ((fx != 0) | (x0 == c))
        ty = (r >= y0 - (h - 1)) & (r <= y0 + h) & ((fy != 0) | (y0 == r))
        touches = tx & ty
    assert touches.any() and (~touches).any()
    # Points away from the image border are valid in the clean image.
    inner = (x >= HALF[method]) & (x <= width - 1 - HALF[method])
    inner &= (y >= HALF[method]) & (y <= height - 1 - HALF[method])
    np.testing.assert_array_equal(np.isnan(got[inner]), touches[inner])
    ok = ~touches
    np.testing.assert_array_equal(got[ok], got_clean[ok])


@pytest.mark.parametrize("method", METHODS)
def test_outside_points_are_nan(method: str) -> None:
    height, width = 10, 14
    image = _image((height, width), seed=9)
    x = np.array([-0.51, width - 0.49, 3.0, 3.0, -5.0, 1e30, np.nan, 2.0])
    y = np.array([3.0, 3.0, -0.51, height - 0.49, 2.0, 2.0, 2.0, -np.inf])
    got = sample(image, x, y, method=method)
    assert np.isnan(got).all()
    # Just inside: the last row/column and the first, at exact positions.
    xe = np.array([0.0, width - 1.0, 0.0, width - 1.0])
    ye = np.array([0.0, 0.0, height - 1.0, height - 1.0])
    np.testing.assert_array_equal(sample(image, xe, ye, method=method), image[ye.astype(int), xe.astype(int)])
    if method == "bilinear":
        # Sub-pixel along the last row/column.
        v = sample(image, np.array([width - 1.0, 2.5]), np.array([4.5, height - 1.0]), method=method)
        assert np.isfinite(v).all()
    if method == "nearest":
        v = sample(image, np.array([-0.5, width - 0.51]), np.array([height - 0.51, -0.5]), method=method)
        np.testing.assert_array_equal(v, [image[height - 1, 0], image[0, width - 1]])


@pytest.mark.parametrize("method", METHODS)
def test_multiband_equals_band_by_band(method: str) -> None:
    image = _image((4, 18, 22), seed=10)
    image[2, 4:6, 9] = np.nan
    x, y = _points(600, 18, 22, seed=11)
    x, y = x.reshape(20, 30), y.reshape(20, 30)
    got = sample(image, x, y, method=method)
    for b in range(image.shape[0]):
        np.testing.assert_array_equal(got[b], sample(image[b], x, y, method=method))


@pytest.mark.parametrize("method", METHODS)
def test_window_for_matches_full_image(method: str) -> None:
    height, width = 60, 70
    image = _image((2, height, width), seed=12)
    image[1, 30, 33] = np.nan
    rng = np.random.default_rng(13)
    # A small rotated patch of points, partly outside on the left/top.
    t = np.deg2rad(17.0)
    v, u = np.mgrid[0:15, 0:20].astype(np.float64)
    x = -3.3 + np.cos(t) * u * 1.7 - np.sin(t) * v + rng.normal(0, 0.1, u.shape)
    y = 8.6 + np.sin(t) * u * 1.7 + np.cos(t) * v
    x[0, 0] = np.nan
    for dx, dy in [(0.0, 0.0), (25.4, 20.0), (49.5, 41.0)]:
        xs, ys = x + dx, y + dy
        win = window_for(xs, ys, method=method, shape=(height, width))
        assert win is not None
        r0, r1, c0, c1 = win
        assert 0 <= r0 < r1 <= height and 0 <= c0 < c1 <= width
        full = sample(image, xs, ys, method=method)
        part = sample(image[:, r0:r1, c0:c1], xs - c0, ys - r0, method=method)
        np.testing.assert_array_equal(part, full)
        assert np.isfinite(full).any()
    # Interior points: the window is the tap footprint.
    win = window_for(np.array([10.2, 20.7]), np.array([5.5, 7.0]), method=method, shape=(height, width))
    h = HALF[method]
    if method == "nearest":
        assert win == (6, 8, 10, 22)
    else:
        assert win == (5 - (h - 1), 7 + h + 1, 10 - (h - 1), 20 + h + 1)


def test_window_for_none() -> None:
    shape = (20, 30)
    assert window_for(np.array([np.nan]), np.array([3.0]), method="bilinear", shape=shape) is None
    assert window_for(np.array([-10.0, 50.0]), np.array([-10.0, -5.0]), method="cubic", shape=shape) is None
    assert window_for(np.array([], dtype=float), np.array([], dtype=float), method="nearest", shape=shape) is None


def test_shapes_and_errors() -> None:
    image = _image((5, 6), seed=14)
    assert sample(image, np.array(2.5), np.array(1.5)).shape == ()
    assert sample(image[None], np.zeros(7), np.zeros(7)).shape == (1, 7)
    assert sample(image, np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)
    with pytest.raises(ValueError):
        sample(image, np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError):
        sample(image, np.zeros(3), np.zeros(3), method="spline")
    with pytest.raises(ValueError):
        sample(image[None, None], np.zeros(3), np.zeros(3))


def test_affine_patches_are_the_samples_of_their_positions() -> None:
    """The correlation's patches, sampled one patch at a time, equal :func:`sample` of the (n, P)
    positions bit for bit: inside, across nodata, past the edges, within the edge snap, NaN centres."""
    from geocoder.kernels.correlate import patch_offsets

    rng = np.random.default_rng(4)
    image = _image((97, 131), seed=2)
    image[40:44, 10:90] = np.nan
    n = 600
    x, y = _points(n, 97, 131, seed=5, margin=10.0)
    x[:20], y[20:30] = np.round(x[:20]), np.nan  # integral centres, undefined centres
    jac = np.eye(2)[None] + rng.normal(0.0, 0.05, (n, 2, 2))
    jac[:40] = np.round(jac[:40])
    offsets = patch_offsets(5)
    # centres whose patch's top row ends a hair (< 1e-3 px) above the first pixel centre
    y[30:40] = 5.0 * jac[30:40, 1, 1] + 5.0 * jac[30:40, 1, 0] - 4e-4
    px = x[:, None] + jac[:, 0, 0, None] * offsets[:, 0] + jac[:, 0, 1, None] * offsets[:, 1]
    py = y[:, None] + jac[:, 1, 0, None] * offsets[:, 0] + jac[:, 1, 1, None] * offsets[:, 1]
    want = sample(image, px, py, method="bilinear")
    got = sample_affine_patches(image, x, y, jac, offsets)
    assert got.dtype == np.float32 and got.shape == (n, len(offsets))
    assert np.array_equal(got, want, equal_nan=True)
    assert 0.05 < np.isnan(want).mean() < 0.5, "the case covers the undefined samples"
    with pytest.raises(ValueError, match="same patches"):
        sample_affine_patches(image, x, y[:-1], jac, offsets)
