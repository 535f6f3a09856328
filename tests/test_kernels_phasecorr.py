"""Tests of geocoder.kernels.phasecorr."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
from scipy import ndimage

from geocoder.kernels.phasecorr import Shift, Similarity, estimate_similarity, phase_correlation

SIZE = 256  # side of a and b
BIG = 768  # side of the texture they are cut from


@lru_cache(maxsize=4)
def _texture(size: int = BIG, seed: int = 0) -> np.ndarray:
    """Smoothed random noise plus random blocks (read-only)."""
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.normal(size=(size, size)), 2.0)
    tex /= tex.std()
    for _ in range(size // 16):
        r, c = rng.integers(0, size - 40, 2)
        h, w = rng.integers(8, 40, 2)
        tex[r : r + h, c : c + w] += rng.normal(0.0, 2.0)
    tex = ndimage.gaussian_filter(tex, 0.7)
    tex.flags.writeable = False
    return tex


def _crop(image: np.ndarray, size: int = SIZE) -> np.ndarray:
    o = (image.shape[0] - size) // 2
    return np.array(image[o : o + size, o : o + size])


def _similarity_pair(
    angle_deg: float, scale: float, shift: tuple[float, float], *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``a`` = centre crop of the texture, ``b`` = warped copy with p_b = A p_a + t.

    The rotation follows the documented convention (counter-clockwise as
    displayed); ``shift`` is where the centre of ``a`` lands in ``b``
    relative to the centre of ``b``.
    """
    tex = _texture(BIG, seed)
    th = math.radians(angle_deg)
    lin = scale * np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])
    centre = np.full(2, (SIZE - 1) / 2.0)
    t = centre + np.asarray(shift, dtype=float) - lin @ centre
    origin = (BIG - SIZE) // 2  # a(p) = tex(p + origin)
    a = _crop(tex)
    # b(q) = tex(inv(lin) @ (q - t) + origin); affine_transform works in (row, col).
    inv = np.linalg.inv(lin)
    offset = origin - inv @ t
    b = ndimage.affine_transform(
        tex, inv[::-1, ::-1], offset=offset[::-1], output_shape=(SIZE, SIZE), order=3
    )
    # Both images are fully inside the texture.
    corners = np.array([[0, 0], [SIZE - 1, 0], [0, SIZE - 1], [SIZE - 1, SIZE - 1]], float)
    src = (corners - t) @ inv.T + origin
    assert src.min() > 4 and src.max() < BIG - 5
    return a, b, np.column_stack([lin, t])


def _grid_error(result: Similarity, truth: np.ndarray) -> float:
    g = np.linspace(0.0, SIZE - 1.0, 9)
    pts = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    est = pts @ result.matrix[:, :2].T + result.matrix[:, 2]
    true = pts @ truth[:, :2].T + truth[:, 2]
    return float(np.hypot(*(est - true).T).max())


# --------------------------------------------------------------------------
# phase_correlation
# --------------------------------------------------------------------------


@pytest.mark.parametrize("dx, dy", [(3.3, -7.6), (-12.5, 20.25), (0.4, 0.7), (0.0, 0.0)])
def test_phase_correlation_subpixel_shift(dx: float, dy: float) -> None:
    tex = _texture()
    a = _crop(tex)
    b = _crop(ndimage.shift(tex, (dy, dx), order=3))  # b(x + dx, y + dy) = a(x, y)
    s = phase_correlation(a, b)
    assert isinstance(s, Shift)
    assert abs(s.dx - dx) < 0.15 and abs(s.dy - dy) < 0.15
    assert s.peak > 0.8
    # Integer-only result without the sub-pixel fit.
    si = phase_correlation(a, b, upsample=False)
    assert si.dx == round(si.dx) and si.dy == round(si.dy)
    assert abs(si.dx - dx) <= 0.5 + 1e-9 and abs(si.dy - dy) <= 0.5 + 1e-9


def test_phase_correlation_fourier_shift_and_swap() -> None:
    a = _crop(_texture(), 200)
    dx, dy = -5.7, 2.45
    fy = np.fft.fftfreq(a.shape[0])[:, None]
    fx = np.fft.fftfreq(a.shape[1])[None, :]
    b = np.fft.ifft2(np.fft.fft2(a) * np.exp(-2j * np.pi * (fx * dx + fy * dy))).real
    s = phase_correlation(a, b)
    assert abs(s.dx - dx) < 0.15 and abs(s.dy - dy) < 0.15
    back = phase_correlation(b, a)
    assert abs(back.dx + dx) < 0.15 and abs(back.dy + dy) < 0.15


