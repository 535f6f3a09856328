import numpy as np
import pytest

from geocoder.kernels.polynomial import fit_polymap
from geocoder.pipeline.resample import poly_grid


@pytest.mark.parametrize("order", [1, 2, 3])
def test_poly_grid_equals_the_mapping(order):
    rng = np.random.default_rng(order)
    x, y = rng.uniform(0, 2048, 200), rng.uniform(0, 2048, 200)
    m = fit_polymap(x, y, x + 3 + 1e-3 * x + 2e-6 * y**2, y - 5 + 1e-6 * x * y + 1e-9 * x**3, order=order, robust=False)
    ys, xs = np.mgrid[512:1000, 1500:2048].astype(np.float64)
    px, py = m(xs, ys)
    np.testing.assert_allclose(poly_grid(m, (512, 1000), (1500, 2048), 0), px - xs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(poly_grid(m, (512, 1000), (1500, 2048), 1), py - ys, rtol=0, atol=1e-9)
