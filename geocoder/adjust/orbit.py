"""Keplerian orbit and scan timing of a satellite line scanner: the 8 "orbit and time" parameters.

Paderes, Mikhail & Foerstner (1984), sec. 2.1: the ideal satellite position ``(Xs, Ys, Zs)(t)``
of the collinearity equations (1) follows a Keplerian orbit; deviations from it are modelled by
:class:`geocoder.adjust.linescanner_geometry.LineScanner`.  The elements are osculating at the
epoch ``t = 0`` in the inertial frame that coincides with ECEF at ``t = 0``
(:func:`geocoder.geodesy.eci_to_ecef`).  Pure numpy; no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ..geodesy import GM_EARTH, J2_EARTH, WGS84_A, eci_to_ecef, geodetic_to_ecef, rotation

__all__ = ["Orbit"]

#: Mean motion of the sun in right ascension (rad/s): 2 pi per tropical year.
_SUN_RATE = 2.0 * np.pi / (365.2421897 * 86400.0)


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
        R = rotation(2, self.raan) @ rotation(0, self.inclination) @ rotation(2, self.arg_perigee)
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
        return eci_to_ecef(pos, vel, t)

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
