"""The rigorous line scanner as a sensor model: all or a subset of its 32 parameters adjusted.

:class:`LineScannerModel` wraps :class:`~geocoder.adjust.linescanner_geometry.LineScanner`
(8 orbit/time + 24 position/attitude deviation parameters, Paderes, Mikhail & Foerstner
(1984), sec. 2.1).  Its Jacobians are exact: forward-mode jets and implicit differentiation at
the solved acquisition time (:mod:`geocoder.adjust.linescanner_jacobian`); the projection
solves the acquisition time per point (:mod:`geocoder.adjust.linescanner_projection`).
Follows :class:`~geocoder.adjust.sensor.SensorModel`.  Pure numpy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ..linescanner_geometry import LineScanner
from ..linescanner_jacobian import line_scanner_jacobians
from ..linescanner_projection import project_with_times
from ..sensor import as_ground, as_params

__all__ = ["LINE_SCANNER_PARAMETER_NAMES", "LineScannerModel"]


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
    """The rigorous line scanner of :mod:`geocoder.adjust.linescanner_geometry` as a sensor model.

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
        p[self.free] = as_params(params, self.n_params)
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
        p = as_params(params, self.n_params)
        g = as_ground(ground)
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
        p = as_params(params, self.n_params)
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