def test_phase_correlation_nan_borders() -> None:
    tex = _texture()
    dx, dy = 3.3, -7.6
    a = _crop(tex)
    b = _crop(ndimage.shift(tex, (dy, dx), order=3))
    a[:, -30:] = np.nan
    a[-12:, :] = np.nan
    b[:20, :] = np.nan
    b[:, :25] = np.nan
    b[100:110, 140:150] = np.nan  # a hole
    s = phase_correlation(a, b)
    assert abs(s.dx - dx) < 0.15 and abs(s.dy - dy) < 0.15
    assert s.peak > 0.5


def test_phase_correlation_peak_separates_unrelated() -> None:
    tex = _texture()
    a = _crop(tex)
    same = phase_correlation(a, a)
    assert same.dx == pytest.approx(0.0, abs=1e-9) and same.dy == pytest.approx(0.0, abs=1e-9)
    assert same.peak == pytest.approx(1.0, abs=1e-6)
    rng = np.random.default_rng(21)
    noisy = _crop(ndimage.shift(tex, (4.0, -9.5), order=3)) + rng.normal(0.0, 0.5, a.shape)
    match = phase_correlation(a, noisy)
    other = phase_correlation(a, _crop(_texture(BIG, seed=1)))
    assert 0.0 <= other.peak < 0.1
    assert match.peak > 0.4
    assert match.peak > 5.0 * other.peak


def test_phase_correlation_degenerate_inputs() -> None:
    a = _crop(_texture(), 64)
    s = phase_correlation(np.full_like(a, np.nan), a)
    assert math.isnan(s.dx) and math.isnan(s.dy) and s.peak == 0.0
    s = phase_correlation(a, np.full_like(a, 3.0))
    assert math.isnan(s.dx) and s.peak == 0.0
    with pytest.raises(ValueError):
        phase_correlation(a, a[:-1])


# --------------------------------------------------------------------------
# estimate_similarity
# --------------------------------------------------------------------------


def _check_similarity(
    result: Similarity, angle_deg: float, scale: float, truth: np.ndarray
) -> None:
    assert isinstance(result, Similarity)
    assert result.matrix.shape == (2, 3) and result.matrix.dtype == np.float64
    err_deg = math.degrees(math.remainder(result.angle - math.radians(angle_deg), 2 * math.pi))
    assert abs(err_deg) < 0.5
    assert abs(result.scale / scale - 1.0) < 0.01
    assert _grid_error(result, truth) < 1.5
    # The matrix follows the documented angle/scale convention.
    c, s = math.cos(result.angle), math.sin(result.angle)
    np.testing.assert_allclose(
        result.matrix[:, :2], result.scale * np.array([[c, s], [-s, c]]), atol=1e-12
    )
    assert 0.3 < result.peak <= 1.0


@pytest.mark.parametrize(
    "angle_deg, scale, shift",
    [
        (30.0, 0.8, (10.0, -6.0)),
        (0.0, 1.0, (9.3, -12.6)),
        (-20.0, 1.15, (-8.0, 5.0)),
        (150.0, 0.9, (4.0, 7.0)),  # needs the 180-degree disambiguation
    ],
)
def test_estimate_similarity(angle_deg: float, scale: float, shift: tuple[float, float]) -> None:
    a, b, truth = _similarity_pair(angle_deg, scale, shift)
    _check_similarity(estimate_similarity(a, b), angle_deg, scale, truth)


def test_estimate_similarity_nan_corners_and_noise() -> None:
    a, b, truth = _similarity_pair(30.0, 0.8, (10.0, -6.0))
    rng = np.random.default_rng(5)
    a = a + rng.normal(0.0, 0.3, a.shape)
    b = 2.5 * b + 100.0 + rng.normal(0.0, 0.75, b.shape)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    b[xx + yy < 60] = np.nan  # nodata corner, as in a rotated scene footprint
    a[:, :15] = np.nan
    _check_similarity(estimate_similarity(a, b), 30.0, 0.8, truth)


def test_estimate_similarity_sign_matches_ndimage_rotate() -> None:
    tex = _texture()
    a = _crop(tex)
    b = _crop(ndimage.rotate(tex, 25.0, reshape=False, order=3))
    result = estimate_similarity(a, b)
    assert math.degrees(result.angle) == pytest.approx(25.0, abs=0.5)
    assert result.scale == pytest.approx(1.0, rel=0.01)
    # Rotation about the common centre: the centre maps to itself.
    centre = np.full(2, (SIZE - 1) / 2.0)
    np.testing.assert_allclose(result.matrix[:, :2] @ centre + result.matrix[:, 2], centre, atol=1.0)


def test_estimate_similarity_unrelated_and_degenerate() -> None:
    a = _crop(_texture())
    other = estimate_similarity(a, _crop(_texture(BIG, seed=1)))
    assert other.peak < 0.15
    bad = estimate_similarity(np.full((64, 64), np.nan), a[:64, :64])
    assert bad.peak == 0.0 and np.isnan(bad.matrix).all()
    with pytest.raises(ValueError):
        estimate_similarity(a, a, min_scale=2.0, max_scale=1.0)
