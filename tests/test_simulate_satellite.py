"""Tests of geocoder.simulate.satellite (rigorous line-scanner geometry)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, optimize

from geocoder.simulate.satellite import (
    GM_EARTH,
    OMEGA_EARTH,
    WGS84_A,
    WGS84_F,
    LineScanner,
    Orbit,
    ecef_to_geodetic,
    geodetic_to_ecef,
    landsat_mss_like,
)

E2 = WGS84_F * (2 - WGS84_F)


def _terrain(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Smooth terrain, 0..2000 m, wavelengths of a few tens of km."""
    return 1000.0 + 1000.0 * np.sin(lat * 200.0) * np.cos(lon * 150.0)


def _grid(sc: LineScanner, n: int = 21) -> tuple[np.ndarray, np.ndarray]:
    r, c = np.meshgrid(np.linspace(0, sc.rows - 1, n), np.linspace(0, sc.cols - 1, n), indexing="ij")
    return r, c


# --------------------------------------------------------------------------- #
# 1. ellipsoid
# --------------------------------------------------------------------------- #
def test_geodetic_ecef_round_trip() -> None:
    rng = np.random.default_rng(0)
    n = 20000
    lat = np.arcsin(rng.uniform(-1, 1, n))
    lon = rng.uniform(-np.pi, np.pi, n)
    h = rng.uniform(-10e3, 1.2e6, n)
    lat = np.concatenate([lat, [np.pi / 2, -np.pi / 2, 0.0, 1e-9]])
    lon = np.concatenate([lon, [0.3, -2.0, 0.0, np.pi]])
    h = np.concatenate([h, [100.0, 917e3, 0.0, -500.0]])
    X, Y, Z = geodetic_to_ecef(lat, lon, h)
    lat2, lon2, h2 = ecef_to_geodetic(X, Y, Z)
    X2, Y2, Z2 = geodetic_to_ecef(lat2, lon2, h2)
    err = np.sqrt((X2 - X) ** 2 + (Y2 - Y) ** 2 + (Z2 - Z) ** 2)
    assert err.max() < 1e-6
    assert np.abs(h2 - h).max() < 1e-6
    assert np.abs(lat2 - lat).max() * WGS84_A < 1e-6
    # a hand value: the pole is at Z = b
    assert geodetic_to_ecef(np.pi / 2, 0.0, 0.0)[2] == pytest.approx(WGS84_A * (1 - WGS84_F), abs=1e-6)


# --------------------------------------------------------------------------- #
# 2. Kepler
# --------------------------------------------------------------------------- #
def test_kepler_circular_speed_and_elliptic_energy() -> None:
    t = np.linspace(-7000.0, 7000.0, 501)
    circ = Orbit(7.1e6, 0.0, 1.7, 0.4, 0.2, 1.0, line_time=0.01)
    pos, vel = circ.position_velocity(t)
    assert np.allclose(np.linalg.norm(vel, axis=-1), np.sqrt(GM_EARTH / 7.1e6), rtol=1e-12)
    assert np.allclose(np.linalg.norm(pos, axis=-1), 7.1e6, rtol=1e-12)

    ell = Orbit(8.0e6, 0.15, 0.9, 1.1, 2.3, 0.5, line_time=0.01)
    pos, vel = ell.position_velocity(t)
    r = np.linalg.norm(pos, axis=-1)
    energy = 0.5 * np.sum(vel * vel, axis=-1) - GM_EARTH / r
    assert np.ptp(energy) / abs(energy.mean()) < 1e-12
    assert energy.mean() == pytest.approx(-GM_EARTH / (2 * 8.0e6), rel=1e-12)
    # angular momentum is conserved and the velocity is the derivative of position
    hvec = np.cross(pos, vel)
    assert np.abs(hvec - hvec[0]).max() / np.linalg.norm(hvec[0]) < 1e-12
    h = 1e-3
    p1, _ = ell.position_velocity(t + h)
    p0, _ = ell.position_velocity(t - h)
    assert np.abs((p1 - p0) / (2 * h) - vel).max() < 1e-4
    # perigee and apogee radii
    assert r.min() >= 8.0e6 * (1 - 0.15) - 1e-3 and r.max() <= 8.0e6 * (1 + 0.15) + 1e-3


def test_ecef_velocity_includes_earth_rotation() -> None:
    orb = Orbit(7.2e6, 0.01, 1.0, 0.3, 0.5, 0.7, line_time=0.01)
    t = np.array([0.0, 100.0, 1234.5])
    re, ve = orb.position_velocity_ecef(t)
    h = 1e-3
    rp, _ = orb.position_velocity_ecef(t + h)
    rm, _ = orb.position_velocity_ecef(t - h)
    assert np.abs((rp - rm) / (2 * h) - ve).max() < 1e-4
    # ECI = ECEF at t = 0
    pi, _ = orb.position_velocity(0.0)
    assert np.allclose(re[0], pi)


