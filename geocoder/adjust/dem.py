"""A gridded DEM as a height constraint of ground points (seed 000 sec. 2.5).

Tie points over relief are held to the terrain: the pseudo-observation of a point ``P`` (ECEF)
is ``c(P) = h(P) - H(lat(P), lon(P)) = 0`` with standard deviation ``sigma``, where ``h`` is the
ellipsoidal height and ``H`` the DEM's bilinear height.  Its gradient ``dc/dP`` includes the
DEM's slope::

    dc/dP = up - (dH/dlat) north / (M + h) - (dH/dlon) east / ((N + h) cos lat)

with ``up``, ``north``, ``east`` the local unit vectors and ``M``, ``N`` the meridian and prime
vertical radii of curvature of the WGS84 ellipsoid.  :func:`geocoder.adjust.solver.adjust`
re-linearises the constraint at every iteration (``Problem.dem``, ``Problem.dem_points``).

Pure numpy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ..geodesy import WGS84_A, WGS84_E2, ecef_to_geodetic

__all__ = ["DEM"]


@dataclass(frozen=True, eq=False)
class DEM:
    """Ellipsoidal heights on a regular latitude/longitude grid, with their accuracy.

    Attributes
    ----------
    heights : ndarray, shape (ny, nx)
        Height (m above the WGS84 ellipsoid) at node ``(i, j)``, latitude ``lat0 + i dlat``,
        longitude ``lon0 + j dlon``.
    lat0, lon0 : float
        Latitude and longitude of node ``(0, 0)`` (degrees).
    dlat, dlon : float
        Node spacing (degrees, > 0).
    sigma : float
        Standard deviation of a DEM height (m): the weight of the constraint is ``1 / sigma^2``.
    """

    heights: np.ndarray
    lat0: float
    lon0: float
    dlat: float
    dlon: float
    sigma: float

    def __post_init__(self) -> None:
        h = np.array(self.heights, dtype=np.float64, copy=True)
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError(f"heights must be a 2-D grid of at least 2 x 2 nodes, got {h.shape}")
        if not (self.dlat > 0 and self.dlon > 0 and self.sigma > 0):
            raise ValueError("dlat, dlon and sigma must be > 0")
        h.setflags(write=False)
        object.__setattr__(self, "heights", h)

    @classmethod
    def from_function(
        cls,
        terrain: Callable[[np.ndarray, np.ndarray], ArrayLike],
        lat_range: tuple[float, float],
        lon_range: tuple[float, float],
        spacing: float,
        sigma: float,
    ) -> DEM:
        """Sample a terrain function on a grid.

        Parameters
        ----------
        terrain : callable
            ``terrain(lat, lon) -> h`` (radians in, metres out), as the simulator's terrains.
        lat_range, lon_range : tuple of float
            Extent (degrees); the grid covers it with nodes ``spacing`` apart.
        spacing : float
            Node spacing (degrees).
        sigma : float
            Standard deviation of the heights (m).

        Returns
        -------
        DEM
        """
        ny = int(np.ceil((lat_range[1] - lat_range[0]) / spacing)) + 1
        nx = int(np.ceil((lon_range[1] - lon_range[0]) / spacing)) + 1
        lat = lat_range[0] + spacing * np.arange(ny)
        lon = lon_range[0] + spacing * np.arange(nx)
        la, lo = np.meshgrid(np.deg2rad(lat), np.deg2rad(lon), indexing="ij")
        h = np.broadcast_to(np.asarray(terrain(la, lo), dtype=np.float64), la.shape)
        return cls(h, float(lat_range[0]), float(lon_range[0]), float(spacing), float(spacing), float(sigma))

    def height(self, lat: ArrayLike, lon: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear height and its slopes.

        Parameters
        ----------
        lat, lon : array_like
            Latitude and longitude (degrees); broadcast together.

        Returns
        -------
        h : ndarray
            Height (m); NaN outside the grid.
        dh_dlat, dh_dlon : ndarray
            Derivatives of the bilinear surface (m per degree); NaN outside the grid.
        """
        lat, lon = np.broadcast_arrays(np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64))
        ny, nx = self.heights.shape
        u = (lat - self.lat0) / self.dlat
        v = (lon - self.lon0) / self.dlon
        inside = (u >= 0) & (u <= ny - 1) & (v >= 0) & (v <= nx - 1)
        i = np.clip(np.floor(np.where(inside, u, 0.0)).astype(np.int64), 0, ny - 2)
        j = np.clip(np.floor(np.where(inside, v, 0.0)).astype(np.int64), 0, nx - 2)
        fu, fv = np.where(inside, u - i, 0.0), np.where(inside, v - j, 0.0)
        g = self.heights
        h00, h01, h10, h11 = g[i, j], g[i, j + 1], g[i + 1, j], g[i + 1, j + 1]
        h = (1 - fu) * ((1 - fv) * h00 + fv * h01) + fu * ((1 - fv) * h10 + fv * h11)
        du = ((1 - fv) * (h10 - h00) + fv * (h11 - h01)) / self.dlat
        dv = ((1 - fu) * (h01 - h00) + fu * (h11 - h10)) / self.dlon
        nan = np.where(inside, 1.0, np.nan)
        return h * nan, du * nan, dv * nan

    def constraint(self, ground: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Misclosure and gradient of the height constraint at ECEF points.

        Parameters
        ----------
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        c : ndarray, shape (m,)
            ``h(P) - H(lat, lon)`` (m); NaN outside the grid.
        grad : ndarray, shape (m, 3)
            ``dc / dP`` (see the module docstring); NaN outside the grid.
        """
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        lat, lon, h = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
        H, dH_dlat, dH_dlon = self.height(np.rad2deg(lat), np.rad2deg(lon))
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        w = np.sqrt(1.0 - WGS84_E2 * sl * sl)
        n_rad = WGS84_A / w
        m_rad = WGS84_A * (1.0 - WGS84_E2) / w**3
        up = np.stack([cl * co, cl * so, sl], axis=-1)
        north = np.stack([-sl * co, -sl * so, cl], axis=-1)
        east = np.stack([-so, co, np.zeros_like(co)], axis=-1)
        dlat_dP = north / (m_rad + h)[:, None]  # radians per metre
        dlon_dP = east / ((n_rad + h) * cl)[:, None]
        per_rad = 180.0 / np.pi
        grad = up - (dH_dlat * per_rad)[:, None] * dlat_dP - (dH_dlon * per_rad)[:, None] * dlon_dP
        return h - H, grad
