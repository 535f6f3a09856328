"""Tests of geocoder.adjust.dem (a gridded DEM as a height constraint) and its use by the solver."""

from __future__ import annotations

import numpy as np
import pytest

from geocoder.adjust.dem import DEM
from geocoder.simulate.satellite import ecef_to_geodetic, geodetic_to_ecef


def _terrain(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    la, lo = np.rad2deg(lat), np.rad2deg(lon)
    return 1500.0 + 900.0 * np.sin(la * 55.0) * np.cos(lo * 30.0)


@pytest.fixture(scope="module")
def dem() -> DEM:
    return DEM.from_function(_terrain, (58.0, 59.0), (-99.0, -97.0), 0.002, 5.0)


def _points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lat, lon, h = rng.uniform(58.1, 58.9, n), rng.uniform(-98.9, -97.1, n), rng.uniform(0, 3000, n)
    return lat, lon, h, np.stack(geodetic_to_ecef(np.deg2rad(lat), np.deg2rad(lon), h), axis=-1)


def test_bilinear_height_is_exact_on_a_plane_and_close_on_terrain(dem: DEM) -> None:
    lat, lon, _, _ = _points(200, 1)
    plane = DEM.from_function(lambda la, lo: 100 + 2000 * np.rad2deg(la) - 500 * np.rad2deg(lo), (58, 59), (-99, -97),
                              0.01, 1.0)
    h, dlat, dlon = plane.height(lat, lon)
    np.testing.assert_allclose(h, 100 + 2000 * lat - 500 * lon, rtol=1e-12)
    np.testing.assert_allclose(dlat, 2000.0, rtol=1e-9)
    np.testing.assert_allclose(dlon, -500.0, rtol=1e-9)
    h, _, _ = dem.height(lat, lon)
    assert np.abs(h - _terrain(np.deg2rad(lat), np.deg2rad(lon))).max() < 3.0  # 220 m nodes, 12 km waves
    h, d1, d2 = dem.height(np.array([57.0, 58.5]), np.array([-98.0, -100.0]))
    assert np.all(np.isnan(h)) and np.all(np.isnan(d1)) and np.all(np.isnan(d2))


def test_constraint_misclosure_and_gradient(dem: DEM) -> None:
    """``c = h - H`` and ``dc/dP`` (slope included) against central differences in ECEF."""
    lat, lon, h, P = _points(300, 2)
    c, g = dem.constraint(P)
    np.testing.assert_allclose(c, h - dem.height(lat, lon)[0], atol=1e-6)
    num = np.stack([(dem.constraint(P + 0.01 * e)[0] - dem.constraint(P - 0.01 * e)[0]) / 0.02 for e in np.eye(3)],
                   axis=-1)
    err = np.abs(g - num).max(axis=1)
    assert np.mean(err < 1e-6) > 0.97  # the rest lie within the 1 cm step of a cell edge (slope kink)
    assert err.max() < 1e-2
    # the slope matters: on steep terrain the gradient leaves the vertical by tens of degrees
    la, lo, _ = ecef_to_geodetic(*P.T)
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    assert np.degrees(np.arccos(np.max(np.einsum("pi,pi->p", g, up) / np.linalg.norm(g, axis=1)))) < 1.0
    assert np.degrees(np.arccos(np.min(np.einsum("pi,pi->p", g, up) / np.linalg.norm(g, axis=1)))) > 10.0


def test_solver_puts_a_point_seen_once_on_the_dem(dem: DEM) -> None:
    """A tie point seen by one oblique ray is undetermined; held to the DEM it lands where the ray
    meets the terrain (Newton on the bilinear surface, slope included)."""
    from geocoder.adjust.solver import AdjustOptions, Frame, Problem, adjust

    class Ortho:
        """Image = (east, north) metres around an origin, tilted by ``k`` px per metre of height."""

        n_params = 2

        def __init__(self, k: float, origin: np.ndarray) -> None:
            self.k, self.o = k, origin
            la, lo, _ = ecef_to_geodetic(*origin)
            self.e = np.array([-np.sin(lo), np.cos(lo), 0.0])
            self.n = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
            self.u = np.cross(self.e, self.n)

        def project(self, p: np.ndarray, g: np.ndarray) -> np.ndarray:
            d = g - self.o
            return np.stack([d @ self.e + self.k * (d @ self.u) + p[0], d @ self.n + p[1]], axis=-1)

        def jacobians(self, p: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            m = g.shape[0]
            jp = np.zeros((m, 2, 2))
            jp[:, 0, 0] = jp[:, 1, 1] = 1.0
            jg = np.broadcast_to(np.stack([self.e + self.k * self.u, self.n]), (m, 2, 3)).copy()
            return jp, jg

    origin = np.array(geodetic_to_ecef(np.deg2rad(58.5), np.deg2rad(-98.0), 0.0))
    lat, lon = 58.5123, -97.9871
    true_h = float(dem.height(lat, lon)[0])
    P = np.array(geodetic_to_ecef(np.deg2rad(lat), np.deg2rad(lon), true_h))
    model = Ortho(0.05, origin)
    xy = model.project(np.zeros(2), P[None])
    start = P + np.array([300.0, -200.0, 400.0])
    base = {"frames": [Frame(model, np.zeros(2), prior_weight=np.eye(2) * 1e6)], "ground": start[None].copy(),
            "ground_prior": start[None].copy(), "ground_weight": np.zeros((1, 3, 3)), "obs_frame": np.array([0]),
            "obs_point": np.array([0]), "obs_xy": xy, "obs_weight": np.eye(2)[None] / 0.5**2}
    free = adjust(Problem(**base), AdjustOptions(covariance=False))
    assert not free.point_valid[0]  # one ray: the 3x3 block is singular
    res = adjust(Problem(**base, dem=dem), AdjustOptions(covariance=False))
    assert res.converged and res.point_valid.all()
    assert np.linalg.norm(res.ground[0] - P) < 1e-3  # on the ray and on the DEM
    # redundancy: 2 observations + 1 DEM height + 2 parameter priors - 3 - 2 unknowns
    assert res.total_redundancy == pytest.approx(0.0)
