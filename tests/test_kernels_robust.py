import numpy as np
import pytest

from geocoder.kernels.polynomial import PolyMap, design, fit_polymap
from geocoder.kernels.robust import robust_fit, weight_exp, weight_l1


def test_weight_functions_follow_the_seed():
    v = np.array([0.1, 1.0, 2.0, 5.0])
    np.testing.assert_allclose(weight_l1(v), 4 * (np.sqrt(1 + v**2 / 2) - 1) / v**2)  # eq 20b
    np.testing.assert_allclose(weight_exp(v), np.exp(-(v**2) / 2))  # eq 22b
    assert weight_l1(np.array([0.0]))[0] == pytest.approx(1.0)


def test_robust_affine_with_many_outliers():
    rng = np.random.default_rng(0)
    n = 300
    x, y = rng.uniform(0, 1000, n), rng.uniform(0, 1000, n)
    truth = np.array([[1.02, 0.05, 12.0], [-0.04, 0.97, -7.0]])
    xp = truth[0, 0] * x + truth[0, 1] * y + truth[0, 2] + rng.normal(0, 0.1, n)
    yp = truth[1, 0] * x + truth[1, 1] * y + truth[1, 2] + rng.normal(0, 0.1, n)
    bad = rng.random(n) < 0.35
    xp[bad] += rng.uniform(-30, 30, bad.sum())
    yp[bad] += rng.uniform(-30, 30, bad.sum())
    m = fit_polymap(x, y, xp, yp, order=1)
    gx, gy = np.meshgrid(np.linspace(0, 1000, 5), np.linspace(0, 1000, 5))
    px, py = m(gx, gy)
    assert np.max(np.hypot(px - (truth[0, 0] * gx + truth[0, 1] * gy + truth[0, 2]), py - (truth[1, 0] * gx + truth[1, 1] * gy + truth[1, 2]))) < 0.1
    found = ~m.fit_info.inliers
    assert found[bad].mean() > 0.9  # nearly every outlier rejected
    assert found[~bad].mean() < 0.02
    assert m.fit_info.sigma0 == pytest.approx(0.1, rel=0.25)


def test_too_few_points():
    fit = robust_fit(design(np.zeros(3), np.zeros(3), 1), np.zeros((3, 2)))
    assert fit.reason == "too_few" and not fit.inliers.any()


def test_polymap_jacobian_and_affine_roundtrip():
    m = PolyMap.from_affine(np.array([[1.1, 0.2, 3.0], [-0.1, 0.9, 4.0]]))
    x, y = m(np.array([10.0]), np.array([20.0]))
    assert (x[0], y[0]) == pytest.approx((1.1 * 10 + 0.2 * 20 + 3, -0.1 * 10 + 0.9 * 20 + 4))
    rng = np.random.default_rng(1)
    q = PolyMap(rng.normal(size=(6, 2)), 2, (50.0, 40.0), 30.0)
    jac = q.jacobian(np.array([12.0]), np.array([7.0]))[0]
    h = 1e-5
    num = np.array([[(q(12 + h, 7)[i] - q(12 - h, 7)[i]) / (2 * h), (q(12, 7 + h)[i] - q(12, 7 - h)[i]) / (2 * h)] for i in range(2)])
    np.testing.assert_allclose(jac, num, rtol=1e-5)
    r = q.recentred((0.0, 0.0), 100.0)
    np.testing.assert_allclose(np.array(r(np.array([3.0, 80.0]), np.array([9.0, 2.0]))), np.array(q(np.array([3.0, 80.0]), np.array([9.0, 2.0]))), atol=1e-9)
