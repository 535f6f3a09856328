"""Exact Jacobians of the rigorous line scanner (seed 000 eqs 1-3), vectorised over points.

The geometry of :class:`geocoder.adjust.linescanner_geometry.LineScanner` is re-evaluated at *fixed*
acquisition times with forward-mode jets (:mod:`geocoder.adjust.jet`) along 16 directions::

    0..5   a, e, i, raan, arg_perigee, mean_anomaly0   (Keplerian elements)
    6      t                                           (acquisition time)
    7..12  dA, dC, dR, roll, pitch, yaw                (deviation values at t)
    13..15 X, Y, Z                                     (ground point, ECEF)

giving ``col``, ``row`` and the along-track collinearity ratio ``F = x_s / z_s`` with their
partial derivatives.  Kepler's equation is solved numerically for the value and differentiated
implicitly (``dE = (dM + sin E de) / (1 - e cos E)``).  The acquisition time is defined by
``F(t*, q) = 0``, so by the implicit function theorem the image derivatives are::

    d(col, row)/dq = d(col, row)/dq|_t - d(col, row)/dt|_q * (dF/dq|_t) / (dF/dt|_q)

A deviation coefficient ``c_jk`` (``dev_j(t) = sum_k c_jk t^k``) acts through ``t^k`` times the
derivative with respect to ``dev_j``; ``line_time`` and ``t0`` only enter the row formula
``row = (t - t0 - col col_time) / line_time``.

References
----------
Paderes, Mikhail & Foerstner (1984), eqs 1-3 (collinearity of a line scanner with polynomial
position and attitude deviations).
"""

from __future__ import annotations

import numpy as np

from ..geodesy import GM_EARTH, OMEGA_EARTH
from . import jet
from .jet import Jet
from .linescanner_geometry import LineScanner

__all__ = ["N_DIRECTIONS", "image_jets", "line_scanner_jacobians"]

#: Number of jet directions (6 elements, time, 6 deviation values, 3 ground coordinates).
N_DIRECTIONS = 16
_T, _DEV, _GROUND = 6, 7, 13


def _deviation_jets(sc: LineScanner, t: np.ndarray) -> Jet:
    """The six deviation values at ``t``: own directions 7..12 plus their rates along ``t``."""
    c = sc.deviations  # (6, 4)
    powers = np.stack([np.ones_like(t), t, t * t, t * t * t], axis=-1)
    rates = np.stack([np.zeros_like(t), np.ones_like(t), 2.0 * t, 3.0 * t * t], axis=-1)
    d = np.zeros(t.shape + (6, N_DIRECTIONS))
    d[..., np.arange(6), _DEV + np.arange(6)] = 1.0
    d[..., _T] = rates @ c.T
    return Jet(powers @ c.T, d)


def _pad(x: Jet) -> Jet:
    """The jet with zero derivatives along the directions it does not carry (all 16)."""
    d = np.zeros(x.d.shape[:-1] + (N_DIRECTIONS,))
    d[..., : x.d.shape[-1]] = x.d
    return Jet(x.v, d)


