"""Geodesy of the WGS84 earth: the ellipsoid, geodetic <-> ECEF, local frames, earth rotation.

Shared by the block adjustment (:mod:`geocoder.adjust`), its sensor models and the simulator
(:mod:`geocoder.simulate`), which all work in WGS84 ECEF metres.

* **Geodetic / ECEF**: :func:`geodetic_to_ecef`, :func:`ecef_to_geodetic` (Bowring, iterated);
  latitudes and longitudes in radians, heights above the ellipsoid in metres.
* **Local frames**: :func:`ellipsoid_normal` (geodetic up) and :func:`enu_basis` (east, north,
  up at a geodetic position).
* **Inertial frame**: ECI coincides with ECEF at ``t = 0`` and ECEF rotates about ``+z`` by
  ``OMEGA_EARTH * t`` (:func:`eci_to_ecef`).
* **Rotations**: :func:`rotation` (active, right-handed, about a coordinate axis) and
  :func:`unit` for arrays of 3-vectors in the last axis.

Pure numpy, vectorised over arrays of points.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "GM_EARTH",
    "J2_EARTH",
    "OMEGA_EARTH",
    "WGS84_A",
    "WGS84_B",
    "WGS84_E2",
    "WGS84_F",
    "ecef_to_geodetic",
    "eci_to_ecef",
    "ellipsoid_normal",
    "enu_basis",
    "geodetic_to_ecef",
    "rotation",
    "unit",
]

#: WGS84 semi-major axis (m).
WGS84_A = 6378137.0
#: WGS84 flattening.
WGS84_F = 1 / 298.257223563
#: WGS84 semi-minor axis (m).
WGS84_B = WGS84_A * (1.0 - WGS84_F)
#: First eccentricity squared.
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
#: Second eccentricity squared.
_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
#: Earth gravitational parameter GM (m^3 s^-2).
GM_EARTH = 3.986004418e14
#: Earth rotation rate (rad/s).
OMEGA_EARTH = 7.2921151467e-5
#: Earth J2 (only used to choose a sun-synchronous inclination).
J2_EARTH = 1.08262668e-3


# --------------------------------------------------------------------------- #
# Ellipsoid
# --------------------------------------------------------------------------- #
def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Geodetic WGS84 coordinates to ECEF.

    Parameters
    ----------
    lat, lon : array_like
        Geodetic latitude and longitude (radians); broadcast together.
    h : array_like
        Height above the ellipsoid (m).

    Returns
    -------
    X, Y, Z : ndarray
        ECEF coordinates (m).
    """
    lat, lon, h = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (lat, lon, h)))
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    X = (n + h) * cl * np.cos(lon)
    Y = (n + h) * cl * np.sin(lon)
    Z = (n * (1.0 - WGS84_E2) + h) * sl
    return X, Y, Z


def ecef_to_geodetic(X: ArrayLike, Y: ArrayLike, Z: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF to geodetic WGS84 coordinates (Bowring's method, iterated).

    Bowring's parametric-latitude formula is iterated four times, which is
    accurate to far below a millimetre (typically ~1e-9 m) for heights from
    the earth's interior to beyond geostationary orbit; valid at the poles.

    Parameters
    ----------
    X, Y, Z : array_like
        ECEF coordinates (m); broadcast together.

    Returns
    -------
    lat, lon, h : ndarray
        Geodetic latitude and longitude (radians) and ellipsoidal height (m).
    """
    X, Y, Z = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (X, Y, Z)))
    p = np.hypot(X, Y)
    lon = np.arctan2(Y, X)
    # the angles as (sine, cosine) pairs, normalised: tan(beta) = (1 - f) tan(lat), and
    # Bowring's latitude is the direction of (num, den); no trigonometric function in the loop
    # (the simulator's ground of every pixel spent half its time in this function's arctan2, sin, cos)
    k = 1.0 - WGS84_F
    with np.errstate(invalid="ignore", divide="ignore"):
        kp = k * p
        r = np.sqrt(Z * Z + kp * kp)
        sb, cb = Z / r, kp / r
        for _ in range(4):
            num = Z + (_EP2 * WGS84_B) * (sb * sb * sb)
            den = p - (WGS84_E2 * WGS84_A) * (cb * cb * cb)
            kn = k * num
            r = np.sqrt(kn * kn + den * den)
            sb, cb = kn / r, den / r
        r = np.sqrt(num * num + den * den)
        sl, cl = num / r, den / r
    lat = np.arctan2(num, den)
    h = p * cl + Z * sl - WGS84_A * np.sqrt(1.0 - WGS84_E2 * sl * sl)
    return lat, lon, h


def ellipsoid_normal(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Unit ellipsoid normal (geodetic up) in ECEF.

    Parameters
    ----------
    lat, lon : ndarray
        Geodetic latitude and longitude (radians), same shape.

    Returns
    -------
    ndarray, shape ``lat.shape + (3,)``
    """
    cl = np.cos(lat)
    return np.stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)], axis=-1)


def enu_basis(lat_deg: float, lon_deg: float) -> np.ndarray:
    """The local east, north and up unit vectors (ECEF) at a geodetic position.

    Parameters
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude (degrees).

    Returns
    -------
    ndarray, shape (3, 3)
        Rows are east, north and up.
    """
    la, lo = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    sla, cla, slo, clo = np.sin(la), np.cos(la), np.sin(lo), np.cos(lo)
    return np.array(
        [
            [-slo, clo, 0.0],
            [-sla * clo, -sla * slo, cla],
            [cla * clo, cla * slo, sla],
        ]
    )


# --------------------------------------------------------------------------- #
# Vectors and rotations (arrays of 3-vectors in the last axis)
# --------------------------------------------------------------------------- #
def unit(v: np.ndarray) -> np.ndarray:
    """Vectors scaled to unit length along the last axis.

    Parameters
    ----------
    v : ndarray, shape ``(..., 3)``

    Returns
    -------
    ndarray, shape ``(..., 3)``
    """
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotation(axis: int, angle: ArrayLike) -> np.ndarray:
    """Active right-handed rotation matrices about a coordinate axis.

    Parameters
    ----------
    axis : int
        0 = x, 1 = y, 2 = z.
    angle : array_like
        Rotation angle (radians).

    Returns
    -------
    ndarray, shape ``angle.shape + (3, 3)``
    """
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def eci_to_ecef(pos: np.ndarray, vel: np.ndarray, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Inertial position and velocity to ECEF (velocity relative to the rotating earth).

    Parameters
    ----------
    pos, vel : ndarray, shape ``(..., 3)``
        ECI position (m) and velocity (m/s); ECI coincides with ECEF at ``t = 0``.
    t : array_like
        Time since the epoch (s), broadcast against ``pos[..., 0]``.

    Returns
    -------
    pos, vel : ndarray, shape ``(..., 3)``
        ``Rz(-OMEGA_EARTH t) pos`` and ``Rz(-OMEGA_EARTH t) vel - omega x pos_ecef``.
    """
    th = OMEGA_EARTH * np.asarray(t, dtype=np.float64)
    c, s = np.cos(th), np.sin(th)
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    re = np.stack([c * x + s * y, -s * x + c * y, z], axis=-1)
    vx, vy, vz = vel[..., 0], vel[..., 1], vel[..., 2]
    ve = np.stack(
        [c * vx + s * vy + OMEGA_EARTH * re[..., 1], -s * vx + c * vy - OMEGA_EARTH * re[..., 0], vz],
        axis=-1,
    )
    return re, ve

