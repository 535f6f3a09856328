"""Rigorous line-scanner geometry: a Keplerian orbit over a rotating WGS84 earth.

The model follows Paderes, Mikhail & Foerstner (1984), sec. 2.1, eq. (1)::

    (x, y, z)^T = lambda * M(t) * (X - Xs(t), Y - Ys(t), Z - Zs(t))^T

where ``t`` is a function of the image row (and of the column for a scanning
mirror), ``(Xs, Ys, Zs)`` is the ideal Keplerian satellite position plus a
deviation, and ``M`` rotates ground (ECEF) vectors into the sensor frame.
Deviations of position (3) and attitude (3) are cubic polynomials in time
(6 x 4 = 24 parameters); the orbit and timing add 8 parameters.

Frames and conventions
----------------------
* **ECEF / ECI.**  Ground coordinates are WGS84 ECEF (metres).  The inertial
  frame (ECI) coincides with ECEF at ``t = 0`` (the orbit epoch) and ECEF
  rotates about ``+z`` by ``OMEGA_EARTH * t``::

      r_ecef = Rz(-OMEGA_EARTH t) r_eci,   v_ecef = Rz(-OMEGA_EARTH t) v_eci - omega x r_ecef

* **Orbital frame** (from the *ideal* ECEF position ``r`` and the ECEF
  velocity ``v``, i.e. including earth rotation; "yaw-steered")::

      z_o = -r / |r|                       (toward the earth centre: geocentric nadir)
      y_o = z_o x v / |z_o x v|            (cross-track; to the right of the motion)
      x_o = y_o x z_o                      (along-track, ~ along v)

* **Position deviation** ``(dA, dC, dR)`` = (along-track, cross-track,
  radial) in metres; radial is positive *outward* (higher altitude)::

      S = r + dA x_o + dC y_o - dR z_o

* **Attitude** (roll, pitch, yaw) in radians: the sensor axes expressed in the
  orbital frame are the columns of ``A = Rz(yaw) Ry(pitch) Rx(roll)`` (active,
  right-handed rotations about the orbital x, y, z axes; full matrices, not
  small-angle).  ``M = (B A)^T`` where the columns of ``B`` are
  ``x_o, y_o, z_o`` in ECEF.
* **Look vector** of column ``c`` in the sensor frame:
  ``(0, sin psi, cos psi)`` with ``psi = (c - (cols - 1) / 2) * ifov``, so the
  collinearity ratios are ``x/z = 0`` and ``y/z = tan(psi)``.  Positive ``psi``
  (larger column) looks to the right of the motion (``+y_o``).
* **Time**: ``t = t0 + row * line_time`` (pushbroom) plus ``col * col_time``
  for a whiskbroom (scanning mirror).  Deviation polynomials are evaluated at
  this ``t`` (seconds from the orbit epoch): ``d(t) = c0 + c1 t + c2 t^2 + c3 t^3``.
* Image coordinates follow ``CONVENTIONS.md``: ``x`` = column, ``y`` = row,
  pixel centres at integers.

Everything is vectorised over arrays of points; iterations (Kepler, ray -
terrain intersection, time search) are fixed-point/Newton loops over whole
arrays.  Pure numpy; no file I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

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
    "LineScanner",
    "Orbit",
    "ecef_to_geodetic",
    "geodetic_to_ecef",
    "landsat_mss_like",
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
#: Mean motion of the sun in right ascension (rad/s): 2 pi per tropical year.
_SUN_RATE = 2.0 * np.pi / (365.2421897 * 86400.0)

_KINDS = ("pushbroom", "whiskbroom")


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
    # initial parametric latitude
    beta = np.arctan2(Z, p * (1.0 - WGS84_F))
    for _ in range(4):
        sb, cb = np.sin(beta), np.cos(beta)
        lat = np.arctan2(Z + _EP2 * WGS84_B * sb**3, p - WGS84_E2 * WGS84_A * cb**3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    sl, cl = np.sin(lat), np.cos(lat)
    h = p * cl + Z * sl - WGS84_A * np.sqrt(1.0 - WGS84_E2 * sl * sl)
    return lat, lon, h


def _up(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Unit ellipsoid normal (geodetic up) in ECEF, shape ``lat.shape + (3,)``."""
    cl = np.cos(lat)
    return np.stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)], axis=-1)