def image_jets(sc: LineScanner, t: np.ndarray, ground: np.ndarray, *, e_sign: float = 1.0) -> tuple[Jet, Jet, Jet]:
    """Image coordinates and along-track ratio at fixed times, with their partial derivatives.

    Parameters
    ----------
    sc : LineScanner
        The sensor (eccentricity ``>= 0``).
    t : ndarray, shape (m,)
        Acquisition times (s from the orbit epoch).
    ground : ndarray, shape (m, 3)
        ECEF coordinates (m).
    e_sign : float
        Derivative of the scanner's eccentricity with respect to the model's (``-1`` when the
        model's negative eccentricity was mapped to the identical orbit with ``e >= 0``).

    Returns
    -------
    col, row, F : Jet
        Values of shape ``(m,)``, derivatives ``(m, 16)`` along the directions of the module
        docstring (partial: at fixed ``t``, except direction 6, the time itself).  ``row``
        holds ``line_time`` and ``t0`` constant.
    """
    k = _T + 1  # the orbit depends on the elements and the time only: 7 directions, padded below
    o = sc.orbit
    t = np.asarray(t, dtype=np.float64)
    a = jet.seed(o.semi_major_axis, k, 0)
    e = jet.seed(o.eccentricity, k, 1, e_sign)
    inc = jet.seed(o.inclination, k, 2)
    raan = jet.seed(o.raan, k, 3)
    argp = jet.seed(o.arg_perigee, k, 4)
    m0 = jet.seed(o.mean_anomaly0, k, 5)
    tj = jet.seed(t, k, _T)

    # Kepler: value by the orbit's own Newton solve, derivative implicitly
    n = jet.sqrt(GM_EARTH / (a * a * a))
    mean = m0 + n * tj
    ev = o.eccentric_anomaly(t)
    se, ce = np.sin(ev), np.cos(ev)
    ecc = jet.Jet(ev, (mean.d + se[:, None] * e.d) / (1.0 - o.eccentricity * ce)[:, None])
    cE, sE = jet.cos(ecc), jet.sin(ecc)
    q = jet.sqrt(1.0 - e * e)
    r = a * (1.0 - e * cE)
    xp, yp = a * (cE - e), a * q * sE
    kk = jet.sqrt(GM_EARTH * a) / r
    vxp, vyp = -(kk * sE), kk * q * cE

    # perifocal axes P, Q = first two columns of Rz(raan) Rx(i) Rz(arg_perigee)
    cO, sO, ci, si, cw, sw = jet.cos(raan), jet.sin(raan), jet.cos(inc), jet.sin(inc), jet.cos(argp), jet.sin(argp)
    P = jet.stack([cO * cw - sO * ci * sw, sO * cw + cO * ci * sw, si * sw])
    Q = jet.stack([-(cO * sw) - sO * ci * cw, -(sO * sw) + cO * ci * cw, si * cw])
    pos = xp.expand() * P + yp.expand() * Q
    vel = vxp.expand() * P + vyp.expand() * Q

    # ECI -> ECEF (earth rotation since the epoch)
    th = OMEGA_EARTH * tj
    c, s = jet.cos(th), jet.sin(th)
    x, y, z = pos.comp(0), pos.comp(1), pos.comp(2)
    re0, re1 = c * x + s * y, -(s * x) + c * y
    re = jet.stack([re0, re1, z])
    vx, vy = vel.comp(0), vel.comp(1)
    ve = jet.stack([c * vx + s * vy + OMEGA_EARTH * re1, -(s * vx) + c * vy - OMEGA_EARTH * re0, vel.comp(2)])

    # orbital frame and actual sensor position
    z_o = -jet.unit(re)
    y_o = jet.unit(jet.cross(z_o, ve))
    x_o = jet.cross(y_o, z_o)
    re, x_o, y_o, z_o, tj = (_pad(v) for v in (re, x_o, y_o, z_o, tj))
    k = N_DIRECTIONS
    dev = _deviation_jets(sc, t)
    S = re + dev.comp(0).expand() * x_o + dev.comp(1).expand() * y_o - dev.comp(2).expand() * z_o

    g = np.asarray(ground, dtype=np.float64)
    gd = np.zeros(g.shape + (k,))
    gd[:, np.arange(3), _GROUND + np.arange(3)] = 1.0
    w = Jet(g, gd) - S
    u0, u1, u2 = jet.dot(x_o, w), jet.dot(y_o, w), jet.dot(z_o, w)

    # sensor frame: A^T u with A = Rz(yaw) Ry(pitch) Rx(roll)
    cr, sr = jet.cos(dev.comp(3)), jet.sin(dev.comp(3))
    cp, sp = jet.cos(dev.comp(4)), jet.sin(dev.comp(4))
    cy, sy = jet.cos(dev.comp(5)), jet.sin(dev.comp(5))
    a0, a1 = cy * u0 + sy * u1, -(sy * u0) + cy * u1
    b0, b2 = cp * a0 - sp * u2, sp * a0 + cp * u2
    xs, ys, zs = b0, cr * a1 + sr * b2, -(sr * a1) + cr * b2

    col = sc.centre_col + jet.arctan2(ys, zs) / sc.ifov
    tr = tj - o.t0
    if sc.kind == "whiskbroom":
        tr = tr - col * sc.col_time
    row = tr / o.line_time
    return col, row, xs / zs


def line_scanner_jacobians(
    sc: LineScanner, t: np.ndarray, ground: np.ndarray, *, e_sign: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of ``(col, row)`` with respect to all 32 parameters and the ground point.

    Parameters
    ----------
    sc : LineScanner
        The sensor (eccentricity ``>= 0``).
    t : ndarray, shape (m,)
        Solved acquisition times of the points (``F(t) = 0``, e.g. ``sc.time(row, col)`` of
        ``sc.ground_to_image``).
    ground : ndarray, shape (m, 3)
        ECEF coordinates (m).
    e_sign : float
        See :func:`image_jets`.

    Returns
    -------
    J_params : ndarray, shape (m, 2, 32)
        ``d(x, y) / d p`` in the order of :meth:`LineScanner.parameters`.
    J_ground : ndarray, shape (m, 2, 3)
        ``d(x, y) / d(X, Y, Z)``.
    """
    t = np.asarray(t, dtype=np.float64)
    col, row, F = image_jets(sc, t, ground, e_sign=e_sign)
    m = t.shape[0]
    dF = F.d / F.d[:, _T : _T + 1]  # (m, 16): dt*/dq = -dF/dq / dF/dt
    J = np.stack([col.d - col.d[:, _T : _T + 1] * dF, row.d - row.d[:, _T : _T + 1] * dF], axis=1)  # (m, 2, 16)
    Jp = np.zeros((m, 2, 32))
    Jp[:, :, :6] = J[:, :, :6]
    lt = sc.orbit.line_time
    Jp[:, 1, 6] = -row.v / lt  # d row / d line_time at fixed t
    Jp[:, 1, 7] = -1.0 / lt  # d row / d t0
    powers = np.stack([np.ones_like(t), t, t * t, t * t * t], axis=-1)  # (m, 4)
    Jp[:, :, 8:] = (J[:, :, _DEV : _DEV + 6, None] * powers[:, None, None, :]).reshape(m, 2, 24)
    return Jp, J[:, :, _GROUND:].copy()
