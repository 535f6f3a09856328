import dask.array as da
import numpy as np
import pytest
import scipy.ndimage as ndi
from conftest import read_band

from geocoder.kernels.interest import detect, foerstner, select_points
from geocoder.pipeline.detect import InterestOptions, interest_points


def _corner_image():
    img = np.zeros((64, 64))
    img[20:, 30:] = 100.0  # one corner at (row 20, col 30)
    return img


def test_foerstner_roundness_edge_and_corner():
    w, q = foerstner(_corner_image(), window=5)
    # on a straight edge the normal matrix is singular: q = 0
    assert q[45, 30] == pytest.approx(0.0, abs=1e-6)
    assert q[20, 50] == pytest.approx(0.0, abs=1e-6)
    # at the corner the gradients span both directions
    r, c = np.unravel_index(np.argmax(w), w.shape)
    assert abs(r - 19.5) <= 2 and abs(c - 29.5) <= 2  # within half the window
    assert q[r, c] > 0.25
    # flat area: nothing
    assert w[5, 5] == 0 and q[5, 5] == 0


def test_foerstner_matches_definition():
    rng = np.random.default_rng(3)
    img = ndi.gaussian_filter(rng.normal(size=(40, 40)), 1.5)
    w, q = foerstner(img, window=7)
    r, c = 20, 17
    a, b, cc, d = img[:-1, :-1], img[:-1, 1:], img[1:, :-1], img[1:, 1:]
    gx = 0.5 * ((b - a) + (d - cc))
    gy = 0.5 * ((cc - a) + (d - b))
    sl = (slice(r - 3, r + 3), slice(c - 3, c + 3))  # 6 x 6 quad gradients around pixel (r, c)
    n = np.array([[np.sum(gx[sl] ** 2), np.sum(gx[sl] * gy[sl])], [np.sum(gx[sl] * gy[sl]), np.sum(gy[sl] ** 2)]])
    det, tr = np.linalg.det(n), np.trace(n)
    assert w[r, c] == pytest.approx(det / tr, rel=1e-5)  # eq 33: 1 / tr Q
    assert q[r, c] == pytest.approx(4 * det / tr**2, rel=1e-5)  # eq 30


def test_nodata_suppresses_points():
    rng = np.random.default_rng(4)
    img = ndi.gaussian_filter(rng.normal(size=(128, 128)), 2)
    img[:, :40] = np.nan
    pts = detect(img, window=7)
    assert len(pts) > 10
    assert pts.x.min() >= 40 + 3  # no window may touch nodata


def test_cap_and_suppression():
    rng = np.random.default_rng(5)
    img = ndi.gaussian_filter(rng.normal(size=(256, 256)), 1.0)
    pts = detect(img, cell=64, cap=3, radius=4)
    cells = (pts.y // 64) * 4 + pts.x // 64
    assert np.bincount(cells.astype(int)).max() <= 3
    d = np.hypot(pts.x[:, None] - pts.x[None], pts.y[:, None] - pts.y[None])
    np.fill_diagonal(d, np.inf)
    assert np.all(np.maximum(np.abs(pts.x[:, None] - pts.x[None]), np.abs(pts.y[:, None] - pts.y[None]))[d < np.inf] > 4)


def test_select_points_tie_break_is_global():
    w = np.ones((9, 9), dtype=np.float32)  # a plateau: exactly one winner per window
    q = np.ones_like(w)
    pts = select_points(w, q, w_min=0.5, radius=4, cap=0)
    assert len(pts) == 1 and (pts.x[0], pts.y[0]) == (0, 0)


@pytest.mark.data
@pytest.mark.parametrize("chunks", [256, 1024])
def test_tiled_points_equal_whole_image(shared_data, chunks):
    img = read_band(shared_data / "s2_arosics/ref_S2A_20160608T153121_T33UUU_sub.tif", window=(0, 1500, 500, 1800))
    img[img == 0] = np.nan
    ref = detect(img)
    tiled = interest_points(da.from_array(img.astype(np.float32), chunks=chunks), InterestOptions())
    assert len(ref) > 500
    np.testing.assert_array_equal(tiled.x, ref.x)
    np.testing.assert_array_equal(tiled.y, ref.y)
    np.testing.assert_allclose(tiled.w, ref.w, rtol=1e-6)


def test_foerstner_matches_numpy_reference_and_is_block_independent():
    from geocoder.kernels.interest import foerstner_reference

    rng = np.random.default_rng(6)
    img = ndi.gaussian_filter(rng.normal(size=(150, 170)), 1.5) * 1000
    img[60:66, 30:41] = np.nan
    w, q = foerstner(img, window=7)
    wr, qr = foerstner_reference(img, window=7)
    np.testing.assert_array_equal(w > 0, wr > 0)
    np.testing.assert_allclose(w, wr, rtol=1e-5, atol=1e-6 * wr.max())
    np.testing.assert_allclose(q, qr, rtol=1e-5, atol=1e-6)
    wb, qb = foerstner(img[17:120, 9:151], window=7)  # any block: the same values, bit for bit
    np.testing.assert_array_equal(wb[3:-3, 3:-3], w[20:117, 12:148])
    np.testing.assert_array_equal(qb[3:-3, 3:-3], q[20:117, 12:148])


@pytest.mark.parametrize("chunks", [64, 128])
def test_one_pass_tiles_equal_whole_image_synthetic(chunks):
    rng = np.random.default_rng(7)
    img = ndi.gaussian_filter(rng.normal(size=(320, 256)), 1.2)
    img[:, :20] = np.nan
    ref = detect(img)
    tiled = interest_points(da.from_array(img.astype(np.float32), chunks=chunks), InterestOptions())
    assert len(ref) > 100
    np.testing.assert_array_equal(tiled.x, ref.x)
    np.testing.assert_array_equal(tiled.y, ref.y)
    np.testing.assert_allclose(tiled.w, ref.w, rtol=1e-6)


def test_local_maxima_against_the_nine_neighbours():
    """Candidates of the non-maximum suppression: above 0 and beaten by none of the 8 neighbours
    (ties kept, NaN never beats, outside the block ignored), in raster order, on any sub-block."""
    from geocoder.kernels.interest import _local_maxima

    rng = np.random.default_rng(7)
    w = rng.integers(0, 6, (61, 47)).astype(np.float32)  # small integers: many plateaus and ties
    w[rng.random(w.shape) < 0.05] = np.nan
    w[0, :4] = np.nan
    padded = np.pad(w, 1, constant_values=-np.inf)
    beaten = np.zeros(w.shape, bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            beaten |= padded[1 + dr : 1 + dr + w.shape[0], 1 + dc : 1 + dc + w.shape[1]] > w
    want = (w > 0) & ~beaten
    for r0, r1, c0, c1 in [(0, 61, 0, 47), (3, 58, 5, 40), (0, 1, 0, 47), (60, 61, 46, 47)]:
        rows, cols = _local_maxima(w, r0, r1, c0, c1)
        sub = np.zeros(w.shape, bool)
        sub[r0:r1, c0:c1] = want[r0:r1, c0:c1]
        wr, wc = np.nonzero(sub)
        np.testing.assert_array_equal(rows, wr)
        np.testing.assert_array_equal(cols, wc)
