"""Sensor models for block adjustment: 2-D polynomials, a rigorous line scanner, RPCs.

Every model maps ECEF ground coordinates (metres, shape ``(m, 3)``) to image
coordinates ``(x = column, y = row)`` (shape ``(m, 2)``; pixel centres at
integers, see ``CONVENTIONS.md``) through a parameter vector, and follows the
:class:`SensorModel` protocol consumed by the solver:

* ``n_params`` -- length of the parameter vector;
* ``project(params, ground) -> (m, 2)``;
* ``jacobians(params, ground) -> (d image / d params (m, 2, n_params),
  d image / d ground (m, 2, 3))``;
* ``initial_params() -> (n_params,)``.

Each model also carries ``param_steps`` (central-difference step per
parameter; a natural scale for each parameter that moves the image by roughly
0.01 px) and ``ground_step`` (metres).  Models without analytic Jacobians use
the private :func:`_central_difference` helper, vectorised over points and
looping only over the parameters and the three ground coordinates.  The line
scanner's Jacobians are exact (forward-mode jets and implicit differentiation
at the solved acquisition time, :mod:`geocoder.adjust.linescanner_jacobian`).

Models
------
:class:`Polynomial2D`
    Classic 2-D rectification: ground -> local tangent plane (east, north) at
    an origin, height ignored -> image by polynomials of order 1..3.
:class:`LineScannerModel`
    Wraps :class:`geocoder.simulate.satellite.LineScanner` (8 orbit/time + 24
    position/attitude deviation parameters), all or a subset free.
:class:`RPCModel`
    An :class:`RPC` (RPC00B rational polynomial coefficients) with an affine
    bias compensation in image space (6 parameters).

Pure numpy; no file I/O (``rasterio`` is imported lazily only by the
:class:`RPC` conversions).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from geocoder.simulate.satellite import LineScanner, ecef_to_geodetic, geodetic_to_ecef

from .linescanner_jacobian import line_scanner_jacobians
from .linescanner_projection import project_with_times

__all__ = [
    "RPC",
    "LineScannerModel",
    "Polynomial2D",
    "RPCModel",
    "SensorModel",
    "fit_rpc",
    "rpc_terms",
]


# --------------------------------------------------------------------------- #
# Protocol and helpers
# --------------------------------------------------------------------------- #
@runtime_checkable
class SensorModel(Protocol):
    """What the block-adjustment solver needs from a sensor model.

    Attributes
    ----------
    n_params : int
        Length of the parameter vector.
    """

    n_params: int

    def project(self, params: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Image coordinates of ECEF ground points.

        Parameters
        ----------
        params : ndarray, shape (n_params,)
            Parameter vector.
        ground : ndarray, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x, y)``.
        """
        ...

    def jacobians(self, params: np.ndarray, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of :meth:`project` with respect to the parameters and the ground points.

        Parameters
        ----------
        params : ndarray, shape (n_params,)
            Parameter vector.
        ground : ndarray, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        J_params : ndarray, shape (m, 2, n_params)
            ``d image / d params``.
        J_ground : ndarray, shape (m, 2, 3)
            ``d image / d ground``.
        """
        ...

    def initial_params(self) -> np.ndarray:
        """A sensible starting parameter vector.

        Returns
        -------
        ndarray, shape (n_params,)
            The start values of the adjustment.
        """
        ...


def _as_ground(ground: ArrayLike) -> np.ndarray:
    g = np.asarray(ground, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != 3:
        raise ValueError(f"ground must have shape (m, 3), got {g.shape}")
    return g


def _as_params(params: ArrayLike, n: int) -> np.ndarray:
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (n,):
        raise ValueError(f"params must have shape ({n},), got {p.shape}")
    return p


def _central_difference(f: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, steps: ArrayLike) -> np.ndarray:
    """Central-difference Jacobian of ``f`` with respect to the last axis of ``x0``.

    Parameters
    ----------
    f : callable
        ``f(x) -> (m, d)`` (``d = 2`` for image coordinates); ``x`` has the
        shape of ``x0``.
    x0 : ndarray, shape ``(..., k)``
        Either a shared parameter vector ``(k,)`` or per-point variables
        ``(m, k)`` (e.g. ground coordinates): component ``j`` is perturbed in
        all points at once, which is valid because the points are independent.
    steps : array_like, shape ``(k,)``
        Step per component.

    Returns
    -------
    ndarray, shape ``(m, d, k)``
        ``(f(x0 + h_j e_j) - f(x0 - h_j e_j)) / (2 h_j)`` for each ``j``.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    steps = np.broadcast_to(np.asarray(steps, dtype=np.float64), (x0.shape[-1],))
    cols = []
    for j, h in enumerate(steps):
        xp = x0.copy()
        xm = x0.copy()
        xp[..., j] += h
        xm[..., j] -= h
        cols.append((f(xp) - f(xm)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def _enu_basis(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rows are the unit east, north, up vectors (ECEF) at a geodetic position (degrees)."""
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
# 1. 2-D polynomial
# --------------------------------------------------------------------------- #
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
        self._enu = _enu_basis(self.origin_lat, self.origin_lon)
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
        g = _as_ground(ground)
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
        p = _as_params(params, self.n_params)
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
        p = _as_params(params, self.n_params).reshape(2, self.n_monomials)
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


# --------------------------------------------------------------------------- #
# 2. Rigorous line scanner
# --------------------------------------------------------------------------- #
#: Names of the 32 line-scanner parameters, in :meth:`LineScanner.parameters` order.
LINE_SCANNER_PARAMETER_NAMES: tuple[str, ...] = (
    "semi_major_axis",
    "eccentricity",
    "inclination",
    "raan",
    "arg_perigee",
    "mean_anomaly0",
    "line_time",
    "t0",
) + tuple(f"{q}_c{k}" for q in ("along", "cross", "radial", "roll", "pitch", "yaw") for k in range(4))


class LineScannerModel:
    """The rigorous line scanner of :mod:`geocoder.simulate.satellite` as a sensor model.

    The full parameter vector is the 32-vector of
    :meth:`LineScanner.parameters`: ``(a, e, i, raan, arg_perigee,
    mean_anomaly0, line_time, t0)`` then the cubic-in-time coefficients
    ``c0..c3`` of the along-track, cross-track, radial position deviations (m)
    and of the roll, pitch, yaw attitude deviations (rad).  Only the entries
    flagged in ``free`` are adjusted; the others stay at the template's values.
    The internal geometry (``rows``, ``cols``, ``ifov``, ``kind``,
    ``col_time``) is always taken from the template.

    A negative eccentricity is accepted and mapped to the identical orbit
    ``(-e, arg_perigee + pi, mean_anomaly0 + pi)``, so that the model is
    smooth through the circular orbit ``e = 0`` (where central differences
    and solver steps would otherwise leave the valid domain).

    Parameters
    ----------
    template : LineScanner
        Nominal scanner; supplies the start values and the fixed parameters.
    free : ndarray, optional
        Boolean mask of shape (32,) (or integer indices) of the adjusted
        parameters; default all 32.  See :meth:`parameter_sets`.

    Attributes
    ----------
    n_params : int
        Number of free parameters.
    free : ndarray of bool, shape (32,)
        The mask.
    param_steps : ndarray, shape (n_params,)
        Natural scales of the free parameters, each moving the image by
        roughly 0.003-0.03 px: 10 m for ``a``; 1e-7 for ``e`` and the orbit
        angles; ``1e-5 line_time`` for ``line_time``; ``0.01 line_time`` for
        ``t0``; for coefficient ``k`` of the deviations ``1 m / T^k`` along
        and across track, ``10 m / T^k`` radially, ``1e-6 rad / T^k`` for
        roll and pitch and ``3e-5 rad / T^k`` for yaw, with ``T`` the largest
        ``|t|`` over the frame.  Central-difference steps for checks, and a
        scale for parameter normalisation.
    ground_step : float
        Ground step of numeric checks of the ground Jacobian (m).

    Notes
    -----
    Each :meth:`project` builds a :class:`LineScanner` and solves the
    acquisition times of all points at once with the iteration of
    ``ground_to_image`` (:func:`geocoder.adjust.linescanner_projection.project_with_times`,
    which agrees with it to ~1e-10 px), starting from the previous call's times
    when the points are the same ones moved a little.  The last projection is
    kept, so :meth:`jacobians` at the same parameters and points (the solver's
    pattern: residuals, then linearisation) does not solve again.
    :meth:`jacobians` is exact: forward-mode jets through the orbit,
    deviation and attitude geometry at the solved time, and the implicit
    function theorem for the time
    (:mod:`geocoder.adjust.linescanner_jacobian`).  It agrees with central
    differences of :meth:`project` (whose ``ground_to_image`` converges to
    ~1e-10 rows) to ~3e-8 of each column's largest entry, the noise of the
    differences, and costs about as much as one :meth:`project`.

    For a circular orbit (``e = 0``) ``arg_perigee`` and ``mean_anomaly0``
    enter only through their sum, and the orbit/time parameters are strongly
    correlated with the low-order deviations (e.g. ``t0``, ``mean_anomaly0``
    and ``along_c0``/``pitch_c0``): the "full" and "attitude_only" sets need
    prior weights (or a regularised solver) to be estimable.
    """

    def __init__(self, template: LineScanner, free: np.ndarray | None = None) -> None:
        self.template = template
        self._p0 = template.parameters()
        if free is None:
            mask = np.ones(32, dtype=bool)
        else:
            f = np.asarray(free)
            if f.dtype == bool:
                if f.shape != (32,):
                    raise ValueError(f"a boolean free mask must have shape (32,), got {f.shape}")
                mask = f.copy()
            else:
                mask = np.zeros(32, dtype=bool)
                mask[f.astype(np.int64)] = True
        self.free = mask
        self.n_params = int(mask.sum())
        self.param_steps = self._full_steps()[mask]
        self.ground_step = 1.0
        self._last: tuple[np.ndarray, LineScanner, np.ndarray, np.ndarray, np.ndarray] | None = None

    def __repr__(self) -> str:
        return f"LineScannerModel(n_params={self.n_params}, rows={self.template.rows}, cols={self.template.cols})"

    # ------------------------------------------------------------ sets
    @staticmethod
    def parameter_sets() -> dict[str, np.ndarray]:
        """Named boolean masks of the 32 parameters.

        Returns
        -------
        dict of str to ndarray of bool, shape (32,)
            * ``"full"``: all 32 (8 orbit/time + 24 deviation coefficients).
            * ``"attitude_only"``: the 8 orbit/time parameters and the 12
              roll/pitch/yaw coefficients ``c0..c3`` (20); the position
              deviations stay at the template's values.
            * ``"low_order"``: ``c0`` and ``c1`` (offset and rate) of the six
              position and attitude deviations (12); orbit/time and the
              quadratic/cubic terms stay at the template's values.  The
              reduced set for scarce control.
        """
        full = np.ones(32, dtype=bool)
        att = np.zeros(32, dtype=bool)
        att[:8] = True
        att[8 + 12 :] = True
        low = np.zeros(32, dtype=bool)
        dev = low[8:].reshape(6, 4)
        dev[:, :2] = True
        return {"full": full, "attitude_only": att, "low_order": low}

    @property
    def names(self) -> list[str]:
        """Names of the free parameters."""
        return [n for n, f in zip(LINE_SCANNER_PARAMETER_NAMES, self.free) if f]

    def _full_steps(self) -> np.ndarray:
        sc = self.template
        o = sc.orbit
        corner_rows = np.array([0.0, sc.rows - 1.0, 0.0, sc.rows - 1.0])
        t_ends = sc.time(corner_rows, np.array([0.0, 0.0, sc.cols - 1.0, sc.cols - 1.0]))
        T = max(float(np.max(np.abs(t_ends))), o.line_time)
        k = np.arange(4)
        steps = np.empty(32)
        steps[:8] = [10.0, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-5 * o.line_time, 1e-2 * o.line_time]
        steps[8:20] = (np.array([1.0, 1.0, 10.0])[:, None] / T**k).ravel()  # radial acts only off nadir
        steps[20:28] = np.tile(1e-6 / T**k, 2)  # roll, pitch: ~1 m on the ground
        steps[28:32] = 3e-5 / T**k  # yaw acts only through the half-swath lever arm
        return steps

    # ------------------------------------------------------------ model
    def full_parameters(self, params: ArrayLike) -> np.ndarray:
        """The 32-vector: the template's values with the free entries replaced by ``params``.

        Parameters
        ----------
        params : array_like, shape (n_params,)
            Free parameters.

        Returns
        -------
        ndarray, shape (32,)
            In the order of :meth:`LineScanner.parameters`.
        """
        p = self._p0.copy()
        p[self.free] = _as_params(params, self.n_params)
        return p

    def scanner(self, params: ArrayLike) -> LineScanner:
        """The :class:`LineScanner` for a (free) parameter vector.

        Parameters
        ----------
        params : array_like, shape (n_params,)
            Free parameters.

        Returns
        -------
        LineScanner
            The template's internal geometry with these parameters (a negative eccentricity
            mapped to the identical orbit with ``e >= 0``).
        """
        p = self.full_parameters(params)
        if p[1] < 0:  # identical orbit with e >= 0
            p[1] = -p[1]
            p[4] += np.pi
            p[5] += np.pi
        sc = self.template
        return LineScanner.from_parameters(
            p, rows=sc.rows, cols=sc.cols, ifov=sc.ifov, kind=sc.kind, col_time=sc.col_time
        )

    def initial_params(self) -> np.ndarray:
        """The template's values of the free parameters.

        Returns
        -------
        ndarray, shape (n_params,)
            A copy.
        """
        return self._p0[self.free].copy()

    @staticmethod
    def _image(sc: LineScanner, ground: np.ndarray) -> np.ndarray:
        row, col = sc.ground_to_image(ground[:, 0], ground[:, 1], ground[:, 2])
        return np.stack([col, row], axis=-1)

    @staticmethod
    def _image_at_time(sc: LineScanner, t: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Image coordinates and along-track ratio of ground points at fixed times (no time search).

        Evaluates the formulas of ``LineScanner.ground_to_image`` at the given
        times instead of the solved ones.

        Parameters
        ----------
        sc : LineScanner
            The sensor.
        t : ndarray, shape (m,)
            Acquisition times (s from the orbit epoch).
        ground : ndarray, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 3)
            ``(col, row, F)``: ``col = centre_col + atan2(y_s, z_s) / ifov``,
            ``row = (t - t0 (- col * col_time)) / line_time`` and
            ``F = x_s / z_s`` (zero at the true acquisition time), with
            ``(x_s, y_s, z_s)`` the sensor-frame vector ``M(t) (P - S(t))``.
        """
        v = sc._sensor_vector(t, ground)
        col = sc.centre_col + np.arctan2(v[:, 1], v[:, 2]) / sc.ifov
        tr = t - sc.orbit.t0
        if sc.kind == "whiskbroom":
            tr = tr - col * sc.col_time
        return np.stack([col, tr / sc.orbit.line_time, v[:, 0] / v[:, 2]], axis=-1)

    def _solved(self, params: ArrayLike, ground: ArrayLike) -> tuple[LineScanner, np.ndarray, np.ndarray, np.ndarray]:
        """Scanner, image coordinates, ground and acquisition times of a projection.

        The solver projects every frame's points (residuals) and then asks for the Jacobians at
        the same parameters and points, so the last result is kept (compared by value, so never
        stale).  A new projection of the same number of points, none moved by more than 10 km,
        starts its time search from the last times (the next iteration of an adjustment).
        """
        p = _as_params(params, self.n_params)
        g = _as_ground(ground)
        last = self._last
        same_set = last is not None and last[2].shape == g.shape
        if same_set and np.array_equal(last[0], p) and np.array_equal(last[2], g):
            return last[1], last[3], last[2], last[4]
        t_start = None
        if same_set and g.size and float(np.max(np.abs(g - last[2]))) < 1e4:
            t_start = last[4]
        sc = self.scanner(p)
        xy, t = project_with_times(sc, g, t_start)
        self._last = (p.copy(), sc, g.copy(), xy, t)
        return sc, xy, g, t

    def project(self, params: ArrayLike, ground: ArrayLike) -> np.ndarray:
        """Image coordinates of ECEF ground points.

        Parameters
        ----------
        params : array_like, shape (n_params,)
            Free parameters.
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x, y) = (col, row)`` as ``LineScanner.ground_to_image`` (to its
            1e-8-row tolerance; :mod:`geocoder.adjust.linescanner_projection`);
            NaN where it does not converge or the point is behind the sensor.
        """
        return self._solved(params, ground)[1].copy()

    def jacobians(self, params: ArrayLike, ground: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Exact Jacobians by forward-mode differentiation and the implicit acquisition time.

        The image point is solved once (:meth:`project`; reused when it was the last call) and
        its time ``t* = time(row, col)`` recovered.  The geometry at the fixed time ``t*`` is
        then evaluated with jets (:func:`geocoder.adjust.linescanner_jacobian.line_scanner_jacobians`):
        with ``F = x_s / z_s`` the along-track collinearity ratio (``F(t*, q) = 0`` defines
        ``t*(q)``)::

            d(col, row) / dq = d(col, row)/dq|_t - d(col, row)/dt * (dF/dq|_t) / (dF/dt)

        for every parameter or ground coordinate ``q``, all points at once (no per-point Python,
        no numerical differences).

        Parameters
        ----------
        params : array_like, shape (n_params,)
            Free parameters.
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        J_params : ndarray, shape (m, 2, n_params)
            ``d(x, y) / d params``; NaN rows where :meth:`project` is NaN.
        J_ground : ndarray, shape (m, 2, 3)
            ``d(x, y) / d(X, Y, Z)``; NaN rows where :meth:`project` is NaN.
        """
        p = _as_params(params, self.n_params)
        sc, xy, g, t = self._solved(p, ground)
        m = g.shape[0]
        Jp = np.full((m, 2, self.n_params), np.nan)
        Jg = np.full((m, 2, 3), np.nan)
        ok = np.all(np.isfinite(xy), axis=1)
        if not ok.any():
            return Jp, Jg
        t = t[ok]
        e_sign = -1.0 if self.full_parameters(p)[1] < 0 else 1.0
        jp32, jg = line_scanner_jacobians(sc, t, g[ok], e_sign=e_sign)
        Jp[ok] = jp32[:, :, self.free]
        Jg[ok] = jg
        return Jp, Jg


# --------------------------------------------------------------------------- #
# 3. RPC
# --------------------------------------------------------------------------- #
def rpc_terms(P: ArrayLike, L: ArrayLike, H: ArrayLike) -> np.ndarray:
    """The 20 cubic terms of RPC00B, in the standard order.

    With ``P``, ``L``, ``H`` the normalised latitude, longitude and height::

        1, L, P, H, L P, L H, P H, L^2, P^2, H^2,
        P L H, L^3, L P^2, L H^2, L^2 P, P^3, P H^2, L^2 H, P^2 H, H^3

    (NITF STDI-0002 RPC00B; the order used by GDAL).

    Parameters
    ----------
    P, L, H : array_like
        Normalised latitude, longitude and height; broadcast together.

    Returns
    -------
    ndarray, shape ``broadcast_shape + (20,)``
    """
    P, L, H = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (P, L, H)))
    one = np.ones_like(P)
    return np.stack(
        [
            one, L, P, H, L * P, L * H, P * H, L * L, P * P, H * H,
            P * L * H, L**3, L * P * P, L * H * H, L * L * P, P**3, P * H * H, L * L * H, P * P * H, H**3,
        ],
        axis=-1,
    )  # fmt: skip


_RPC_SCALARS = (
    "line_off",
    "samp_off",
    "lat_off",
    "long_off",
    "height_off",
    "line_scale",
    "samp_scale",
    "lat_scale",
    "long_scale",
    "height_scale",
)
_RPC_ARRAYS = ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff")


@dataclass(frozen=True, eq=False)
class RPC:
    """Rational polynomial coefficients (RPC00B).

    With ``P = (lat - lat_off) / lat_scale``, ``L = (lon - long_off) /
    long_scale``, ``H = (h - height_off) / height_scale`` (degrees, degrees,
    metres above the ellipsoid) and ``T`` the 20 terms of :func:`rpc_terms`::

        row = line_off + line_scale * (line_num . T) / (line_den . T)
        col = samp_off + samp_scale * (samp_num . T) / (samp_den . T)

    Image coordinates have pixel centres at integers (RPC00B and
    ``CONVENTIONS.md`` agree; GDAL adds 0.5 for its corner convention).

    Attributes
    ----------
    line_off, samp_off, lat_off, long_off, height_off : float
        Offsets.
    line_scale, samp_scale, lat_scale, long_scale, height_scale : float
        Scales.
    line_num_coeff, line_den_coeff, samp_num_coeff, samp_den_coeff : ndarray, shape (20,)
        Coefficients in the order of :func:`rpc_terms`.
    err_bias, err_rand : float or None
        Optional RMS errors (m), carried through conversions.
    """

    line_off: float
    samp_off: float
    lat_off: float
    long_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    long_scale: float
    height_scale: float
    line_num_coeff: np.ndarray
    line_den_coeff: np.ndarray
    samp_num_coeff: np.ndarray
    samp_den_coeff: np.ndarray
    err_bias: float | None = None
    err_rand: float | None = None

    def __post_init__(self) -> None:
        for name in _RPC_SCALARS:
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in _RPC_ARRAYS:
            a = np.array(getattr(self, name), dtype=np.float64, copy=True)
            if a.shape != (20,):
                raise ValueError(f"{name} must have 20 coefficients, got shape {a.shape}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        for name in ("err_bias", "err_rand"):
            v = getattr(self, name)
            object.__setattr__(self, name, None if v is None else float(v))

    def project(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates of geodetic points.

        Parameters
        ----------
        lat, lon : array_like
            Geodetic latitude and longitude (degrees); broadcast with ``h``.
        h : array_like
            Ellipsoidal height (m).

        Returns
        -------
        row, col : ndarray
            Image coordinates (``y``, ``x``).
        """
        T = rpc_terms(
            (np.asarray(lat, dtype=np.float64) - self.lat_off) / self.lat_scale,
            (np.asarray(lon, dtype=np.float64) - self.long_off) / self.long_scale,
            (np.asarray(h, dtype=np.float64) - self.height_off) / self.height_scale,
        )
        row = self.line_off + self.line_scale * (T @ self.line_num_coeff) / (T @ self.line_den_coeff)
        col = self.samp_off + self.samp_scale * (T @ self.samp_num_coeff) / (T @ self.samp_den_coeff)
        return row, col

    def project_ecef(self, ground: ArrayLike) -> np.ndarray:
        """Image coordinates of ECEF points: :meth:`project` after the conversion to geodetic.

        Parameters
        ----------
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x, y)`` = ``(col, row)``.
        """
        g = _as_ground(ground)
        lat, lon, h = ecef_to_geodetic(g[:, 0], g[:, 1], g[:, 2])
        row, col = self.project(np.rad2deg(lat), np.rad2deg(lon), h)
        return np.stack([col, row], axis=-1)

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain Python values (JSON-serialisable).

        Returns
        -------
        dict
            Field name -> value: floats, lists of 20 floats, ``err_bias``/``err_rand``
            (float or None).
        """
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = [float(c) for c in v] if f.name in _RPC_ARRAYS else v
        return out

    @classmethod
    def from_rasterio(cls, rpcs: Any) -> RPC:
        """From a ``rasterio.rpc.RPC`` (e.g. ``src.rpcs``) or a GDAL-style RPC metadata dict.

        Parameters
        ----------
        rpcs : rasterio.rpc.RPC or dict
            A rasterio RPC object, or a dict of GDAL ``RPC`` metadata
            (upper-case keys with string values, as ``src.tags(ns="RPC")``).

        Returns
        -------
        RPC
        """
        if isinstance(rpcs, dict):
            from rasterio.rpc import RPC as _RioRPC

            rpcs = _RioRPC.from_gdal(rpcs)
        kw = {name: getattr(rpcs, name) for name in _RPC_SCALARS + _RPC_ARRAYS}
        return cls(**kw, err_bias=getattr(rpcs, "err_bias", None), err_rand=getattr(rpcs, "err_rand", None))

    def to_rasterio(self) -> Any:
        """The coefficients as rasterio's RPC object.

        Returns
        -------
        rasterio.rpc.RPC
            Usable as ``rpcs=`` when writing a dataset.
        """
        from rasterio.rpc import RPC as _RioRPC

        return _RioRPC(**self.to_dict())


def fit_rpc(
    scanner: LineScanner,
    *,
    grid: tuple[int, int] = (21, 21),
    heights: tuple[float, float] = (0.0, 3000.0),
    layers: int = 7,
    rows: tuple[float, float] | None = None,
    cols: tuple[float, float] | None = None,
    regularization: float = 1e-12,
    iterations: int = 3,
) -> RPC:
    """Fit an RPC to a line scanner (terrain-independent least squares).

    A grid of ``grid[0] x grid[1]`` image points over the row and column
    ranges is intersected by the scanner's inverse mode with ``layers``
    constant-height surfaces spanning ``heights``; the RPC's offsets and
    scales normalise the resulting 3-D point cloud to ``[-1, 1]``.  Each of
    the row and column rational functions is then fitted by the linearised
    least squares of Tao & Hu (2001)::

        num . T - r (den[1:] . T[1:]) = r,      den[0] = 1

    with a small ridge term ``regularization * trace(N) / n`` on the normal
    matrix (the rational terms are nearly redundant for a smooth sensor), and
    re-weighted by ``1 / den`` from the previous solution (``iterations``
    passes) so that the residual minimised is the image residual.

    Parameters
    ----------
    scanner : LineScanner
        The sensor.
    grid : tuple of int
        Number of image grid points along rows and columns.
    heights : tuple of float
        Minimum and maximum ellipsoidal height (m) of the fitted volume.
    layers : int
        Number of height layers (>= 4 to determine the cubic height terms).
    rows, cols : tuple of float, optional
        First and last row / column covered; default the whole frame
        ``(0, rows - 1)``, ``(0, cols - 1)``.
    regularization : float
        Relative ridge weight.
    iterations : int
        Number of re-weighting passes (>= 1).

    Returns
    -------
    RPC
    """
    if layers < 4:
        raise ValueError("layers must be >= 4")
    r_rng = (0.0, scanner.rows - 1.0) if rows is None else (float(rows[0]), float(rows[1]))
    c_rng = (0.0, scanner.cols - 1.0) if cols is None else (float(cols[0]), float(cols[1]))
    r1 = np.linspace(*r_rng, int(grid[0]))
    c1 = np.linspace(*c_rng, int(grid[1]))
    hs = np.linspace(float(heights[0]), float(heights[1]), int(layers))
    R, C, Hh = np.meshgrid(r1, c1, hs, indexing="ij")
    R, C, Hh = R.ravel(), C.ravel(), Hh.ravel()
    X, Y, Z = scanner.image_to_ground(R, C, height=Hh)
    lat, lon, h = ecef_to_geodetic(X, Y, Z)
    lat, lon = np.rad2deg(lat), np.rad2deg(lon)
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(h)
    if ok.sum() < 39:
        raise ValueError("too few ground points: the grid misses the earth")
    R, C, lat, lon, h = R[ok], C[ok], lat[ok], lon[ok], h[ok]

    def off_scale(a: np.ndarray) -> tuple[float, float]:
        lo, hi = float(a.min()), float(a.max())
        return 0.5 * (lo + hi), (0.5 * (hi - lo) if hi > lo else 1.0)

    lat_off, lat_scale = off_scale(lat)
    lon_off, lon_scale = off_scale(lon)
    h_off, h_scale = off_scale(h)
    line_off, line_scale = off_scale(R)
    samp_off, samp_scale = off_scale(C)
    T = rpc_terms((lat - lat_off) / lat_scale, (lon - lon_off) / lon_scale, (h - h_off) / h_scale)

    def solve(target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        A = np.concatenate([T, -target[:, None] * T[:, 1:]], axis=1)
        w = np.ones(len(target))
        for _ in range(max(int(iterations), 1)):
            Aw, bw = A * w[:, None], target * w
            N = Aw.T @ Aw
            N[np.diag_indices_from(N)] += regularization * np.trace(N) / N.shape[0]
            x = np.linalg.solve(N, Aw.T @ bw)
            den = np.concatenate([[1.0], x[20:]])
            w = 1.0 / np.abs(T @ den)
        return x[:20], den

    line_num, line_den = solve((R - line_off) / line_scale)
    samp_num, samp_den = solve((C - samp_off) / samp_scale)
    return RPC(
        line_off=line_off,
        samp_off=samp_off,
        lat_off=lat_off,
        long_off=lon_off,
        height_off=h_off,
        line_scale=line_scale,
        samp_scale=samp_scale,
        lat_scale=lat_scale,
        long_scale=lon_scale,
        height_scale=h_scale,
        line_num_coeff=line_num,
        line_den_coeff=line_den,
        samp_num_coeff=samp_num,
        samp_den_coeff=samp_den,
    )


class RPCModel:
    """An RPC with an affine bias compensation in image space.

    With ``(x, y) = (col, row)`` from the RPC::

        x' = x + p0 + p1 x + p2 y
        y' = y + p3 + p4 x + p5 y

    (Grodecki & Dial 2003; ``p0``/``p3`` alone is the shift-only bias
    correction.)  Parameters start at zero (the RPC as delivered).

    Parameters
    ----------
    rpc : RPC
        The sensor's rational polynomial coefficients.

    Attributes
    ----------
    n_params : int
        6.
    param_steps : ndarray, shape (6,)
        Central-difference steps (for checks; the parameter Jacobian is analytic).
    ground_step : float
        Ground step of the numeric ground Jacobian (m).
    """

    n_params = 6

    def __init__(self, rpc: RPC) -> None:
        self.rpc = rpc
        self.param_steps = np.array([1e-2, 1e-5, 1e-5, 1e-2, 1e-5, 1e-5])
        self.ground_step = 1.0

    def __repr__(self) -> str:
        return f"RPCModel(rpc=<RPC line_off={self.rpc.line_off}, samp_off={self.rpc.samp_off}>)"

    def initial_params(self) -> np.ndarray:
        """Zeros: the RPC as delivered, no bias.

        Returns
        -------
        ndarray, shape (6,)
            All zero.
        """
        return np.zeros(6)

    @staticmethod
    def _bias(p: np.ndarray, xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        return np.stack([x + p[0] + p[1] * x + p[2] * y, y + p[3] + p[4] * x + p[5] * y], axis=-1)

    def project(self, params: ArrayLike, ground: ArrayLike) -> np.ndarray:
        """Bias-compensated image coordinates of ECEF ground points.

        Parameters
        ----------
        params : array_like, shape (6,)
            ``(p0 .. p5)``.
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x', y')``.
        """
        p = _as_params(params, 6)
        return self._bias(p, self.rpc.project_ecef(ground))

    def jacobians(self, params: ArrayLike, ground: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Analytic parameter Jacobian; ground Jacobian by central differences of the RPC.

        Parameters
        ----------
        params : array_like, shape (6,)
            ``(p0 .. p5)``.
        ground : array_like, shape (m, 3)
            ECEF coordinates (m).

        Returns
        -------
        J_params : ndarray, shape (m, 2, 6)
            Rows ``(1, x, y, 0, 0, 0)`` and ``(0, 0, 0, 1, x, y)``.
        J_ground : ndarray, shape (m, 2, 3)
            ``(I + [[p1, p2], [p4, p5]]) d(x, y) / d(X, Y, Z)``.
        """
        p = _as_params(params, 6)
        g = _as_ground(ground)
        xy = self.rpc.project_ecef(g)
        m = xy.shape[0]
        Jp = np.zeros((m, 2, 6))
        Jp[:, 0, 0] = 1.0
        Jp[:, 0, 1] = xy[:, 0]
        Jp[:, 0, 2] = xy[:, 1]
        Jp[:, 1, 3] = 1.0
        Jp[:, 1, 4] = xy[:, 0]
        Jp[:, 1, 5] = xy[:, 1]
        J_rpc = _central_difference(self.rpc.project_ecef, g, np.full(3, self.ground_step))
        B = np.eye(2) + np.array([[p[1], p[2]], [p[4], p[5]]])
        return Jp, B @ J_rpc