# --------------------------------------------------------------------------- #
# Small vector helpers (arrays of 3-vectors in the last axis)
# --------------------------------------------------------------------------- #
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rot(axis: int, angle: np.ndarray) -> np.ndarray:
    """Active right-handed rotation matrices about ``axis`` (0=x, 1=y, 2=z), shape ``(..., 3, 3)``."""
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


def _eci_to_ecef(pos: np.ndarray, vel: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


# --------------------------------------------------------------------------- #
# Orbit
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class Orbit:
    """Keplerian orbit and scan timing: the 8 "orbit and time" parameters.

    The elements are osculating Keplerian elements at the epoch ``t = 0``, in
    the ECI frame that coincides with ECEF at ``t = 0``.  Angles in radians.

    Attributes
    ----------
    semi_major_axis : float
        Semi-major axis ``a`` (m).
    eccentricity : float
        Eccentricity ``0 <= e < 1``.
    inclination : float
        Inclination ``i``.
    raan : float
        Right ascension of the ascending node ``Omega`` (in the ECI frame, i.e.
        the ECEF longitude of the node at ``t = 0``).
    arg_perigee : float
        Argument of perigee ``omega``.
    mean_anomaly0 : float
        Mean anomaly at ``t = 0``.
    line_time : float
        Seconds per scan line: the time of row ``r`` is ``t0 + r * line_time``.
    t0 : float
        Time of row 0 (s, relative to the epoch).
    """

    semi_major_axis: float
    eccentricity: float
    inclination: float
    raan: float
    arg_perigee: float
    mean_anomaly0: float
    line_time: float
    t0: float = 0.0

    def __post_init__(self) -> None:
        if not self.semi_major_axis > 0:
            raise ValueError("semi_major_axis must be > 0")
        if not 0.0 <= self.eccentricity < 1.0:
            raise ValueError("eccentricity must be in [0, 1)")
        if not self.line_time > 0:
            raise ValueError("line_time must be > 0")

    @property
    def mean_motion(self) -> float:
        """Mean motion ``n = sqrt(GM / a^3)`` (rad/s)."""
        return float(np.sqrt(GM_EARTH / self.semi_major_axis**3))

    def eccentric_anomaly(self, t: ArrayLike) -> np.ndarray:
        """Solve Kepler's equation ``E - e sin E = M0 + n t`` by Newton's method.

        Parameters
        ----------
        t : array_like
            Time since the epoch (s).

        Returns
        -------
        ndarray
            Eccentric anomaly (radians), same shape as ``t``.
        """
        e = self.eccentricity
        M = self.mean_anomaly0 + self.mean_motion * np.asarray(t, dtype=np.float64)
        M = np.remainder(M + np.pi, 2.0 * np.pi) - np.pi  # keep |M| <= pi for accuracy
        E = M + e * np.sin(M) if e < 0.8 else np.pi * np.sign(M) + 0.0 * M
        for _ in range(50):
            dE = (E - e * np.sin(E) - M) / (1.0 - e * np.cos(E))
            E = E - dE
            if np.all(np.abs(dE) < 1e-15):
                break
        return E

    def position_velocity(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Ideal inertial (ECI) position and velocity.

        Parameters
        ----------
        t : array_like
            Time since the epoch (s).

        Returns
        -------
        pos, vel : ndarray
            Shape ``t.shape + (3,)``; metres and metres per second.
        """
        a, e = self.semi_major_axis, self.eccentricity
        E = self.eccentric_anomaly(t)
        cE, sE = np.cos(E), np.sin(E)
        q = np.sqrt(1.0 - e * e)
        r = a * (1.0 - e * cE)
        # perifocal frame (P toward perigee, Q 90 deg ahead in the orbit plane)
        xp, yp = a * (cE - e), a * q * sE
        k = np.sqrt(GM_EARTH * a) / r
        vxp, vyp = -k * sE, k * q * cE
        R = _rot(2, self.raan) @ _rot(0, self.inclination) @ _rot(2, self.arg_perigee)
        P, Q = R[:, 0], R[:, 1]
        pos = xp[..., None] * P + yp[..., None] * Q
        vel = vxp[..., None] * P + vyp[..., None] * Q
        return pos, vel

    def position_velocity_ecef(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Ideal ECEF position and velocity (velocity relative to the rotating earth).

        Parameters
        ----------
        t : array_like
            Time since the epoch (s).

        Returns
        -------
        pos, vel : ndarray
            Shape ``t.shape + (3,)``.
        """
        t = np.asarray(t, dtype=np.float64)
        pos, vel = self.position_velocity(t)
        return _eci_to_ecef(pos, vel, t)

    @classmethod
    def circular_sun_synchronous(
        cls,
        *,
        altitude: float,
        lat0: float,
        lon0: float,
        line_time: float,
        descending: bool = True,
        inclination_deg: float | None = None,
        t0: float = 0.0,
    ) -> Orbit:
        """A circular near-polar orbit passing over a given point at ``t = 0``.

        Parameterisation: ``a = WGS84_A + altitude``, ``e = 0``,
        ``arg_perigee = 0`` (so ``mean_anomaly0`` is the argument of latitude
        ``u``).  At ``t = 0`` the satellite lies on the *geocentric* radius
        through the ground point ``(lat0, lon0, h=0)`` -- i.e. that point is
        the geocentric nadir, where the sensor's centre column looks -- on the
        descending (or ascending) pass: with geocentric latitude ``phi_c``,
        ``sin u = sin phi_c / sin i`` and ``raan = lambda - atan2(cos i sin u, cos u)``.

        Parameters
        ----------
        altitude : float
            Height of the circular orbit above the equatorial radius (m).
        lat0, lon0 : float
            Geodetic latitude and longitude (radians) of the point overflown at ``t = 0``.
        line_time : float
            Seconds per scan line.
        descending : bool
            Descending (north to south) pass at ``t = 0`` if true.
        inclination_deg : float, optional
            Inclination in degrees.  Default: the sun-synchronous inclination
            for this altitude from the J2 nodal precession
            ``cos i = -2 rate a^(7/2) / (3 J2 R^2 sqrt(GM))`` (98.2 deg at
            705 km, 99.1 deg at 917 km).  The propagation itself is purely
            Keplerian (no J2).
        t0 : float
            Time of row 0 (s).

        Returns
        -------
        Orbit
        """
        a = WGS84_A + float(altitude)
        if inclination_deg is None:
            cos_i = -2.0 * _SUN_RATE * a**3.5 / (3.0 * J2_EARTH * WGS84_A**2 * np.sqrt(GM_EARTH))
            inc = float(np.arccos(cos_i))
        else:
            inc = float(np.deg2rad(inclination_deg))
        X, Y, Z = geodetic_to_ecef(lat0, lon0, 0.0)
        phi_c = float(np.arctan2(Z, np.hypot(X, Y)))
        lam = float(np.arctan2(Y, X))
        s = np.sin(phi_c) / np.sin(inc)
        if abs(s) > 1.0:
            raise ValueError("latitude not reachable with this inclination")
        u = float(np.arcsin(s))
        if descending:
            u = np.pi - u
        raan = lam - float(np.arctan2(np.cos(inc) * np.sin(u), np.cos(u)))
        return cls(
            semi_major_axis=a,
            eccentricity=0.0,
            inclination=inc,
            raan=float(np.remainder(raan, 2 * np.pi)),
            arg_perigee=0.0,
            mean_anomaly0=float(u),
            line_time=float(line_time),
            t0=float(t0),
        )


# --------------------------------------------------------------------------- #
# Line scanner
# --------------------------------------------------------------------------- #
@dataclass(frozen=True, eq=False)
class LineScanner:
    """A pushbroom or whiskbroom line scanner on a Keplerian orbit.

    See the module docstring for the frames.  Points are vectorised: all
    methods take broadcastable arrays and return arrays of the broadcast shape.

    Attributes
    ----------
    orbit : Orbit
        Ideal orbit and timing.
    rows, cols : int
        Frame size.
    ifov : float
        Angular step between columns (radians per pixel, across track).
    kind : {"pushbroom", "whiskbroom"}
        ``"pushbroom"``: all columns of a row are imaged at the same time.
        ``"whiskbroom"``: a scanning mirror; column ``c`` is imaged
        ``c * col_time`` after the start of its row.
    col_time : float
        Seconds per column (whiskbroom only).
    deviations : ndarray, shape (6, 4)
        Cubic-in-time coefficients ``(c0, c1, c2, c3)`` of the along-track,
        cross-track and radial (outward) position deviation (m) and of the
        roll, pitch, yaw attitude deviation (rad).  Zeros = ideal.
    """

    orbit: Orbit
    rows: int
    cols: int
    ifov: float
    kind: str = "pushbroom"
    col_time: float = 0.0
    deviations: np.ndarray = field(default_factory=lambda: np.zeros((6, 4)))

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"kind must be one of {_KINDS}, got {self.kind!r}")
        if self.rows < 1 or self.cols < 1 or not self.ifov > 0:
            raise ValueError("rows, cols must be >= 1 and ifov > 0")
        dev = np.array(self.deviations, dtype=np.float64, copy=True)
        if dev.shape != (6, 4):
            raise ValueError(f"deviations must have shape (6, 4), got {dev.shape}")
        dev.setflags(write=False)
        object.__setattr__(self, "deviations", dev)

    # ---------------------------------------------------------------- time
    @property
    def centre_col(self) -> float:
        """Column of the nominal nadir look, ``(cols - 1) / 2``."""
        return (self.cols - 1) / 2.0

    def time(self, row: ArrayLike, col: ArrayLike = 0.0) -> np.ndarray:
        """Acquisition time of image points.

        Parameters
        ----------
        row, col : array_like
            Row (``y``) and column (``x``) coordinates; broadcast together.

        Returns
        -------
        ndarray
            ``t0 + row * line_time`` (+ ``col * col_time`` for a whiskbroom), seconds.
        """
        row, col = np.broadcast_arrays(np.asarray(row, dtype=np.float64), np.asarray(col, dtype=np.float64))
        t = self.orbit.t0 + row * self.orbit.line_time
        if self.kind == "whiskbroom":
            t = t + col * self.col_time
        return t

    # ---------------------------------------------------------- exterior
    def deviation_values(self, t: ArrayLike) -> np.ndarray:
        """The six deviations ``(dA, dC, dR, roll, pitch, yaw)`` at time ``t``, shape ``t.shape + (6,)``."""
        t = np.asarray(t, dtype=np.float64)
        powers = np.stack([np.ones_like(t), t, t * t, t * t * t], axis=-1)
        return powers @ self.deviations.T

    def exterior(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Sensor position and orientation in ECEF at time ``t``.

        Parameters
        ----------
        t : array_like
            Time since the epoch (s).

        Returns
        -------
        S : ndarray, shape ``t.shape + (3,)``
            Actual sensor position (ideal orbit + deviation), ECEF metres.
        R : ndarray, shape ``t.shape + (3, 3)``
            Columns are the sensor x, y, z axes in ECEF; ``M = R^T`` of eq. (1).
        """
        t = np.asarray(t, dtype=np.float64)
        r, v = self.orbit.position_velocity_ecef(t)
        z_o = -_unit(r)
        y_o = _unit(np.cross(z_o, v))
        x_o = np.cross(y_o, z_o)
        B = np.stack([x_o, y_o, z_o], axis=-1)
        d = self.deviation_values(t)
        S = r + d[..., 0:1] * x_o + d[..., 1:2] * y_o - d[..., 2:3] * z_o
        A = _rot(2, d[..., 5]) @ _rot(1, d[..., 4]) @ _rot(0, d[..., 3])
        return S, B @ A

    def look_angle(self, col: ArrayLike) -> np.ndarray:
        """Cross-track look angle ``psi = (col - (cols - 1) / 2) * ifov`` (radians)."""
        return (np.asarray(col, dtype=np.float64) - self.centre_col) * self.ifov

    # ---------------------------------------------------------- inverse
    def image_to_ground(
        self,
        row: ArrayLike,
        col: ArrayLike,
        *,
        terrain: Callable[[np.ndarray, np.ndarray], Any] | None = None,
        height: ArrayLike = 0.0,
        tol: float = 1e-6,
        max_iter: int = 100,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse mode: intersect the look ray of image points with the terrain.

        The ray is first intersected with the ellipsoid whose semi-axes are
        raised by the target height; the ray parameter is then refined by
        ``s <- s + (h_target - h(s)) / (n . u)`` (``n`` the geodetic normal,
        ``u`` the unit look vector), re-evaluating ``h_target = terrain(lat, lon)``
        at the current intersection, until the step is below ``tol`` metres.

        Parameters
        ----------
        row, col : array_like
            Image coordinates (``y``, ``x``); broadcast together.
        terrain : callable, optional
            ``terrain(lat, lon) -> h`` (radians in, metres out), vectorised.
            Takes precedence over ``height``.
        height : array_like
            Constant (or per-point) ellipsoidal height (m) used without ``terrain``.
        tol : float
            Convergence tolerance on the ray step (m).
        max_iter : int
            Maximum number of refinement steps.

        Returns
        -------
        X, Y, Z : ndarray
            ECEF coordinates (m); NaN where the ray misses or did not converge.
        """
        row, col = np.broadcast_arrays(np.asarray(row, dtype=np.float64), np.asarray(col, dtype=np.float64))
        shape = row.shape
        t = self.time(row, col).ravel()
        psi = self.look_angle(col).ravel()
        S, R = self.exterior(t)
        u_s = np.stack([np.zeros_like(psi), np.sin(psi), np.cos(psi)], axis=-1)
        u = np.einsum("nij,nj->ni", R, u_s)

        if terrain is None:
            h_t = np.broadcast_to(np.asarray(height, dtype=np.float64), shape).ravel().copy()
        else:
            # start from the ellipsoid, then follow the terrain
            h_t = np.zeros(t.shape)
        # intersection with the ellipsoid (a + h, a + h, b + h)
        ax = (WGS84_A + h_t)[:, None]
        scale = np.concatenate([ax, ax, (WGS84_B + h_t)[:, None]], axis=1)
        Ps, us = S / scale, u / scale
        qa = np.sum(us * us, axis=1)
        qb = 2.0 * np.sum(Ps * us, axis=1)
        qc = np.sum(Ps * Ps, axis=1) - 1.0
        disc = qb * qb - 4.0 * qa * qc
        with np.errstate(invalid="ignore"):
            s = (-qb - np.sqrt(disc)) / (2.0 * qa)
        ok = np.isfinite(s) & (s > 0)
        s = np.where(ok, s, np.nan)

        converged = np.zeros(t.shape, dtype=bool)
        for _ in range(max_iter):
            P = S + s[:, None] * u
            lat, lon, h = ecef_to_geodetic(P[:, 0], P[:, 1], P[:, 2])
            if terrain is not None:
                h_t = np.broadcast_to(np.asarray(terrain(lat, lon), dtype=np.float64), lat.shape)
            dh_ds = np.sum(_up(lat, lon) * u, axis=1)
            ds = (h_t - h) / dh_ds
            s = s + ds
            converged = np.abs(ds) < tol
            if np.all(converged | ~ok):
                break
        s = np.where(ok & converged, s, np.nan)
        P = S + s[:, None] * u
        return tuple(P[:, k].reshape(shape) for k in range(3))  # type: ignore[return-value]

    # ----------------------------------------------------------- direct
    def _sensor_vector(self, t: np.ndarray, P: np.ndarray) -> np.ndarray:
        S, R = self.exterior(t)
        return np.einsum("nji,nj->ni", R, P - S)  # M (P - S), M = R^T

    def ground_to_image(
        self,
        X: ArrayLike,
        Y: ArrayLike,
        Z: ArrayLike,
        *,
        tol: float = 1e-8,
        max_iter: int = 50,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Direct mode: image coordinates of ECEF ground points.

        The acquisition time is found by Newton's method on
        ``f(t) = x_s(t) / z_s(t)`` (the along-track collinearity ratio of the
        sensor-frame vector ``M(t) (P - S(t))``, which must vanish: the look
        vectors lie in the sensor's y-z plane), with a central-difference
        derivative, starting at the frame-centre time.  The column then
        follows from the cross-track angle ``atan2(y_s, z_s) / ifov``, and the
        row from ``t = t0 + row * line_time (+ col * col_time)``.  Because the
        column is determined by the geometry at ``t``, this also solves the
        whiskbroom case (row and column jointly) without an outer iteration.

        Parameters
        ----------
        X, Y, Z : array_like
            ECEF coordinates (m); broadcast together.
        tol : float
            Convergence tolerance on the Newton step, in rows (the
            floating-point noise floor of the step is ~1e-10 rows).
        max_iter : int
            Maximum number of Newton steps.

        Returns
        -------
        row, col : ndarray
            Image coordinates (``y``, ``x``); NaN for points behind the sensor
            or where the iteration did not converge.
        """
        X, Y, Z = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (X, Y, Z)))
        shape = X.shape
        P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=-1)
        lt = self.orbit.line_time
        t_c = float(self.time((self.rows - 1) / 2.0, self.centre_col))
        t = np.full(P.shape[0], t_c)
        dt = 10.0 * lt

        def f(tt: np.ndarray) -> np.ndarray:
            v = self._sensor_vector(tt, P)
            return v[:, 0] / v[:, 2]

        converged = np.zeros(t.shape, dtype=bool)
        for _ in range(max_iter):
            fp = (f(t + dt) - f(t - dt)) / (2.0 * dt)
            step = f(t) / fp
            # limit a step to 10 % of an orbital period (robustness far from the frame)
            lim = 0.1 * 2 * np.pi / self.orbit.mean_motion
            step = np.clip(step, -lim, lim)
            t = t - step
            converged = np.abs(step) < tol * lt
            if np.all(converged | ~np.isfinite(step)):
                break
        v = self._sensor_vector(t, P)
        col = self.centre_col + np.arctan2(v[:, 1], v[:, 2]) / self.ifov
        tr = t - self.orbit.t0
        if self.kind == "whiskbroom":
            tr = tr - col * self.col_time
        row = tr / lt
        bad = ~converged | (v[:, 2] <= 0)
        row = np.where(bad, np.nan, row)
        col = np.where(bad, np.nan, col)
        return row.reshape(shape), col.reshape(shape)

    # ------------------------------------------------------- parameters
    def parameters(self) -> np.ndarray:
        """The 8 + 24 = 32 parameter vector.

        Returns
        -------
        ndarray, shape (32,)
            ``(a, e, i, raan, arg_perigee, mean_anomaly0, line_time, t0)``
            followed by ``deviations.ravel()`` (row-major: the 4 coefficients
            of dA, then dC, dR, roll, pitch, yaw).
        """
        o = self.orbit
        head = [
            o.semi_major_axis,
            o.eccentricity,
            o.inclination,
            o.raan,
            o.arg_perigee,
            o.mean_anomaly0,
            o.line_time,
            o.t0,
        ]
        return np.concatenate([np.asarray(head, dtype=np.float64), self.deviations.ravel()])

    @classmethod
    def from_parameters(
        cls,
        p: ArrayLike,
        *,
        rows: int,
        cols: int,
        ifov: float,
        kind: str = "pushbroom",
        col_time: float = 0.0,
    ) -> LineScanner:
        """Rebuild a scanner from :meth:`parameters` plus the internal geometry.

        Parameters
        ----------
        p : array_like, shape (32,)
            Parameter vector as returned by :meth:`parameters`.
        rows, cols : int
            Frame size.
        ifov : float
            Radians per column.
        kind : {"pushbroom", "whiskbroom"}
            Scanner type.
        col_time : float
            Seconds per column (whiskbroom).

        Returns
        -------
        LineScanner
        """
        p = np.asarray(p, dtype=np.float64)
        if p.shape != (32,):
            raise ValueError(f"p must have shape (32,), got {p.shape}")
        orbit = Orbit(*(float(v) for v in p[:8]))
        return cls(
            orbit=orbit, rows=rows, cols=cols, ifov=ifov, kind=kind, col_time=col_time, deviations=p[8:].reshape(6, 4)
        )

    def replace(self, **changes: Any) -> LineScanner:
        """A copy with some fields changed (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------- #
# LANDSAT MSS-like frame
# --------------------------------------------------------------------------- #
def _nadir_ground_speed(orbit: Orbit, t: float = 0.0) -> float:
    """Speed (m/s, ECEF) of the geocentric nadir point over the ellipsoid at time ``t``."""
    r, v = orbit.position_velocity_ecef(np.float64(t))
    rn = float(np.linalg.norm(r))
    rhat = r / rn
    v_h = v - np.dot(v, rhat) * rhat
    # ellipsoid radius along rhat
    rg = 1.0 / np.sqrt((rhat[0] ** 2 + rhat[1] ** 2) / WGS84_A**2 + rhat[2] ** 2 / WGS84_B**2)
    return float(np.linalg.norm(v_h) * rg / rn)


def landsat_mss_like(
    *,
    lat0: float = 39.0,
    lon0: float = -98.0,
    rows: int = 2340,
    cols: int = 3240,
    seed: int | None = None,
    kind: str = "pushbroom",
    altitude: float = 917e3,
    swath: float = 185e3,
    line_spacing: float = 79.0,
    descending: bool = True,
    position_sigma: float = 15.0,
    attitude_sigma: float = 5e-5,
) -> LineScanner:
    """A LANDSAT-MSS-like frame (default: centred on Kansas).

    LANDSAT 1-3 flew at ~917 km in a sun-synchronous orbit (99.1 deg).  An
    MSS frame has 2340 lines of 79 m (the along-track IFOV footprint) and
    3240 samples per line over a 185 km swath, i.e. the cross-track sample
    step is ~57 m (the 79 m IFOV was oversampled).  Here ``ifov`` is the
    angular *sample step*, ``2 atan(swath / 2 / altitude) / cols``, so the
    frame covers the swath, and ``line_time = line_spacing / ground speed``
    of the nadir point at the frame centre (~12.2 ms).  The frame centre
    (row ``(rows-1)/2``, column ``(cols-1)/2``) is acquired at ``t = 0``, when
    the satellite is above ``(lat0, lon0)`` (degrees).

    The real MSS is a whiskbroom: an oscillating mirror sweeps 6 lines per
    73.4 ms cycle with 6 detectors per band, the active sweep lasting ~45 %
    of the cycle.  ``kind="whiskbroom"`` models one detector's sweep per row:
    ``col_time = 0.45 * 6 * line_time / cols`` (~ 10 us), so a row is skewed
    by ~2.7 lines across the swath.  The 6-detector interleave is not modelled.

    Parameters
    ----------
    lat0, lon0 : float
        Geodetic latitude and longitude of the frame centre (degrees).
    rows, cols : int
        Frame size.
    seed : int, optional
        With a seed, random cubic deviations are drawn
        (``numpy.random.default_rng(seed)``): coefficient ``k`` of each
        position component has standard deviation ``position_sigma / T^k`` and
        of each attitude component ``attitude_sigma / T^k``, with ``T`` half the
        frame duration, i.e. tens of metres and ~1e-4 rad over the frame.
        Without a seed the deviations are zero.
    kind : {"pushbroom", "whiskbroom"}
        Scanner type.
    altitude : float
        Orbit altitude above the equatorial radius (m).
    swath : float
        Nominal swath width (m).
    line_spacing : float
        Along-track ground distance between lines at the frame centre (m).
    descending : bool
        Descending pass (LANDSAT's daytime pass) if true.
    position_sigma, attitude_sigma : float
        Scales of the random deviations (m, rad).

    Returns
    -------
    LineScanner
    """
    lat0r, lon0r = np.deg2rad(lat0), np.deg2rad(lon0)
    orbit = Orbit.circular_sun_synchronous(
        altitude=altitude, lat0=lat0r, lon0=lon0r, descending=descending, line_time=1.0
    )
    line_time = line_spacing / _nadir_ground_speed(orbit, 0.0)
    col_time = 0.45 * 6.0 * line_time / cols if kind == "whiskbroom" else 0.0
    t0 = -((rows - 1) / 2.0 * line_time + (cols - 1) / 2.0 * col_time)
    orbit = dataclasses.replace(orbit, line_time=line_time, t0=t0)
    ifov = 2.0 * np.arctan(swath / 2.0 / altitude) / cols
    deviations = np.zeros((6, 4))
    if seed is not None:
        rng = np.random.default_rng(seed)
        half = max(rows * line_time / 2.0, 1e-3)
        k = np.arange(4)
        sig = np.concatenate([np.full(3, position_sigma), np.full(3, attitude_sigma)])
        deviations = rng.standard_normal((6, 4)) * sig[:, None] / half ** k[None, :]
    return LineScanner(
        orbit=orbit, rows=rows, cols=cols, ifov=float(ifov), kind=kind, col_time=col_time, deviations=deviations
    )