def test_sun_synchronous_orbit_over_point() -> None:
    lat0, lon0 = np.deg2rad(39.0), np.deg2rad(-98.0)
    for descending in (True, False):
        orb = Orbit.circular_sun_synchronous(
            altitude=705e3, lat0=lat0, lon0=lon0, line_time=0.01, descending=descending
        )
        assert np.rad2deg(orb.inclination) == pytest.approx(98.2, abs=0.05)
        r, v = orb.position_velocity_ecef(0.0)
        g = np.array(geodetic_to_ecef(lat0, lon0, 0.0))
        assert np.allclose(r / np.linalg.norm(r), g / np.linalg.norm(g), atol=1e-14)
        assert (v[2] < 0) == descending
    orb917 = Orbit.circular_sun_synchronous(altitude=917e3, lat0=lat0, lon0=lon0, line_time=0.01)
    assert np.rad2deg(orb917.inclination) == pytest.approx(99.1, abs=0.1)


# --------------------------------------------------------------------------- #
# 3. direct <-> inverse round trips over the whole frame
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("kind", ["pushbroom", "whiskbroom"])
def test_round_trips_whole_frame(kind: str) -> None:
    sc = landsat_mss_like(seed=7, kind=kind)
    assert np.abs(sc.deviations).max() > 0
    r, c = _grid(sc, 25)
    X, Y, Z = sc.image_to_ground(r, c, terrain=_terrain)
    assert np.all(np.isfinite(X))
    lat, lon, h = ecef_to_geodetic(X, Y, Z)
    assert np.abs(h - _terrain(lat, lon)).max() < 1e-3
    rr, cc = sc.ground_to_image(X, Y, Z)
    assert np.abs(rr - r).max() < 1e-6
    assert np.abs(cc - c).max() < 1e-6

    # ground -> image -> ground, for points on the terrain all over the frame
    rng = np.random.default_rng(1)
    lat_b, lon_b = (lat.min(), lat.max()), (lon.min(), lon.max())
    lat_g = rng.uniform(*lat_b, 2000)
    lon_g = rng.uniform(*lon_b, 2000)
    G = geodetic_to_ecef(lat_g, lon_g, _terrain(lat_g, lon_g))
    row, col = sc.ground_to_image(*G)
    assert np.all(np.isfinite(row))
    X2, Y2, Z2 = sc.image_to_ground(row, col, terrain=_terrain)
    err = np.sqrt((X2 - G[0]) ** 2 + (Y2 - G[1]) ** 2 + (Z2 - G[2]) ** 2)
    assert err.max() < 1e-3

    # constant height
    X3, Y3, Z3 = sc.image_to_ground(r, c, height=1500.0)
    assert np.abs(ecef_to_geodetic(X3, Y3, Z3)[2] - 1500.0).max() < 1e-3
    rr3, cc3 = sc.ground_to_image(X3, Y3, Z3)
    assert np.abs(rr3 - r).max() < 1e-6 and np.abs(cc3 - c).max() < 1e-6


def test_whiskbroom_skews_rows() -> None:
    push = landsat_mss_like(kind="pushbroom")
    whisk = landsat_mss_like(kind="whiskbroom")
    assert whisk.col_time > 0
    # same ground point: the whiskbroom sees the right edge later, i.e. at a smaller row
    G = push.image_to_ground(1000.0, 3000.0)
    rw, cw = whisk.ground_to_image(*G)
    assert rw < 1000.0 - 1.0
    t_w = whisk.time(rw, cw)
    t_p = push.time(1000.0, 3000.0)
    assert abs(float(t_w - t_p)) < 5 * push.orbit.line_time


def test_parameters_round_trip() -> None:
    sc = landsat_mss_like(seed=3, kind="whiskbroom", rows=200, cols=300)
    p = sc.parameters()
    assert p.shape == (32,)
    sc2 = LineScanner.from_parameters(p, rows=200, cols=300, ifov=sc.ifov, kind="whiskbroom", col_time=sc.col_time)
    assert np.array_equal(sc2.parameters(), p)
    r, c = _grid(sc, 5)
    assert np.allclose(np.stack(sc.image_to_ground(r, c)), np.stack(sc2.image_to_ground(r, c)), rtol=0, atol=0)
    with pytest.raises(ValueError):
        LineScanner(orbit=sc.orbit, rows=10, cols=10, ifov=1e-4, kind="frame")


