"""LANDSAT-MSS-like satellite frames for the simulator, on the rigorous line-scanner geometry.

The geometry itself -- a pushbroom or whiskbroom scanner on a Keplerian orbit over a rotating
WGS84 earth (Paderes, Mikhail & Foerstner (1984), sec. 2.1, eq. (1)) -- is the block
adjustment's sensor: :class:`~geocoder.adjust.linescanner_geometry.LineScanner` and
:class:`~geocoder.adjust.orbit.Orbit`, with the ellipsoid in :mod:`geocoder.geodesy`.  This
module makes frames of it with known truth (:func:`landsat_mss_like`) and re-exports those
names so that ``from geocoder.simulate.satellite import LineScanner, geodetic_to_ecef`` keeps
working.  Pure numpy; no file I/O.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..adjust.linescanner_geometry import LineScanner
from ..adjust.orbit import Orbit
from ..geodesy import (
    GM_EARTH,
    J2_EARTH,
    OMEGA_EARTH,
    WGS84_A,
    WGS84_B,
    WGS84_E2,
    WGS84_F,
    ecef_to_geodetic,
    geodetic_to_ecef,
)

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
