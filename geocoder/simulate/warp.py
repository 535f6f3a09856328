"""Synthetic image pairs with a known displacement for every base pixel.

The module produces *(base, distorted)* image pairs together with the true
displacement field, so that registration accuracy can be measured against
truth in tests, benchmarks and the built-in demo.

Conventions (see ``CONVENTIONS.md``):

* pixel centres: ``x`` = column, ``y`` = row; arrays are indexed
  ``image[..., y, x]`` and multi-band images are ``(band, y, x)``;
* a displacement field is ``d(x, y) = p_distorted - p_base`` evaluated on
  *base* pixel coordinates;
* the distorted image lives in the same coordinate frame as the base image
  (distorted pixel ``(row 0, col 0)`` sits at base coordinate ``(0, 0)``),
  so a base pixel ``p`` is seen in the distorted image at ``p + d(p)``;
* nodata is NaN; every random draw takes a ``seed``.

The module is pure numpy/scipy (no dask, xarray or zarr).  It is over 500 lines because
:class:`WarpField` (the displacement model with its inverse, about 390 lines) and
:func:`make_pair`, which renders through it, belong together; :func:`seed_affine_experiment`
(seed 000 sec. 4.5) is the paper experiment built on :func:`make_pair`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

__all__ = [
    "WarpField",
    "SyntheticPair",
    "invert",
    "make_pair",
    "seed_affine_experiment",
]

#: Largest |d(turbulence)/dy| (px per line) that :meth:`WarpField.random` accepts.
_TURBULENCE_SLOPE_MAX = 0.2
#: Largest entry of the Jacobian of d (smooth + turbulence) that
#: :meth:`WarpField.random` produces; keeps I + J well conditioned.
_JACOBIAN_MAX = 0.45
#: Maximum number of sample points per axis used to bound |d| over a grid.
_BOUND_SAMPLES = 513
#: plane waves of a relief-like displacement (:meth:`WarpField.random`)
_RELIEF_WAVES = 6


def _as_float_array(a: Any, name: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    arr = np.array(a, dtype=np.float64, copy=True)
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class WarpField:
    """Analytic displacement ``d(x, y) = p_distorted - p_base`` on base pixel coordinates.

    With ``u = x - cx`` and ``v = y - cy`` (centred frame)::

        dx = A[0, 0] u + A[0, 1] v + A[0, 2] + Q[0, 0] u**2 + Q[0, 1] u v + Q[0, 2] v**2 + tx(y) + rx(x, y)
        dy = A[1, 0] u + A[1, 1] v + A[1, 2] + Q[1, 0] u**2 + Q[1, 1] u v + Q[1, 2] v**2 + ty(y) + ry(x, y)

    where ``tx``/``ty`` are the scan-line turbulence profiles, linearly
    interpolated in ``y`` between base rows and clamped beyond the first and
    last entries.

    Attributes
    ----------
    affine : numpy.ndarray
        ``(2, 3)`` matrix; ``d_affine = affine[:, :2] @ (u, v) + affine[:, 2]``.
    quadratic : numpy.ndarray
        ``(2, 3)`` coefficients of ``(u**2, u*v, v**2)`` for ``dx`` (row 0)
        and ``dy`` (row 1).
    centre : tuple of float
        ``(cx, cy)``, normally the centre of the base grid,
        ``((W - 1) / 2, (H - 1) / 2)``.
    turbulence_x : numpy.ndarray
        1-D array, one extra ``dx`` per base row ``y = 0, 1, ...`` (may be
        empty, meaning zero).
    turbulence_y : numpy.ndarray
        Same for ``dy``.
    relief : numpy.ndarray
        ``(k, 5)`` rows ``(ax, ay, kx, ky, phase)``: ``rx = sum ax sin(kx x + ky y + phase)``
        and ``ry`` likewise with ``ay`` (pixel coordinates, not centred); a displacement that
        varies within a scan line over tens of pixels, as relief does (default: none).

    Notes
    -----
    Instances are immutable (arrays are stored as read-only copies) and
    compare by identity; compare the arrays explicitly to test equality.
    """

    affine: np.ndarray
    quadratic: np.ndarray
    centre: tuple[float, float]
    turbulence_x: np.ndarray
    turbulence_y: np.ndarray
    relief: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "affine", _as_float_array(self.affine, "affine", (2, 3)))
        object.__setattr__(
            self, "quadratic", _as_float_array(self.quadratic, "quadratic", (2, 3))
        )
        cx, cy = self.centre
        object.__setattr__(self, "centre", (float(cx), float(cy)))
        for name in ("turbulence_x", "turbulence_y"):
            arr = _as_float_array(getattr(self, name), name)
            if arr.ndim != 1:
                raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} must be finite")
            object.__setattr__(self, name, arr)
        if not (np.all(np.isfinite(self.affine)) and np.all(np.isfinite(self.quadratic))):
            raise ValueError("affine and quadratic coefficients must be finite")
        relief = _as_float_array(self.relief, "relief")
        if relief.ndim != 2 or relief.shape[1] != 5 or not np.all(np.isfinite(relief)):
            raise ValueError(f"relief must be finite rows (ax, ay, kx, ky, phase), got shape {relief.shape}")
        object.__setattr__(self, "relief", relief)

    # ------------------------------------------------------------------ parts
    def affine_part(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Affine component of the displacement.

        Parameters
        ----------
        x, y : array_like
            Base pixel coordinates (broadcast against each other).

        Returns
        -------
        dx, dy : numpy.ndarray
            float64 arrays of the broadcast shape.
        """
        u, v = self._centred(x, y)
        a = self.affine
        return a[0, 0] * u + a[0, 1] * v + a[0, 2], a[1, 0] * u + a[1, 1] * v + a[1, 2]

    def quadratic_part(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Quadratic component of the displacement.

        Parameters
        ----------
        x, y : array_like
            Base pixel coordinates (broadcast against each other).

        Returns
        -------
        dx, dy : numpy.ndarray
            float64 arrays of the broadcast shape.
        """
        u, v = self._centred(x, y)
        q = self.quadratic
        uu, uv, vv = u * u, u * v, v * v
        return (
            q[0, 0] * uu + q[0, 1] * uv + q[0, 2] * vv,
            q[1, 0] * uu + q[1, 1] * uv + q[1, 2] * vv,
        )

    def turbulence_part(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row-dependent (scan-line) component of the displacement.

        Parameters
        ----------
        y : array_like
            Base row coordinates.

        Returns
        -------
        dx, dy : numpy.ndarray
            float64 arrays shaped like ``y``; linear interpolation between
            rows, clamped to the first/last entry outside the table.
        """
        y = np.asarray(y, dtype=np.float64)
        return _interp_rows(self.turbulence_x, y), _interp_rows(self.turbulence_y, y)

    def relief_part(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Relief-like component of the displacement (sum of plane waves, see ``relief``);
        arguments and results as :meth:`affine_part`."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        dx, dy = np.zeros(x.shape), np.zeros(x.shape)
        for ax, ay, kx, ky, phase in self.relief:
            wave = np.sin(kx * x + ky * y + phase)
            dx += ax * wave
            dy += ay * wave
        return dx, dy

    # ------------------------------------------------------------- public API
    def displacement(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Evaluate ``d(x, y) = p_distorted - p_base``.

        Parameters
        ----------
        x, y : array_like
            Base pixel coordinates (column, row); broadcast against each other.

        Returns
        -------
        dx, dy : numpy.ndarray
            float64 arrays of the broadcast shape.
        """
        x, y = np.broadcast_arrays(
            np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        )
        u, v = self._centred(x, y)
        a, q = self.affine, self.quadratic
        tx, ty = self.turbulence_part(y)
        # Horner-like evaluation of affine + quadratic (fewer temporaries)
        dx = u * (a[0, 0] + q[0, 0] * u + q[0, 1] * v)
        dx += v * (a[0, 1] + q[0, 2] * v)
        dx += tx
        dx += a[0, 2]
        dy = u * (a[1, 0] + q[1, 0] * u + q[1, 1] * v)
        dy += v * (a[1, 1] + q[1, 2] * v)
        dy += ty
        dy += a[1, 2]
        if len(self.relief):
            rx, ry = self.relief_part(x, y)
            dx += rx
            dy += ry
        return dx, dy

    def partials(
        self, x: np.ndarray, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Partial derivatives of the displacement.

        Parameters
        ----------
        x, y : array_like
            Base pixel coordinates (broadcast against each other).

        Returns
        -------
        ddx_dx, ddx_dy, ddy_dx, ddy_dy : numpy.ndarray
            float64 arrays of the broadcast shape.  The turbulence derivative
            is that of the linear segment containing ``y`` (right-hand
            derivative at integer rows, zero in the clamped range).
        """
        x, y = np.broadcast_arrays(
            np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        )
        u, v = self._centred(x, y)
        a, q = self.affine, self.quadratic
        gxx = a[0, 0] + 2.0 * q[0, 0] * u + q[0, 1] * v
        gxy = a[0, 1] + q[0, 1] * u + 2.0 * q[0, 2] * v + _slope_rows(self.turbulence_x, y)
        gyx = a[1, 0] + 2.0 * q[1, 0] * u + q[1, 1] * v
        gyy = a[1, 1] + q[1, 1] * u + 2.0 * q[1, 2] * v + _slope_rows(self.turbulence_y, y)
        for ax, ay, kx, ky, phase in self.relief:
            wave = np.cos(kx * x + ky * y + phase)
            gxx = gxx + ax * kx * wave
            gxy = gxy + ax * ky * wave
            gyx = gyx + ay * kx * wave
            gyy = gyy + ay * ky * wave
        return gxx, gxy, gyx, gyy

    def jacobian_bound(self, shape: tuple[int, int]) -> float:
        """Upper bound of ``max |∂d/∂(x, y)|`` (largest Jacobian entry) over a grid.

        Parameters
        ----------
        shape : tuple of int
            ``(H, W)`` of the base grid; pixel centres ``x in [0, W-1]``,
            ``y in [0, H-1]``.

        Returns
        -------
        float
            The smooth (affine + quadratic) partials are affine functions of
            ``(x, y)`` and are maximised exactly at the grid corners; the
            largest turbulence slope over rows ``[0, H-1]`` is added to the
            ``∂/∂y`` entries.  A value below 0.5 guarantees an
            invertible, well-conditioned field.
        """
        h, w = _check_shape(shape)
        xs = np.array([0.0, w - 1.0, 0.0, w - 1.0])
        ys = np.array([0.0, 0.0, h - 1.0, h - 1.0])
        u, v = self._centred(xs, ys)
        a, q = self.affine, self.quadratic
        gxx = np.abs(a[0, 0] + 2.0 * q[0, 0] * u + q[0, 1] * v).max()
        gxy = np.abs(a[0, 1] + q[0, 1] * u + 2.0 * q[0, 2] * v).max()
        gyx = np.abs(a[1, 0] + 2.0 * q[1, 0] * u + q[1, 1] * v).max()
        gyy = np.abs(a[1, 1] + q[1, 1] * u + 2.0 * q[1, 2] * v).max()
        gxy += _max_slope(self.turbulence_x, h)
        gyy += _max_slope(self.turbulence_y, h)
        r = np.abs(self.relief)
        gxx += float(np.sum(r[:, 0] * r[:, 2]))
        gxy += float(np.sum(r[:, 0] * r[:, 3]))
        gyx += float(np.sum(r[:, 1] * r[:, 2]))
        gyy += float(np.sum(r[:, 1] * r[:, 3]))
        return float(max(gxx, gxy, gyx, gyy))

    def max_displacement(self, shape: tuple[int, int]) -> float:
        """Largest ``|d|`` (Euclidean) over the pixel centres of a grid.

        Parameters
        ----------
        shape : tuple of int
            ``(H, W)`` of the base grid.

        Returns
        -------
        float
            Exact for grids up to 2048 x 2048 pixels; larger grids are
            evaluated on every row and a subset of columns.
        """
        h, w = _check_shape(shape)
        cols = np.arange(w, dtype=np.float64)
        if cols.size > 2048:
            cols = np.unique(np.linspace(0.0, w - 1.0, 2048).round())
        best = 0.0
        for r0 in range(0, h, 256):
            ys = np.arange(r0, min(h, r0 + 256), dtype=np.float64)[:, None]
            dx, dy = self.displacement(cols[None, :], ys)
            best = max(best, float(np.sqrt(dx * dx + dy * dy).max()))
        return best

    @classmethod
    def random(
        cls,
        shape: tuple[int, int],
        *,
        seed: int,
        max_displacement: float = 15.0,
        affine_max: float | None = None,
        turbulence: tuple[float, float] | None = None,
        turbulence_scale: float = 30.0,
        relief: tuple[float, float] | None = None,
    ) -> "WarpField":
        """Draw a random smooth field (affine + quadratic + optional turbulence).

        Parameters
        ----------
        shape : tuple of int
            ``(H, W)`` of the base grid; the centre of the field is the grid
            centre ``((W - 1) / 2, (H - 1) / 2)``.
        seed : int
            Seed of ``numpy.random.default_rng``.
        max_displacement : float, optional
            Bound of ``|d|`` (Euclidean, pixels) over the base grid, turbulence
            included.  The smooth part is scaled to use the budget left by the
            turbulence, so its maximum is close to it.
        affine_max : float, optional
            Upper bound of the absolute entries of the linear part
            ``affine[:, :2]`` (i.e. of ``B - I``).  ``None``: only the
            displacement budget and the invertibility guard limit it.
        turbulence : tuple of float, optional
            ``(amin, amax)``: peak ``|tx|`` and peak ``|ty|`` over the base rows
            are each drawn uniformly in ``[amin, amax]`` pixels.  ``None``: no
            turbulence (zero profiles of length ``H``).
        turbulence_scale : float, optional
            Typical correlation length of the turbulence in lines: it is the
            sum of 3-4 sinusoids with periods between ``2/3`` and ``20/3`` of
            it (20-200 lines for the default 30) and a random walk smoothed
            with a Gaussian of sigma ``turbulence_scale / 2``.
        relief : tuple of float, optional
            ``(peak, wavelength)``: a relief-like displacement of at most ``peak`` px, the
            sum of :data:`_RELIEF_WAVES` plane waves of wavelengths within ``[0.5, 1.5]``
            times ``wavelength`` px in random directions, mostly across the lines (x; y a
            third as strong): structure finer than a scan line's fit, which neither the
            polynomial nor a per-line shift follows. Drawn after the turbulence, from the
            same generator, so a field without it is the same as before it existed.

        Returns
        -------
        WarpField

        Raises
        ------
        ValueError
            On invalid arguments, when the turbulence uses up the whole
            displacement budget, or when the requested turbulence amplitude
            cannot be reached with a slope below 0.2 px/line.

        Notes
        -----
        The linear part is the linearised ``R(theta) S - I`` of a rotation,
        two scales and a shear, ``[[sx, sh - theta], [theta, sy]]``.  Shift,
        linear and quadratic parts each get a comparable share of the smooth
        budget (roughly 25-45 % each before the joint rescale), so all of
        them are clearly present.  The smooth part is scaled down, if
        necessary, so that :meth:`jacobian_bound` stays <= 0.45 (this only
        matters for small grids, below ~200 pixels, where 15 px of
        displacement would otherwise mean strong local distortion).
        """
        h, w = _check_shape(shape)
        if not np.isfinite(max_displacement) or max_displacement <= 0:
            raise ValueError(f"max_displacement must be > 0, got {max_displacement}")
        if affine_max is not None and not (np.isfinite(affine_max) and affine_max >= 0):
            raise ValueError(f"affine_max must be >= 0, got {affine_max}")
        if not np.isfinite(turbulence_scale) or turbulence_scale <= 0:
            raise ValueError(f"turbulence_scale must be > 0, got {turbulence_scale}")
        rng = np.random.default_rng(seed)
        cx, cy = (w - 1) / 2.0, (h - 1) / 2.0

        # --- turbulence (drawn first: it takes its share of the budget)
        if turbulence is None:
            tx = np.zeros(h)
            ty = np.zeros(h)
        else:
            amin, amax = (float(t) for t in turbulence)
            if not (np.isfinite(amin) and np.isfinite(amax) and 0 <= amin <= amax):
                raise ValueError(f"turbulence must be (amin, amax) with 0 <= amin <= amax, got {turbulence}")
            tx = _turbulence_profile(h, rng, rng.uniform(amin, amax), turbulence_scale)
            ty = _turbulence_profile(h, rng, rng.uniform(amin, amax), turbulence_scale)
        # what the turbulence and the relief take of the displacement budget
        reserved = float(np.sqrt(tx * tx + ty * ty).max()) if h else 0.0
        waves = np.zeros((0, 5))
        if relief is not None:
            peak, wavelength = (float(r) for r in relief)
            if not (np.isfinite(peak) and peak >= 0 and np.isfinite(wavelength) and wavelength > 0):
                raise ValueError(f"relief must be (peak >= 0, wavelength > 0), got {relief}")
            n = _RELIEF_WAVES
            amp = rng.uniform(0.5, 1.0, n)
            amp *= peak / amp.sum()  # the waves' amplitudes add up to the peak
            k = 2.0 * np.pi / (wavelength * rng.uniform(0.5, 1.5, n))
            direction = rng.uniform(0.0, 2.0 * np.pi, n)
            waves = np.column_stack([amp, amp * rng.uniform(-1.0, 1.0, n) / 3.0, k * np.cos(direction),
                                     k * np.sin(direction), rng.uniform(0.0, 2.0 * np.pi, n)])
            reserved += float(np.hypot(waves[:, 0], waves[:, 1]).sum())
        budget = max_displacement - reserved
        if budget <= 0.05 * max_displacement:
            raise ValueError(
                f"turbulence (and relief) peak {reserved:.3g} px leaves no room within "
                f"max_displacement={max_displacement}"
            )

        # --- smooth part: raw draws, each normalised to its own share
        hx, hy = max(cx, 0.5), max(cy, 0.5)
        us = np.linspace(-cx, cx, min(w, _BOUND_SAMPLES)) if w > 1 else np.zeros(1)
        vs = np.linspace(-cy, cy, min(h, _BOUND_SAMPLES)) if h > 1 else np.zeros(1)
        uu, vv = np.meshgrid(us, vs)
        corners_u = np.array([-hx, hx, -hx, hx])
        corners_v = np.array([-hy, -hy, hy, hy])

        share_shift, share_lin, share_quad = rng.uniform(0.25, 0.45, size=3)

        ang = rng.uniform(0.0, 2.0 * np.pi)
        shift = np.array([np.cos(ang), np.sin(ang)]) * share_shift

        theta, sx, sy, sh = rng.uniform(-1.0, 1.0, size=4)
        lin = np.array([[sx, sh - theta], [theta, sy]])
        lin_norm = np.hypot(*(lin @ np.stack([corners_u, corners_v]))).max()
        lin *= share_lin / lin_norm

        quad = rng.uniform(-1.0, 1.0, size=(2, 3))
        qx = quad[0, 0] * uu**2 + quad[0, 1] * uu * vv + quad[0, 2] * vv**2
        qy = quad[1, 0] * uu**2 + quad[1, 1] * uu * vv + quad[1, 2] * vv**2
        quad *= share_quad / max(np.hypot(qx, qy).max(), 1e-300)

        # --- joint rescale so that max |smooth| over the grid == budget
        def smooth_max(lin_: np.ndarray, quad_: np.ndarray, shift_: np.ndarray) -> float:
            sx_ = lin_[0, 0] * uu + lin_[0, 1] * vv + shift_[0]
            sy_ = lin_[1, 0] * uu + lin_[1, 1] * vv + shift_[1]
            sx_ = sx_ + quad_[0, 0] * uu**2 + quad_[0, 1] * uu * vv + quad_[0, 2] * vv**2
            sy_ = sy_ + quad_[1, 0] * uu**2 + quad_[1, 1] * uu * vv + quad_[1, 2] * vv**2
            sampled = float(np.hypot(sx_, sy_).max())
            # slack between sample points: Lipschitz bound x half diagonal spacing
            du = 2 * hx / max(us.size - 1, 1) if us.size < w else 0.0
            dv = 2 * hy / max(vs.size - 1, 1) if vs.size < h else 0.0
            if du == 0.0 and dv == 0.0:
                return sampled
            g = np.abs(lin_).max() + 2 * np.abs(quad_).max() * (hx + hy)
            return sampled + 2.0 * g * 0.5 * np.hypot(du, dv)

        k = budget / smooth_max(lin, quad, shift)
        lin, quad, shift = lin * k, quad * k, shift * k

        # --- optional cap of the linear part
        if affine_max is not None and np.abs(lin).max() > affine_max:
            lin *= affine_max / np.abs(lin).max()

        # --- invertibility guard: scale the smooth gradient down if needed
        probe = cls(
            affine=np.column_stack([lin, shift]),
            quadratic=quad,
            centre=(cx, cy),
            turbulence_x=np.zeros(0),
            turbulence_y=np.zeros(0),
        )
        smooth_jac = probe.jacobian_bound((h, w))
        relief_slope = float(np.hypot(waves[:, 0], waves[:, 1]) @ np.hypot(waves[:, 2], waves[:, 3]))
        allowed = _JACOBIAN_MAX - max(_max_slope(tx, h), _max_slope(ty, h)) - relief_slope
        if allowed <= 0:
            raise ValueError(f"relief {relief} slopes by {relief_slope:.3g} px/px: the field would fold")
        if smooth_jac > allowed:
            lin *= allowed / smooth_jac
            quad *= allowed / smooth_jac

        return cls(
            affine=np.column_stack([lin, shift]),
            quadratic=quad,
            centre=(cx, cy),
            turbulence_x=tx,
            turbulence_y=ty,
            relief=waves,
        )

    # ---------------------------------------------------------------- private
    def _centred(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.asarray(x, dtype=np.float64) - self.centre[0],
            np.asarray(y, dtype=np.float64) - self.centre[1],
        )


def _check_shape(shape: tuple[int, int]) -> tuple[int, int]:
    if len(shape) != 2:
        raise ValueError(f"shape must be (H, W), got {shape}")
    h, w = int(shape[0]), int(shape[1])
    if h < 1 or w < 1:
        raise ValueError(f"shape must be positive, got {shape}")
    return h, w


def _interp_rows(table: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Linear interpolation of a per-row table at rows ``y`` (clamped)."""
    if table.size == 0:
        return np.zeros(y.shape)
    if table.size == 1:
        return np.full(y.shape, table[0])
    flat = y.reshape(-1)
    out = np.interp(flat, np.arange(table.size, dtype=np.float64), table)
    return out.reshape(y.shape)


def _slope_rows(table: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivative of :func:`_interp_rows` (segment slope, 0 when clamped)."""
    y = np.asarray(y, dtype=np.float64)
    if table.size < 2:
        return np.zeros(y.shape)
    n = table.size
    diffs = np.diff(table)
    safe = np.where(np.isfinite(y), y, 0.0)
    seg = np.clip(np.floor(safe), 0, n - 2).astype(np.intp)
    slope = diffs[seg]
    return np.where((safe < 0) | (safe > n - 1), 0.0, slope)


def _max_slope(table: np.ndarray, h: int) -> float:
    """Largest |slope| of a per-row table over rows ``[0, h - 1]``."""
    m = min(table.size, h) - 1
    if m < 1:
        return 0.0
    return float(np.abs(np.diff(table[: m + 1])).max())


def _detrend(t: np.ndarray) -> np.ndarray:
    if t.size < 2:
        return t - t.mean()
    y = np.arange(t.size, dtype=np.float64)
    coef = np.polyfit(y, t, 1)
    return t - np.polyval(coef, y)


def _turbulence_profile(n: int, rng: np.random.Generator, amplitude: float, scale: float) -> np.ndarray:
    """Zero-mean, detrended row profile with ``max |t| == amplitude``."""
    if amplitude == 0.0:
        return np.zeros(n)
    if n < 2:
        return np.full(n, amplitude)
    y = np.arange(n, dtype=np.float64)
    n_sin = int(rng.integers(3, 5))
    periods = np.exp(rng.uniform(np.log(2.0 * scale / 3.0), np.log(20.0 * scale / 3.0), n_sin))
    # amplitude ~ period (red spectrum: equal slope contribution per sinusoid)
    amps = periods * rng.uniform(0.5, 1.0, n_sin)
    phases = rng.uniform(0.0, 2.0 * np.pi, n_sin)
    sines = (amps[:, None] * np.sin(2.0 * np.pi * y[None, :] / periods[:, None] + phases[:, None])).sum(0)
    walk = np.cumsum(rng.standard_normal(n))
    walk = ndimage.gaussian_filter1d(walk, sigma=scale / 2.0, mode="nearest")
    rng_walk_weight = rng.uniform(0.5, 1.0)
    # Detrended first (pure scan-line signal, distinct from the affine part);
    # on short profiles that may be too steep, so fall back to mean removal.
    for remove in (_detrend, lambda a: a - a.mean()):
        t = remove(sines) / max(np.abs(remove(sines)).max(), 1e-300)
        t = t + rng_walk_weight * remove(walk) / max(np.abs(remove(walk)).max(), 1e-300)
        t = remove(t)
        sigma = 0.0
        while True:
            peak = np.abs(t).max()
            if peak == 0.0:
                return np.zeros(n)
            scaled = t * (amplitude / peak)
            if np.abs(np.diff(scaled)).max() <= _TURBULENCE_SLOPE_MAX:
                return scaled
            # too steep: smooth progressively (bounded by the profile length)
            sigma = max(1.5 * sigma, 1.0)
            if sigma > max(float(n), 2.0):
                break
            t = remove(ndimage.gaussian_filter1d(t, sigma=sigma, mode="nearest"))
    raise ValueError(
        f"turbulence amplitude {amplitude:.3g} px is too large for {n} lines with "
        f"turbulence_scale={scale}: its slope would exceed {_TURBULENCE_SLOPE_MAX} px/line"
    )


def invert(
    field: WarpField,
    xq: np.ndarray,
    yq: np.ndarray,
    *,
    iterations: int = 50,
    tol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Find the base coordinates ``p`` with ``p + d(p) = q``.

    Vectorised Newton iteration (started from ``q - d(q)``), falling back to a
    fixed-point step where the local Jacobian ``I + ∂d/∂p`` is singular.

    Parameters
    ----------
    field : WarpField
        The displacement field (defined on base coordinates).
    xq, yq : array_like
        Distorted-image coordinates ``q`` (column, row), in the base frame;
        broadcast against each other.  Non-finite entries give NaN.
    iterations : int, optional
        Maximum number of Newton iterations.
    tol : float, optional
        Convergence threshold on the residual ``|p + d(p) - q|`` (each
        component, pixels), relaxed by a few ulps of ``|q|``.

    Returns
    -------
    x, y : numpy.ndarray
        float64 base coordinates of the broadcast shape.

    Raises
    ------
    ValueError
        If some point has not converged after ``iterations`` iterations.
    """
    xq, yq = np.broadcast_arrays(np.asarray(xq, dtype=np.float64), np.asarray(yq, dtype=np.float64))
    shape = xq.shape
    qx = xq.reshape(-1).copy()
    qy = yq.reshape(-1).copy()
    finite = np.isfinite(qx) & np.isfinite(qy)
    px = np.full(qx.shape, np.nan)
    py = np.full(qy.shape, np.nan)
    idx = np.flatnonzero(finite)
    ax, ay = qx[idx], qy[idx]
    eps = np.finfo(np.float64).eps
    thx = tol + 8.0 * eps * (np.abs(ax) + 1.0)
    thy = tol + 8.0 * eps * (np.abs(ay) + 1.0)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _newton(field, px, py, shape, idx, ax, ay, thx, thy, iterations)


def _newton(
    field: WarpField,
    px: np.ndarray,
    py: np.ndarray,
    shape: tuple[int, ...],
    idx: np.ndarray,
    ax: np.ndarray,
    ay: np.ndarray,
    thx: np.ndarray,
    thy: np.ndarray,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Newton iteration of :func:`invert` on the active (finite) points."""
    dx, dy = field.displacement(ax, ay)
    cx, cy = ax - dx, ay - dy
    rx = ry = np.zeros(0)
    for it in range(iterations + 1):
        dx, dy = field.displacement(cx, cy)
        rx = cx + dx - ax
        ry = cy + dy - ay
        done = (np.abs(rx) <= thx) & (np.abs(ry) <= thy)
        if done.any():
            px[idx[done]] = cx[done]
            py[idx[done]] = cy[done]
            keep = ~done
            idx, ax, ay, cx, cy = idx[keep], ax[keep], ay[keep], cx[keep], cy[keep]
            rx, ry, thx, thy = rx[keep], ry[keep], thx[keep], thy[keep]
        if idx.size == 0:
            return px.reshape(shape), py.reshape(shape)
        if it == iterations:
            break
        gxx, gxy, gyx, gyy = field.partials(cx, cy)
        a, b, c, e = 1.0 + gxx, gxy, gyx, 1.0 + gyy
        det = a * e - b * c
        ok = np.isfinite(det) & (det > 1e-12)
        safe = np.where(ok, det, 1.0)
        stepx = np.where(ok, (e * rx - b * ry) / safe, rx)
        stepy = np.where(ok, (-c * rx + a * ry) / safe, ry)
        cx = cx - stepx
        cy = cy - stepy
        if not (np.all(np.isfinite(cx)) and np.all(np.isfinite(cy))):
            break
    res = np.maximum(np.abs(rx), np.abs(ry)) if rx.size == idx.size else np.full(idx.size, np.inf)
    worst = float(np.max(np.where(np.isfinite(res), res, np.inf))) if res.size else float("nan")
    raise ValueError(
        f"invert: {idx.size} point(s) did not converge after {iterations} iterations "
        f"(worst residual {worst:.3g} px); the field may not be invertible there"
    )


@dataclass(frozen=True, eq=False)
class SyntheticPair:
    """A base/distorted image pair with the true displacement on the base grid.

    Attributes
    ----------
    base : numpy.ndarray
        ``(bands, H, W)`` float32 base image.
    distorted : numpy.ndarray
        ``(bands, Hd, Wd)`` float32 distorted image, NaN where undefined.
        Its pixel ``(row r, col c)`` is at base-frame coordinate ``(x=c, y=r)``.
    dx, dy : numpy.ndarray
        ``(H, W)`` float64 truth on the base grid: ``x_distorted - x_base``
        and ``y_distorted - y_base``.  The base pixel ``p`` is seen in the
        distorted image at ``p + (dx, dy)[p]``.
    field : WarpField
        The analytic field that produced ``dx, dy``.
    """

    base: np.ndarray
    distorted: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    field: WarpField


def _as_bands(source: np.ndarray) -> np.ndarray:
    src = np.asarray(source, dtype=np.float64)
    if src.ndim == 2:
        src = src[None]
    if src.ndim != 3:
        raise ValueError(f"source must be (bands, H, W) or (H, W), got shape {src.shape}")
    return src


def _sample(src: np.ndarray, rows: np.ndarray, cols: np.ndarray, *, order: int) -> np.ndarray:
    """Spline-sample every band of ``src`` at (rows, cols); NaN outside/near nodata."""
    bands, hs, ws = src.shape
    inside = (rows >= 0) & (rows <= hs - 1) & (cols >= 0) & (cols <= ws - 1)
    coords = np.stack([np.where(inside, rows, -10.0), np.where(inside, cols, -10.0)])
    out = np.empty((bands,) + rows.shape, dtype=np.float64)
    radius = (order + 1) // 2
    for b in range(bands):
        band = src[b]
        bad = ~np.isfinite(band)
        if bad.all():
            out[b] = np.nan
            continue
        if bad.any():
            near = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
            filled = band[near[0], near[1]]
        else:
            filled = band
        if order > 1:
            coeffs = ndimage.spline_filter(filled, order=order, mode="mirror", output=np.float64)
        else:
            coeffs = filled
        vals = ndimage.map_coordinates(
            coeffs, coords, order=order, prefilter=False, mode="constant", cval=np.nan
        )
        if bad.any():
            if radius > 0:
                bad = ndimage.binary_dilation(bad, structure=np.ones((2 * radius + 1,) * 2, bool))
            hit = ndimage.map_coordinates(
                bad.astype(np.float32), coords, order=0, mode="constant", cval=1.0
            )
            vals[hit > 0.5] = np.nan
        vals[~inside] = np.nan
        out[b] = vals
    return out


def _dynamic_range(band: np.ndarray) -> float:
    finite = band[np.isfinite(band)]
    if finite.size == 0:
        return 1.0
    p1, p99 = np.percentile(finite, [1.0, 99.0])
    rng_ = float(p99 - p1)
    if not np.isfinite(rng_) or rng_ <= 0:
        rng_ = float(finite.max() - finite.min())
    return rng_ if rng_ > 0 else 1.0


def make_pair(
    source: np.ndarray,
    *,
    shape: tuple[int, int],
    seed: int,
    max_displacement: float = 15.0,
    turbulence: tuple[float, float] | None = None,
    noise: float = 0.02,
    gain: tuple[float, float] = (0.75, 1.25),
    offset: float = 0.05,
    distorted_shape: tuple[int, int] | None = None,
    margin: int = 32,
    order: int = 3,
    affine_max: float | None = None,
    relief: tuple[float, float] | None = None,
    warp: WarpField | None = None,
) -> SyntheticPair:
    """Cut a base image from ``source`` and render a distorted copy with known truth.

    Parameters
    ----------
    source : numpy.ndarray
        ``(bands, Hs, Ws)`` or ``(Hs, Ws)`` float image; NaN is nodata.  It
        must hold at least ``margin + H`` rows and ``margin + W`` columns; a
        further ``margin`` on the far sides lets the distorted image look
        outside the base area (otherwise those pixels become NaN).
    shape : tuple of int
        ``(H, W)`` of the base image, the crop
        ``source[:, margin:margin + H, margin:margin + W]``.
    seed : int
        Seed of everything.  The field is ``WarpField.random(shape,
        seed=seed, ...)``; the radiometric draws use
        ``default_rng([seed, 1])``.
    max_displacement, turbulence, affine_max, relief
        Passed to :meth:`WarpField.random`.
    noise : float, optional
        Sigma of the Gaussian noise added to each image, as a fraction of the
        dynamic range (p1-p99 of the noise-free base, per band).
    gain : tuple of float, optional
        The distorted image is multiplied by a gain drawn uniformly (per band)
        in this interval.
    offset : float, optional
        The distorted image gets an offset of ``±offset`` x dynamic range
        (random sign, per band).
    distorted_shape : tuple of int, optional
        ``(Hd, Wd)`` of the distorted image (default: ``shape``).  Its pixel
        ``(row r, col c)`` sits at base-frame coordinate ``(x=c, y=r)``.
    margin : int, optional
        Offset of the base crop inside ``source``.
    order : int, optional
        Spline order of the resampling (0-5).
    warp : WarpField, optional
        The displacement to render instead of a random one (``max_displacement``,
        ``turbulence``, ``affine_max`` and ``relief`` are then not used).

    Returns
    -------
    SyntheticPair

    Notes
    -----
    Every distorted pixel ``q`` is mapped to the base frame by
    :func:`invert` (``p + d(p) = q``) and the source is sampled at
    ``p + margin`` with ``scipy.ndimage.map_coordinates(order=order,
    mode='constant', cval=nan)``; the spline prefilter runs on a NaN-free
    copy (nodata filled with the nearest valid pixel) and NaN is re-imposed
    wherever the spline support touches nodata or the sample falls outside
    the source.  Hence, without noise and radiometric change, the distorted
    image at ``p + d(p)`` equals ``base[p]`` up to interpolation error.
    """
    src = _as_bands(source)
    h, w = _check_shape(shape)
    margin = int(margin)
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    if not 0 <= int(order) <= 5:
        raise ValueError(f"order must be in 0..5, got {order}")
    _, hs, ws = src.shape
    if hs < margin + h or ws < margin + w:
        raise ValueError(
            f"source of shape {src.shape[1:]} is too small for a {shape} crop at margin {margin}"
        )
    if noise < 0 or offset < 0 or gain[0] > gain[1]:
        raise ValueError("noise and offset must be >= 0 and gain an interval (low, high)")
    hd, wd = _check_shape(distorted_shape) if distorted_shape is not None else (h, w)

    field = warp if warp is not None else WarpField.random(
        (h, w),
        seed=seed,
        max_displacement=max_displacement,
        affine_max=affine_max,
        turbulence=turbulence,
        relief=relief,
    )

    yq, xq = np.indices((hd, wd), dtype=np.float64)
    px, py = invert(field, xq, yq)
    distorted = _sample(src, py + margin, px + margin, order=int(order))
    base = src[:, margin : margin + h, margin : margin + w].copy()

    rng = np.random.default_rng([int(seed), 1])
    for b in range(src.shape[0]):
        drange = _dynamic_range(base[b])
        sigma = noise * drange
        g = rng.uniform(gain[0], gain[1])
        off = (1.0 if rng.random() < 0.5 else -1.0) * offset * drange
        distorted[b] = g * distorted[b] + off + rng.normal(0.0, sigma, size=(hd, wd))
        base[b] = base[b] + rng.normal(0.0, sigma, size=(h, w))

    yy, xx = np.indices((h, w), dtype=np.float64)
    dx, dy = field.displacement(xx, yy)
    return SyntheticPair(
        base=base.astype(np.float32),
        distorted=distorted.astype(np.float32),
        dx=dx,
        dy=dy,
        field=field,
    )


_HANNING_3x3 = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0]) / 16.0


def seed_affine_experiment(
    source: np.ndarray,
    *,
    size: int = 128,
    seed: int,
    bbar_max: float = 0.15,
    noise_sigma: float = 15.0,
) -> SyntheticPair:
    """Affine-distortion experiment of Paderes, Mikhail & Förstner (1984, sec. 4.5).

    Two ``size x size`` windows are taken from an original image on the
    0-255 grey-level scale.  The second is the first distorted by the affine
    ``z'' = a + B z'`` (window-centred coordinates), where ``B - I``
    (``B-bar``) has independent entries uniform in ``[-bbar_max, bbar_max]``
    and each component of ``a`` is uniform in ``[-2, 2]`` pixels.  White
    Gaussian noise of sigma ``noise_sigma`` grey levels is added to both
    windows, which are then both smoothed with the 3x3 Hanning filter
    ``(1 2 1)^T (1 2 1) / 16``.

    Parameters
    ----------
    source : numpy.ndarray
        ``(bands, Hs, Ws)`` or ``(Hs, Ws)`` image.  If its finite values are
        not already within ``[0, 255]`` (or all lie within ``[0, 1]``) it is
        linearly rescaled from its ``[min, max]`` to ``[0, 255]``.  It must
        leave room for the distorted footprint around the base window.
    size : int, optional
        Window size (pixels).
    seed : int
        Seed of ``numpy.random.default_rng`` (window position, ``B``, ``a``,
        noise).
    bbar_max : float, optional
        Bound of the entries of ``B - I``.
    noise_sigma : float, optional
        Noise sigma in grey levels.

    Returns
    -------
    SyntheticPair
        ``field.affine == [B - I | a]`` with centre ``((size-1)/2,
        (size-1)/2)``; quadratic and turbulence are zero, so ``dx, dy`` are
        linear in ``(x, y)``.  ``base`` and ``distorted`` are
        ``(bands, size, size)`` float32.

    Raises
    ------
    ValueError
        If the source is too small for the window and its distorted footprint.
    """
    src = _as_bands(source).copy()
    size = int(size)
    if size < 3:
        raise ValueError(f"size must be >= 3, got {size}")
    if bbar_max < 0 or noise_sigma < 0:
        raise ValueError("bbar_max and noise_sigma must be >= 0")
    finite = np.isfinite(src)
    if not finite.any():
        raise ValueError("source has no valid pixels")
    lo, hi = float(src[finite].min()), float(src[finite].max())
    if lo < 0.0 or hi > 255.0 or hi <= 1.0:
        src = (src - lo) * (255.0 / (hi - lo)) if hi > lo else np.zeros_like(src)

    rng = np.random.default_rng(seed)
    bbar = rng.uniform(-bbar_max, bbar_max, size=(2, 2))
    shift = rng.uniform(-2.0, 2.0, size=2)
    c = (size - 1) / 2.0
    field = WarpField(
        affine=np.column_stack([bbar, shift]),
        quadratic=np.zeros((2, 3)),
        centre=(c, c),
        turbulence_x=np.zeros(size),
        turbulence_y=np.zeros(size),
    )
    yq, xq = np.indices((size, size), dtype=np.float64)
    px, py = invert(field, xq, yq)

    # window origin (row0, col0): base window and distorted footprint inside the source
    _, hs, ws = src.shape
    pad = 3  # keep the cubic support away from the border
    lo_r = int(np.ceil(max(0.0, -py.min()))) + pad
    hi_r = hs - 1 - pad - int(np.ceil(max(size - 1.0, py.max())))
    lo_c = int(np.ceil(max(0.0, -px.min()))) + pad
    hi_c = ws - 1 - pad - int(np.ceil(max(size - 1.0, px.max())))
    if hi_r < lo_r or hi_c < lo_c:
        raise ValueError(
            f"source of shape {src.shape[1:]} is too small for a {size}-pixel window "
            f"with bbar_max={bbar_max}"
        )
    row0 = int(rng.integers(lo_r, hi_r + 1))
    col0 = int(rng.integers(lo_c, hi_c + 1))

    base = src[:, row0 : row0 + size, col0 : col0 + size].copy()
    distorted = _sample(src, py + row0, px + col0, order=3)
    base += rng.normal(0.0, noise_sigma, size=base.shape)
    distorted += rng.normal(0.0, noise_sigma, size=distorted.shape)
    for b in range(src.shape[0]):
        base[b] = ndimage.convolve(base[b], _HANNING_3x3, mode="nearest")
        distorted[b] = ndimage.convolve(distorted[b], _HANNING_3x3, mode="nearest")

    yy, xx = np.indices((size, size), dtype=np.float64)
    dx, dy = field.displacement(xx, yy)
    return SyntheticPair(
        base=base.astype(np.float32),
        distorted=distorted.astype(np.float32),
        dx=dx,
        dy=dy,
        field=field,
    )
