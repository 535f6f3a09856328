"""Rigorous line-scanner geometry: a scanner on a Keplerian orbit over a rotating WGS84 earth.

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

This is the rigorous sensor of the block adjustment
(:class:`geocoder.adjust.models.LineScannerModel`) and of the simulator
(:func:`geocoder.simulate.satellite.landsat_mss_like`).  The orbit is
:class:`geocoder.adjust.orbit.Orbit`, the geodesy :mod:`geocoder.geodesy`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..geodesy import WGS84_A, WGS84_B, ecef_to_geodetic, ellipsoid_normal, unit
from .orbit import Orbit

__all__ = ["KINDS", "LineScanner"]

#: Scanner types: all columns of a row at once, or a scanning mirror.
KINDS = ("pushbroom", "whiskbroom")


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of arrays of 3-vectors in the last axis, written out (several times faster)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _yaw_pitch_roll(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``rotation(2, yaw) @ rotation(1, pitch) @ rotation(0, roll)`` in closed form, ``yaw.shape + (3, 3)``."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.empty(np.shape(yaw) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


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
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
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
        S, x_o, y_o, z_o, A = self._frames(t)
        # [x_o y_o z_o] @ A written out: numpy's stacked 3 x 3 matrix products cost several times more
        R = x_o[..., :, None] * A[..., 0, None, :] + y_o[..., :, None] * A[..., 1, None, :] \
            + z_o[..., :, None] * A[..., 2, None, :]
        return S, R

    def _frames(self, t: ArrayLike) -> tuple[np.ndarray, ...]:
        """:meth:`exterior` in parts: ``S``, the orbital frame's axes ``x_o, y_o, z_o`` (``t.shape + (3,)``,
        ECEF) and the attitude deviation ``A`` (``t.shape + (3, 3)``); ``R = [x_o y_o z_o] A``."""
        S, x_o, y_o, z_o, d = self._orbital_frame(t)
        return S, x_o, y_o, z_o, _yaw_pitch_roll(d[..., 5], d[..., 4], d[..., 3])

    def _orbital_frame(self, t: ArrayLike) -> tuple[np.ndarray, ...]:
        """``S``, the orbital frame's axes ``x_o, y_o, z_o`` (ECEF) and the deviations ``d``
        (``t.shape + (6,)``: the position's three offsets, then roll, pitch, yaw) at times ``t``."""
        t = np.asarray(t, dtype=np.float64)
        r, v = self.orbit.position_velocity_ecef(t)
        z_o = -unit(r)
        y_o = unit(_cross(z_o, v))
        x_o = _cross(y_o, z_o)
        d = self.deviation_values(t)
        return r + d[..., 0:1] * x_o + d[..., 1:2] * y_o - d[..., 2:3] * z_o, x_o, y_o, z_o, d

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
        S, x_o, y_o, z_o, A = self._frames(t)
        u_a = A[:, :, 1] * np.sin(psi)[:, None] + A[:, :, 2] * np.cos(psi)[:, None]  # A (0, sin psi, cos psi)
        u = x_o * u_a[:, 0:1] + y_o * u_a[:, 1:2] + z_o * u_a[:, 2:3]  # R u_s without forming R

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
            dh_ds = np.sum(ellipsoid_normal(lat, lon) * u, axis=1)
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
        """``M (P - S)``, shape (m, 3), for times ``t`` (m,) and ECEF points ``P`` (m, 3): the points in
        the orbital frame, then the attitude's three rotations transposed one after the other
        (``M = R^T = A^T [x_o y_o z_o]^T``, no 3 x 3 matrix per point)."""
        S, x_o, y_o, z_o, d = self._orbital_frame(t)
        w = P - S
        u0, u1, u2 = (np.einsum("ni,ni->n", axis, w) for axis in (x_o, y_o, z_o))
        cr, sr, cp, sp = np.cos(d[:, 3]), np.sin(d[:, 3]), np.cos(d[:, 4]), np.sin(d[:, 4])
        cy, sy = np.cos(d[:, 5]), np.sin(d[:, 5])
        a0, a1 = cy * u0 + sy * u1, -sy * u0 + cy * u1  # Rz(yaw)^T
        b0, b2 = cp * a0 - sp * u2, sp * a0 + cp * u2  # Ry(pitch)^T
        return np.stack([b0, cr * a1 + sr * b2, -sr * a1 + cr * b2], axis=-1)  # Rx(roll)^T

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
