"""Classic 2-D rectification: polynomials from a local tangent plane (or map plane) to the image.

:class:`Polynomial2D` projects ECEF ground points onto the tangent plane at an origin (east,
north; the height is ignored -- the relief displacement is the model's systematic error) and
maps them to the image by polynomials of order 1..3; :class:`MapPolynomial` does the same from
map coordinates in a projected CRS (the mosaic's per-scene model).  Analytic Jacobians;
follows :class:`~geocoder.adjust.sensor.SensorModel`.  Pure numpy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ...geodesy import enu_basis, geodetic_to_ecef
from ..sensor import as_ground, as_params

__all__ = ["MapPolynomial", "Polynomial2D"]


class Polynomial2D:
    """2-D polynomial rectification in a local tangent plane.

    Ground ECEF points ``P`` are projected onto the tangent plane at the
    origin ``O`` (geodetic, height 0): ``east = e . (P - O)``,
    ``north = n . (P - O)`` with ``e``, ``n`` the unit east/north vectors at
    ``O``.  The up component (terrain height) is ignored -- the classic 2-D
    rectification, whose relief displacement is a systematic error.  With
    ``u = east / scale``, ``v = north / scale``::

        x = sum_k a_k u^i_k v^j_k,    y = sum_k b_k u^i_k v^j_k

    over all monomials with ``i + j <= order``, ordered by total degree then
    decreasing power of ``u``: ``1, u, v, u^2, u v, v^2, u^3, u^2 v, u v^2, v^3``.
    The parameter vector is ``(a_0 .. a_{K-1}, b_0 .. b_{K-1})``.

    Parameters
    ----------
    order : int
        Polynomial order, 1 (affine), 2 or 3.
    origin_lat, origin_lon : float
        Geodetic latitude and longitude of the tangent point (degrees).
    scale : float
        Normalisation of the plane coordinates (m).

    Attributes
    ----------
    n_params : int
        ``2 K`` with ``K = (order + 1)(order + 2) / 2`` monomials.
    exponents : ndarray, shape (K, 2)
        ``(i, j)`` of each monomial.
    param_steps : ndarray, shape (n_params,)
        Central-difference steps (pixels per unit monomial; for checks only,
        the Jacobians are analytic).
    ground_step : float
        Central-difference ground step (m; for checks only).
    """

    def __init__(self, order: int, origin_lat: float, origin_lon: float, scale: float = 1e5) -> None:
        if order not in (1, 2, 3):
            raise ValueError(f"order must be 1, 2 or 3, got {order}")
        if not scale > 0:
            raise ValueError("scale must be > 0")
        self.order = int(order)
        self.origin_lat = float(origin_lat)
        self.origin_lon = float(origin_lon)
        self.scale = float(scale)
        self.exponents = np.array([(d - j, j) for d in range(order + 1) for j in range(d + 1)], dtype=np.int64)
        self.n_monomials = len(self.exponents)
        self.n_params = 2 * self.n_monomials
        self.origin = np.array(
            geodetic_to_ecef(np.deg2rad(self.origin_lat), np.deg2rad(self.origin_lon), 0.0), dtype=np.float64
        )
        self._enu = enu_basis(self.origin_lat, self.origin_lon)
        self.param_steps = np.full(self.n_params, 1e-3)
        self.ground_step = 1.0

    def __repr__(self) -> str:
        return (
            f"Polynomial2D(order={self.order}, origin_lat={self.origin_lat}, "
            f"origin_lon={self.origin_lon}, scale={self.scale})"
        )

    def plane(self, ground: ArrayLike) -> np.ndarray:
        """Normalised tangent-plane coordinates of ECEF points.

        Parameters
        ----------
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(u, v)``: east and north of the origin on its tangent plane, divided by ``scale``.
        """
        g = as_ground(ground)
        return (g - self.origin) @ self._enu[:2].T / self.scale

    def monomials(self, uv: np.ndarray) -> np.ndarray:
        """Monomial values ``u^i v^j`` for the exponents ``(i, j)`` of the model.

        Parameters
        ----------
        uv : ndarray, shape (m, 2)
            Plane coordinates from :meth:`plane`.

        Returns
        -------
        ndarray, shape (m, K)
            One column per row of ``exponents`` (``K = n_monomials``).
        """
        u, v = uv[:, 0:1], uv[:, 1:2]
        i, j = self.exponents[:, 0], self.exponents[:, 1]
        return u**i * v**j

    def _monomial_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = uv[:, 0:1], uv[:, 1:2]
        i, j = self.exponents[:, 0], self.exponents[:, 1]
        du = i * u ** np.maximum(i - 1, 0) * v**j
        dv = j * u**i * v ** np.maximum(j - 1, 0)
        return du, dv

    def project(self, params: ArrayLike, ground: ArrayLike) -> np.ndarray:
        """Image coordinates of ECEF ground points.

        Parameters
        ----------
        params : array_like, shape (n_params,)
            ``(a_0 .. a_{K-1}, b_0 .. b_{K-1})``.
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x, y)``.
        """
        p = as_params(params, self.n_params)
        mono = self.monomials(self.plane(ground))
        return mono @ p.reshape(2, self.n_monomials).T

    def jacobians(self, params: ArrayLike, ground: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Analytic Jacobians.

        Parameters
        ----------
        params : array_like, shape (n_params,)
            Parameter vector.
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        J_params : ndarray, shape (m, 2, n_params)
            ``d(x, y) / d params``: monomials in the ``a`` (x) and ``b`` (y) blocks.
        J_ground : ndarray, shape (m, 2, 3)
            ``d(x, y) / d(X, Y, Z)`` by the chain rule
            ``d/dP = (d/du) e / scale + (d/dv) n / scale``.
        """
        p = as_params(params, self.n_params).reshape(2, self.n_monomials)
        uv = self.plane(ground)
        m, k = uv.shape[0], self.n_monomials
        mono = self.monomials(uv)
        Jp = np.zeros((m, 2, self.n_params))
        Jp[:, 0, :k] = mono
        Jp[:, 1, k:] = mono
        du, dv = self._monomial_derivatives(uv)
        d_uv = np.stack([du @ p.T, dv @ p.T], axis=-1)  # (m, 2 image, 2 plane)
        Jg = d_uv @ (self._enu[:2] / self.scale)  # (m, 2, 3)
        return Jp, Jg

    def initial_params(self) -> np.ndarray:
        """Zeros (use :meth:`fit` for a real start).

        Returns
        -------
        ndarray, shape (n_params,)
            All zero.
        """
        return np.zeros(self.n_params)

    def fit(self, ground: ArrayLike, xy: ArrayLike, weights: ArrayLike | None = None) -> np.ndarray:
        """Direct linear least-squares fit of the coefficients.

        Parameters
        ----------
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).
        xy : array_like, shape (m, 2)
            Observed image coordinates ``(x, y)``.
        weights : array_like, shape (m,), optional
            Non-negative weights of the squared residuals (e.g. ``1 / sigma^2``).

        Returns
        -------
        ndarray, shape (n_params,)
            Parameter vector minimising ``sum w |project - xy|^2``.
        """
        mono = self.monomials(self.plane(ground))
        xy = np.asarray(xy, dtype=np.float64)
        if xy.shape != (mono.shape[0], 2):
            raise ValueError(f"xy must have shape ({mono.shape[0]}, 2), got {xy.shape}")
        if weights is not None:
            sw = np.sqrt(np.asarray(weights, dtype=np.float64))
            mono, xy = mono * sw[:, None], xy * sw[:, None]
        if np.count_nonzero(np.any(mono != 0, axis=1)) < self.n_monomials:
            raise ValueError(f"need at least {self.n_monomials} (weighted) points for order {self.order}")
        coef, *_ = np.linalg.lstsq(mono, xy, rcond=None)
        return coef.T.ravel()


class MapPolynomial(Polynomial2D):
    """2-D polynomial of map coordinates in a projected CRS: the mosaic's per-scene model.

    Ground points are ``(E, N, h)`` in the mosaic's CRS (metres), not ECEF; the height is
    ignored as in :class:`Polynomial2D`, ``u = (E - E0) / scale``, ``v = (N - N0) / scale``.

    Parameters
    ----------
    order : int
        1 (affine), 2 or 3.
    origin : (float, float)
        ``(E0, N0)``, e.g. the scene's centre.
    scale : float
        Normalisation of the plane coordinates (m), e.g. half the scene's extent.
    """

    def __init__(self, order: int, origin: tuple[float, float], scale: float) -> None:
        super().__init__(order, 0.0, 0.0, scale)
        self.origin = np.array([float(origin[0]), float(origin[1]), 0.0])
        self._enu = np.eye(3)

    def __repr__(self) -> str:
        return f"MapPolynomial(order={self.order}, origin=({self.origin[0]}, {self.origin[1]}), scale={self.scale})"
