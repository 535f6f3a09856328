"""Automatic coarse alignment: no overlap estimate from the user."""

import json

import numpy as np
import pytest
import scipy.ndimage as ndi
from conftest import read_band

from geocoder import MatchingError, register
from geocoder.kernels.polynomial import PolyMap
from geocoder.match.coarse import align_overviews
from geocoder.scene import write_geotiff


def _similarity(angle_deg, scale, centre, shift):
    """Base pixel -> distorted pixel: rotate/scale about ``centre`` then shift."""
    a = np.deg2rad(angle_deg)
    lin = scale * np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    off = np.asarray(centre) + np.asarray(shift) - lin @ np.asarray(centre)
    return np.column_stack([lin, off])


def _render(src, m, shape, origin):
    """Distorted image on ``shape``: the source seen through the inverse of ``m``."""
    inv = np.linalg.inv(np.vstack([m, [0, 0, 1]]))
    qy, qx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    px = inv[0, 0] * qx + inv[0, 1] * qy + inv[0, 2]
    py = inv[1, 0] * qx + inv[1, 1] * qy + inv[1, 2]
    return ndi.map_coordinates(src, [py + origin[0], px + origin[1]], order=3, cval=np.nan)


@pytest.mark.data
@pytest.mark.cluster
def test_register_finds_30_degrees_and_scale_08(shared_data, tmp_path, client):
    src = read_band(shared_data / "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", 1, (200, 1400, 1000, 2200))
    size, origin = 512, (300, 300)
    base = src[origin[0] : origin[0] + size, origin[1] : origin[1] + size]
    m = _similarity(30.0, 0.8, (255.5, 255.5), (40.0, -25.0))
    dist = _render(src, m, (560, 600), origin)
    dist += np.random.default_rng(0).normal(0, 0.01 * np.nanstd(dist), dist.shape)
    write_geotiff(tmp_path / "b.tif", base.astype(np.float32))
    write_geotiff(tmp_path / "d.tif", dist.astype(np.float32))
    ds = register(tmp_path / "b.tif", tmp_path / "d.tif", tile=256, order=1, client=client, dense=False)
    summary = json.loads(ds.attrs["summary"])
    assert summary["coarse_method"].startswith("fourier-mellin")
    found = PolyMap.from_dict(json.loads(ds.attrs["mapping"]))
    gy, gx = np.mgrid[0:size:32, 0:size:32].astype(float)
    fx, fy = found(gx, gy)
    tx = m[0, 0] * gx + m[0, 1] * gy + m[0, 2]
    ty = m[1, 0] * gx + m[1, 1] * gy + m[1, 2]
    assert np.hypot(fx - tx, fy - ty).max() < 0.1
    assert summary["tiepoints"] >= 100


def test_georeference_prior_is_corrected_by_phase_correlation():
    rng = np.random.default_rng(1)
    img = ndi.gaussian_filter(rng.normal(size=(300, 300)), 2)
    a, b = img[20:276, 20:276], img[27:283, 15:271]  # b is a shifted by (-5, +7) in (x, y)
    ca = align_overviews(a, b, 1, prior=np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    assert ca.method.startswith("georeference+shift")
    np.testing.assert_allclose(ca.matrix, [[1, 0, 5], [0, 1, -7]], atol=0.05)


@pytest.mark.data
@pytest.mark.parametrize("angle, start", [(0.5, "translation"), (10.0, "fourier-mellin")])
def test_fourier_mellin_only_where_a_shift_does_not_correlate(shared_data, angle, start):
    """Without a georeference a plain shift is tried first, and Fourier-Mellin only where the
    shift's correlation peak is not decisive. Both ways the affine is found: a half-degree
    rotation by the local refinement, ten degrees from Fourier-Mellin."""
    src = read_band(shared_data / "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", 1, (200, 1400, 1000, 2200))
    size, origin = 384, (300, 300)
    base = src[origin[0] : origin[0] + size, origin[1] : origin[1] + size].astype(np.float64)
    m = _similarity(angle, 1.0, (191.5, 191.5), (12.0, -7.0))
    dist = _render(src, m, (400, 400), origin)
    found = align_overviews(base, dist, 1)
    print(angle, found.method, found.peak)
    assert found.method.startswith(start)
    gy, gx = np.mgrid[0:size:32, 0:size:32].astype(float)
    fx = found.matrix[0, 0] * gx + found.matrix[0, 1] * gy + found.matrix[0, 2]
    fy = found.matrix[1, 0] * gx + found.matrix[1, 1] * gy + found.matrix[1, 2]
    tx = m[0, 0] * gx + m[0, 1] * gy + m[0, 2]
    ty = m[1, 0] * gx + m[1, 1] * gy + m[1, 2]
    assert np.hypot(fx - tx, fy - ty).max() < 1.0  # a coarse start: the tie points refine it


def test_unrelated_images_raise():
    rng = np.random.default_rng(2)
    a = ndi.gaussian_filter(rng.normal(size=(128, 128)), 3)
    flat = np.zeros((128, 128))
    with pytest.raises(MatchingError, match="no overlap"):
        align_overviews(a, flat, 1)


@pytest.mark.parametrize("error_px", [(300.0, 0.0), (-250.0, 180.0)])
def test_georeference_hundreds_of_pixels_off(error_px):
    """A georeference wrong by more than half the overview: phase correlation's circular alias is
    resolved by the overlap's correlation (was: 'does not overlap' at 41 % real overlap)."""
    from geocoder.simulate.texture import synthetic_ortho

    src = np.squeeze(synthetic_ortho((768, 1024), seed=9)).astype(np.float64)
    base, dist = src[:512, :512], src[100:612, 100:612]
    truth = np.array([[1.0, 0.0, -100.0], [0.0, 1.0, -100.0]])
    prior = truth.copy()
    prior[:, 2] -= error_px
    found = align_overviews(base, dist, 1, prior=prior)
    assert found.method.startswith("georeference+shift")
    np.testing.assert_allclose(found.matrix, truth, atol=0.05)