# --------------------------------------------------------------------------- #
# 4. pixel size and swath
# --------------------------------------------------------------------------- #
def test_pixel_size_and_swath() -> None:
    sc = landsat_mss_like()
    rc, cc = (sc.rows - 1) / 2, (sc.cols - 1) / 2
    S, _ = sc.exterior(sc.time(rc, cc))
    altitude = float(ecef_to_geodetic(*S)[2])
    assert 900e3 < altitude < 935e3
    P = np.stack(sc.image_to_ground([rc, rc, rc + 1], [cc, cc + 1, cc]), axis=-1)
    across = np.linalg.norm(P[1] - P[0])
    along = np.linalg.norm(P[2] - P[0])
    assert across == pytest.approx(altitude * sc.ifov, rel=0.01)
    assert along == pytest.approx(79.0, rel=0.01)
    E = np.stack(sc.image_to_ground([rc, rc], [0.0, sc.cols - 1.0]), axis=-1)
    swath = np.linalg.norm(E[1] - E[0]) * sc.cols / (sc.cols - 1)
    assert swath == pytest.approx(185e3, rel=0.03)


# --------------------------------------------------------------------------- #
# 5. hand-computed equatorial case
# --------------------------------------------------------------------------- #
def _equatorial(**kw: float) -> LineScanner:
    orb = Orbit(WGS84_A + 800e3, 0.0, 0.0, 0.0, 0.0, 0.3, line_time=0.01)
    return LineScanner(orbit=orb, rows=1000, cols=2001, ifov=1e-4, **kw)


def _sub_satellite(orb: Orbit, t: float) -> tuple[float, np.ndarray]:
    """Longitude of the satellite over the rotating earth, and the ECEF of the ground point below."""
    n = np.sqrt(GM_EARTH / orb.semi_major_axis**3)
    theta = orb.mean_anomaly0 + (n - OMEGA_EARTH) * t
    return theta, WGS84_A * np.array([np.cos(theta), np.sin(theta), 0.0])


def _meridian_arc(phi: float) -> float:
    """Ellipsoidal meridian arc length from the equator to geodetic latitude ``phi``."""
    return integrate.quad(lambda p: WGS84_A * (1 - E2) / (1 - E2 * np.sin(p) ** 2) ** 1.5, 0.0, phi, epsabs=1e-9)[0]


def _latitude_of_meridian_arc(d: float) -> float:
    return optimize.brentq(lambda p: _meridian_arc(p) - d, -0.1, 0.1, xtol=1e-15)


def test_equatorial_hand_computed() -> None:
    sc = _equatorial()
    orb = sc.orbit
    Hs = orb.semi_major_axis  # satellite geocentric distance
    for row0 in (0.0, 123.0, 777.25):
        t = row0 * orb.line_time
        theta, G = _sub_satellite(orb, t)
        r, c = sc.ground_to_image(*G)
        assert abs(float(r) - row0) < 1e-6
        assert abs(float(c) - sc.centre_col) < 1e-6

        # a point on the same meridian, d metres of meridian arc north of the equator
        for d in (-60e3, 25e3, 90e3):
            phi = _latitude_of_meridian_arc(d)
            N = WGS84_A / np.sqrt(1 - E2 * np.sin(phi) ** 2)
            rho, z = N * np.cos(phi), N * (1 - E2) * np.sin(phi)  # meridian-plane coordinates
            P = np.array([rho * np.cos(theta), rho * np.sin(theta), z])
            # look angle from the satellite's nadir to P, in the meridian plane;
            # the orbit is prograde, so +y (right of the motion) is south.
            psi = np.arctan2(-z, Hs - rho)
            r, c = sc.ground_to_image(*P)
            assert abs(float(r) - row0) < 1e-6
            assert abs(float(c) - (sc.centre_col + psi / sc.ifov)) < 1e-6
            # and back to the ground
            Q = np.array(sc.image_to_ground(r, c))
            assert np.linalg.norm(Q - P) < 1e-3


def test_roll_shifts_column() -> None:
    roll = 2e-4
    dev = np.zeros((6, 4))
    dev[3, 0] = roll
    sc = _equatorial(deviations=dev)
    t = 400 * sc.orbit.line_time
    _, G = _sub_satellite(sc.orbit, t)
    r, c = sc.ground_to_image(*G)
    assert abs(float(r) - 400) < 1e-6
    assert abs(float(c) - (sc.centre_col + roll / sc.ifov)) < 1e-6


def test_behind_sensor_is_nan() -> None:
    sc = _equatorial()
    _, G = _sub_satellite(sc.orbit, 5.0)
    r, c = sc.ground_to_image(*(3.0 * G))  # above the satellite: behind the sensor
    assert np.isnan(r) and np.isnan(c)
    r, c = sc.ground_to_image(*G)
    assert abs(float(r) - 500.0) < 1e-6
