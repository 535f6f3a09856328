"""Rigorous sensor models of airborne line scanners (pushbroom and whiskbroom).

The models follow the sensors described by Allison & Muller (seed 003,
sections 2-3 and Table 1): ASAS (pushbroom, along-track tilts of 15/30/45
degrees, 512 samples per line), CAESAR (pushbroom, 24.3 degree field of view)
and the Daedalus ATM (whiskbroom, 86 degree field of view).  Distortions come
from the scanning geometry itself, from turbulence (roll, pitch and yaw varying
from scan line to scan line), from a slow drift of the attitude (e.g. heading
drift / crab) and from terrain relief.

Frames and conventions
----------------------
* **Ground frame**: a local projected frame, ``X`` east, ``Y`` north, ``Z``
  up, in metres.  Earth curvature and atmospheric refraction are neglected
  (a flat-earth model; at 5000 m flying height and a 2.3 km half-swath the
  curvature drop is ~0.4 m).
* **Image**: ``x`` = column, ``y`` = row, the centre of pixel ``(row r, col
  c)`` is at ``(x=c, y=r)`` (see ``CONVENTIONS.md``).  A row is a scan line;
  the row number is also the time in units of ``line_time`` (row 0 at
  ``t = 0``), and fractional rows are meaningful.  Columns increase to the
  **right** (starboard) of the flight direction, so for a northbound flight
  column increases eastwards and row increases northwards.
* **Body frame**: ``(forward, right, down)``, right-handed.  The attitude is
  applied as ``R = Rz(heading + yaw) @ Ry(pitch) @ Rx(roll)`` from body to
  the local north-east-down frame (aerospace convention): positive roll =
  right wing down (nadir ray swings to the *left*, so image content moves
  to larger columns by about ``roll / ifov``), positive pitch = nose up
  (the view swings *forward*, like a positive tilt), positive yaw = nose to
  the right (clockwise seen from above, like the heading).
* **Track**: the aircraft flies a straight line at constant height and
  ground speed along ``heading``; attitude (including a yaw drift) changes
  only the pointing, not the track.
* **Sensor**: the scan plane of the sensor, in the body frame, contains the
  right axis and the boresight tilted forward by ``tilt`` about the right
  axis.  Pushbroom: flat focal plane, look angle ``atan(u * pitch_f)`` with
  ``u = col - (cols - 1) / 2`` and ``pitch_f = 2 tan(fov / 2) / cols`` (so the
  outer pixel edges, cols -0.5 and cols - 0.5, lie at +-fov/2).  Whiskbroom:
  look angle ``u * ifov`` with ``ifov = fov / cols`` (equal angles,
  panoramic/cylindrical geometry).

The module is pure numpy: every operation is vectorised over arrays of points
(iterative solvers iterate over all points at once).  It is over 500 lines because
:class:`AirborneScanner` (time, attitude, inverse and direct modes, about 330 lines) and the
instrument presets built on it share the private body/ground frame conversions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "ASAS_COLS",
    "ATM_COLS",
    "CAESAR_COLS",
    "AirborneScanner",
    "Attitude",
    "FlightLine",
    "asas",
    "atm",
    "caesar",
    "relief_height_for_one_pixel",
]

Terrain = Callable[[np.ndarray, np.ndarray], np.ndarray]

#: ATM samples per line.  The seed does not give it; Table 1's nadir pixel of
#: 6.28 m at 3000 m implies ifov = 2.093 mrad, i.e. 86 deg / 2.093 mrad = 717.0.
ATM_COLS = 717
#: CAESAR samples per line.  Not given by the seed; Table 1's nadir pixel of
#: 0.49 m at 2000 m with a flat focal plane implies
#: cols = 2 * 2000 * tan(12.15 deg) / 0.49 = 1757.7.
CAESAR_COLS = 1758
#: ASAS samples per line (seed 003, sec. 8: "512 samples per scan line").
ASAS_COLS = 512

_ROW_TOL = 1e-10  # convergence of the direct solver, rows
_Z_TOL = 1e-5  # convergence of the ray/terrain intersection, metres
_MAX_IT = 200


def _as_array(a: object) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


# ----------------------------------------------------------------- rotations
def _body_to_ground(roll, pitch, yaw_total, f, r, d):
    """Rotate body vectors ``(f, r, d)`` to ground ``(X, Y, Z)`` (broadcasting)."""
    # Rx(roll)
    cr, sr = np.cos(roll), np.sin(roll)
    f1, r1, d1 = f, cr * r - sr * d, sr * r + cr * d
    # Ry(pitch)
    cp, sp = np.cos(pitch), np.sin(pitch)
    f2, r2, d2 = cp * f1 + sp * d1, r1, -sp * f1 + cp * d1
    # Rz(heading + yaw) in north-east-down
    cy, sy = np.cos(yaw_total), np.sin(yaw_total)
    n, e, dn = cy * f2 - sy * r2, sy * f2 + cy * r2, d2
    return e, n, -dn


def _ground_to_body(roll, pitch, yaw_total, X, Y, Z):
    """Inverse of :func:`_body_to_ground`."""
    n, e, dn = Y, X, -Z
    cy, sy = np.cos(yaw_total), np.sin(yaw_total)
    f2, r2, d2 = cy * n + sy * e, -sy * n + cy * e, dn
    cp, sp = np.cos(pitch), np.sin(pitch)
    f1, r1, d1 = cp * f2 - sp * d2, r2, sp * f2 + cp * d2
    cr, sr = np.cos(roll), np.sin(roll)
    return f1, cr * r1 + sr * d1, -sr * r1 + cr * d1


# ------------------------------------------------------------------ flight
@dataclass(frozen=True)
class FlightLine:
    """Straight, level flight line in the local ground frame.

    Parameters
    ----------
    x0, y0 : float
        Aircraft ground position (m) at row 0.
    height : float
        Flying height above the datum ``Z = 0`` (m).
    speed : float
        Ground speed (m/s), > 0.
    heading : float
        Radians, clockwise from north (0 = flying north, pi/2 = east).
    line_time : float
        Seconds per scan line, > 0.
    """

    x0: float
    y0: float
    height: float
    speed: float
    heading: float
    line_time: float

    def __post_init__(self) -> None:
        if not (self.height > 0 and self.speed > 0 and self.line_time > 0):
            raise ValueError("height, speed and line_time must be positive")

    @property
    def line_spacing(self) -> float:
        """Ground distance flown per scan line (m)."""
        return self.speed * self.line_time

    @property
    def direction(self) -> np.ndarray:
        """Unit along-track vector ``(X, Y, Z)``."""
        return np.array([np.sin(self.heading), np.cos(self.heading), 0.0])


@dataclass(frozen=True, eq=False)
class Attitude:
    """Per scan line attitude series (radians), linearly interpolated in the row.

    Rows outside ``[0, n - 1]`` take the end values (clamped).

    Parameters
    ----------
    roll, pitch, yaw : ndarray
        1-D series of equal length ``n`` (one value per scan line).
    """

    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray

    def __post_init__(self) -> None:
        arrs = []
        for name in ("roll", "pitch", "yaw"):
            a = np.array(getattr(self, name), dtype=np.float64, copy=True).reshape(-1)
            a.setflags(write=False)
            arrs.append(a)
            object.__setattr__(self, name, a)
        if not (arrs[0].size == arrs[1].size == arrs[2].size) or arrs[0].size < 1:
            raise ValueError(
                "roll, pitch and yaw must be non-empty and of equal length"
            )

    def __len__(self) -> int:
        return int(self.roll.size)

    @classmethod
    def still(cls, rows: int) -> Attitude:
        """Zero roll, pitch and yaw for ``rows`` scan lines."""
        z = np.zeros(int(rows))
        return cls(z, z, z)

    @classmethod
    def turbulent(
        cls,
        rows: int,
        *,
        seed: int,
        roll_sigma: float,
        pitch_sigma: float,
        yaw_sigma: float,
        drift: tuple[float, float, float] = (0.0, 0.0, 0.0),
        correlation_lines: float = 30.0,
        spectrum: str = "gaussian",
        exponent: float = 2.0,
    ) -> Attitude:
        """Seeded turbulent attitude: linear drift plus coloured noise.

        ``spectrum="gaussian"`` (default) smooths white noise with a Gaussian kernel (see
        below); ``spectrum="von-karman"`` draws each angle with the power spectrum
        ``(f^2 + f_c^2)^(-exponent / 2)``, ``f_c = 1 / (2 pi correlation_lines)`` cycles per
        line — flat below the corner and falling as ``f^-exponent`` above it (2 for a
        first-order, Dryden-like process; 5/3 for Kolmogorov turbulence) — scaled to the
        given standard deviations.

        Each angle is ``drift[i] * row + sigma_i * w_i(row)`` where ``w_i`` is
        white Gaussian noise convolved with a Gaussian kernel of standard
        deviation ``correlation_lines / 2`` and scaled to unit process
        variance; its autocorrelation is ``exp(-(lag / correlation_lines)**2)``,
        i.e. ``correlation_lines`` is the 1/e correlation length in lines.

        Parameters
        ----------
        rows : int
            Number of scan lines.
        seed : int
            Seed for ``numpy.random.default_rng``.
        roll_sigma, pitch_sigma, yaw_sigma : float
            Standard deviations of the turbulence (radians).
        drift : tuple of float
            Linear drift of (roll, pitch, yaw) in radians per line.
        correlation_lines : float
            1/e correlation length of the turbulence (lines), > 0.

        Returns
        -------
        Attitude

        Notes
        -----
        The direct model (:meth:`AirborneScanner.ground_to_image`) is unique
        only while the scan plane keeps sweeping forward over the ground: the
        pitch rate (rad/line) must stay below ``line_spacing * cos(tilt)**2 /
        height`` and the yaw rate below ``line_spacing / half_swath``.  The
        rate of this process has standard deviation
        ``sqrt(2) * sigma / correlation_lines``.
        """
        rows = int(rows)
        if correlation_lines <= 0:
            raise ValueError("correlation_lines must be positive")
        if spectrum not in ("gaussian", "von-karman"):
            raise ValueError(f"spectrum must be 'gaussian' or 'von-karman', got {spectrum!r}")
        rng = np.random.default_rng(seed)
        t = np.arange(rows, dtype=np.float64)
        if spectrum == "von-karman":
            n = 2 * rows
            f = np.fft.rfftfreq(n)
            amp = (f**2 + (1.0 / (2 * np.pi * correlation_lines)) ** 2) ** (-exponent / 4)
            amp[0] = 0.0
            out = []
            for sigma, dr in zip((roll_sigma, pitch_sigma, yaw_sigma), drift):
                spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
                w = np.fft.irfft(spec, n)[:rows]
                w = (w - w.mean()) / (w.std() or 1.0)
                out.append(dr * t + sigma * w)
            return cls(*out)
        s = correlation_lines / 2.0
        half = int(np.ceil(4 * s))
        k = np.exp(-0.5 * (np.arange(-half, half + 1) / s) ** 2)
        k /= np.sqrt(np.sum(k**2))  # unit variance of the filtered process
        out = []
        for sigma, dr in zip((roll_sigma, pitch_sigma, yaw_sigma), drift):
            w = rng.standard_normal(rows + 2 * half)
            out.append(dr * t + sigma * np.convolve(w, k, mode="valid"))
        return cls(*out)

    def at(self, row: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Roll, pitch and yaw at (fractional) rows, linear interpolation, clamped ends."""
        row = _as_array(row)
        idx = np.arange(self.roll.size, dtype=np.float64)
        return tuple(
            np.interp(row.ravel(), idx, a).reshape(row.shape)
            for a in (self.roll, self.pitch, self.yaw)
        )


# ----------------------------------------------------------------- scanner
@dataclass(frozen=True, eq=False)
class AirborneScanner:
    """Line scanner on an aircraft: image <-> ground geometry.

    Parameters
    ----------
    flight : FlightLine
        Nominal track.
    attitude : Attitude
        Per line attitude, at least ``rows`` long.
    rows, cols : int
        Image size (scan lines, samples per line).
    fov : float
        Full across-track field of view (radians), from the left edge of
        column 0 to the right edge of column ``cols - 1``.
    kind : {"pushbroom", "whiskbroom"}
        Pushbroom: flat focal plane, ``tan(look) = u * pitch_f``; whiskbroom:
        rotating mirror, ``look = u * ifov`` (``u = col - (cols - 1) / 2``).
    tilt : float
        Along-track tilt of the scan plane (radians, forward positive).
    """

    flight: FlightLine
    attitude: Attitude
    rows: int
    cols: int
    fov: float
    kind: str = "pushbroom"
    tilt: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("pushbroom", "whiskbroom"):
            raise ValueError(
                f"kind must be 'pushbroom' or 'whiskbroom', got {self.kind!r}"
            )
        if self.rows < 1 or self.cols < 1:
            raise ValueError("rows and cols must be positive")
        if len(self.attitude) < self.rows:
            raise ValueError(
                f"attitude has {len(self.attitude)} lines, need >= rows = {self.rows}"
            )
        if not 0 < self.fov < np.pi:
            raise ValueError("fov must be in (0, pi)")
        if abs(self.tilt) >= np.pi / 2:
            raise ValueError("|tilt| must be < pi/2")

    # ------------------------------------------------------------ constants
    @property
    def centre_col(self) -> float:
        """Column of the optical axis, ``(cols - 1) / 2``."""
        return (self.cols - 1) / 2.0

    @property
    def pitch_f(self) -> float:
        """Pushbroom detector pitch over focal length, ``2 tan(fov/2) / cols``."""
        return 2.0 * np.tan(self.fov / 2.0) / self.cols

    def ifov(self) -> float:
        """Nadir instantaneous field of view (rad per pixel).

        Returns
        -------
        float
            Whiskbroom: ``fov / cols``; pushbroom: the angle subtended by the
            central pixel, ``2 atan(pitch_f / 2)``.
        """
        if self.kind == "whiskbroom":
            return self.fov / self.cols
        return 2.0 * np.arctan(self.pitch_f / 2.0)

    def ground_pixel_size(self) -> float:
        """Nadir ground pixel size across track on the datum, ``height * ifov`` (m)."""
        return self.flight.height * self.ifov()

    # ------------------------------------------------------------- geometry
    def _camera_ray(self, col: np.ndarray):
        """Unit ray in the body frame ``(f, r, d)`` for (fractional) columns."""
        u = _as_array(col) - self.centre_col
        ct, st = np.cos(self.tilt), np.sin(self.tilt)
        if self.kind == "pushbroom":
            tu = u * self.pitch_f
            nrm = np.sqrt(1.0 + tu * tu)
            return st / nrm, tu / nrm, ct / nrm
        th = u * self.ifov()
        return st * np.cos(th), np.sin(th), ct * np.cos(th)

    def _col_from_body(self, f, r, d) -> np.ndarray:
        """Column of a body-frame direction (its scan-plane component)."""
        ct, st = np.cos(self.tilt), np.sin(self.tilt)
        cd = st * f + ct * d  # component along the (untilted) boresight
        if self.kind == "pushbroom":
            return r / cd / self.pitch_f + self.centre_col
        return np.arctan2(r, cd) / self.ifov() + self.centre_col

    def position(self, row: np.ndarray | float) -> np.ndarray:
        """Aircraft position at (fractional) rows.

        Parameters
        ----------
        row : array_like
            Row (scan line time in units of ``line_time``).

        Returns
        -------
        ndarray, shape ``row.shape + (3,)``
            ``(X, Y, Z)`` in metres.
        """
        row = _as_array(row)
        fl = self.flight
        s = row * fl.line_spacing
        return np.stack(
            [
                fl.x0 + s * np.sin(fl.heading),
                fl.y0 + s * np.cos(fl.heading),
                np.full(row.shape, fl.height),
            ],
            axis=-1,
        )

    def look_vector(
        self, row: np.ndarray | float, col: np.ndarray | float
    ) -> np.ndarray:
        """Unit viewing ray in the ground frame, attitude applied.

        Parameters
        ----------
        row, col : array_like
            Image coordinates (broadcast together).

        Returns
        -------
        ndarray, shape ``broadcast(row, col).shape + (3,)``
        """
        row, col = np.broadcast_arrays(_as_array(row), _as_array(col))
        roll, pitch, yaw = self.attitude.at(row)
        f, r, d = self._camera_ray(col)
        return np.stack(
            _body_to_ground(roll, pitch, self.flight.heading + yaw, f, r, d), axis=-1
        )

    # ------------------------------------------------------------ inverse
    def image_to_ground(
        self,
        row: np.ndarray | float,
        col: np.ndarray | float,
        *,
        terrain: Terrain | None = None,
        height: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse model: intersect the viewing ray with the ground.

        Parameters
        ----------
        row, col : array_like
            Image coordinates (broadcast together).
        terrain : callable, optional
            ``terrain(X, Y) -> Z`` (vectorised, e.g. a DEM interpolator).  The
            ray is intersected with it by a secant iteration on the ray length
            to better than 1e-5 m in height.  Points that do not converge are
            NaN.
        height : float
            Constant ground height used when ``terrain`` is None.

        Returns
        -------
        X, Y, Z : ndarray
            Ground coordinates (m).
        """
        row, col = np.broadcast_arrays(_as_array(row), _as_array(col))
        p = self.position(row)
        v = self.look_vector(row, col)
        px, py, pz = p[..., 0], p[..., 1], p[..., 2]
        vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            down = np.where(vz < 0, -vz, np.nan)
            if terrain is None:
                s = (pz - height) / down
                return px + s * vx, py + s * vy, pz + s * vz

            def resid(s: np.ndarray) -> np.ndarray:
                return pz + s * vz - _as_array(terrain(px + s * vx, py + s * vy))

            s0 = pz / down
            r0 = resid(s0)
            s1 = s0 + r0 / down  # one fixed-point step
            r1 = resid(s1)
            done = np.abs(r1) < _Z_TOL
            for _ in range(_MAX_IT):
                if done.all():
                    break
                den = r1 - r0
                ok = np.abs(den) > 0
                s2 = np.where(
                    ok, s1 - r1 * (s1 - s0) / np.where(ok, den, 1.0), s1 + r1 / down
                )
                s2 = np.where(done, s1, s2)
                r2 = resid(s2)
                step = np.abs(s2 - s1) * down
                done = (
                    done | ((np.abs(r2) < _Z_TOL) & (step < _Z_TOL)) | (np.abs(r2) == 0)
                )
                s0, r0, s1, r1 = s1, r1, s2, r2
            s1 = np.where(done & (np.abs(r1) < _Z_TOL), s1, np.nan)
            X, Y = px + s1 * vx, py + s1 * vy
            return X, Y, pz + s1 * vz

    # ------------------------------------------------------------- direct
    def _scan_offset(self, t: np.ndarray, X: np.ndarray, Y: np.ndarray, Z: np.ndarray):
        """Body-frame vector to the point and the sine of its angle off the scan plane."""
        p = self.position(t)
        roll, pitch, yaw = self.attitude.at(t)
        f, r, d = _ground_to_body(
            roll,
            pitch,
            self.flight.heading + yaw,
            X - p[..., 0],
            Y - p[..., 1],
            Z - p[..., 2],
        )
        ct, st = np.cos(self.tilt), np.sin(self.tilt)
        g = (ct * f - st * d) / np.sqrt(f * f + r * r + d * d)
        return g, (f, r, d)

    def ground_to_image(
        self, X: np.ndarray | float, Y: np.ndarray | float, Z: np.ndarray | float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Direct model: image coordinates of ground points.

        The row (time) is the root of ``g(t)``, the sine of the along-track
        angle between the point and the scan plane at time ``t``.  ``g``
        decreases as the aircraft passes; it is bracketed around a secant
        estimate from the nominal geometry and refined by the Illinois
        (modified regula falsi) method, all points at once, to 1e-10 rows.
        The column then follows from the across-track angle at that time.

        Parameters
        ----------
        X, Y, Z : array_like
            Ground coordinates (m), broadcast together.

        Returns
        -------
        row, col : ndarray
            Fractional image coordinates (may lie outside the frame; the
            attitude is clamped beyond its ends).  NaN where no root of
            ``g`` could be bracketed.  Points must lie below the aircraft.

        Notes
        -----
        If the attitude varies so fast that the scan plane sweeps backwards
        (see :meth:`Attitude.turbulent`), a point is imaged more than once
        and one of the solutions is returned.
        """
        Xb, Yb, Zb = np.broadcast_arrays(_as_array(X), _as_array(Y), _as_array(Z))
        out_shape = Xb.shape
        X, Y, Z = Xb.ravel(), Yb.ravel(), Zb.ravel()
        fl = self.flight
        a = fl.direction
        s_along = (X - fl.x0) * a[0] + (Y - fl.y0) * a[1]
        t0 = (s_along - (fl.height - Z) * np.tan(self.tilt)) / fl.line_spacing

        def g(t, idx):
            return self._scan_offset(t, X[idx], Y[idx], Z[idx])[0]

        allidx = np.arange(X.size)
        # secant estimate from the nominal guess
        ga = g(t0, allidx)
        gb = g(t0 + 1.0, allidx)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = np.where(gb != ga, t0 - ga / (gb - ga), t0)
        t1 = np.where(np.isfinite(t1), t1, t0)
        # bracket: g(lo) > 0 > g(hi), expanding geometrically
        lo, hi = t1 - 1.0, t1 + 1.0
        glo, ghi = g(lo, allidx), g(hi, allidx)
        w = np.full(X.size, 2.0)
        for _ in range(60):
            bad_lo = ~(glo > 0)
            bad_hi = ~(ghi < 0)
            if not (bad_lo.any() or bad_hi.any()):
                break
            i = np.nonzero(bad_lo)[0]
            lo[i] -= w[i]
            glo[i] = g(lo[i], i)
            j = np.nonzero(bad_hi)[0]
            hi[j] += w[j]
            ghi[j] = g(hi[j], j)
            w[np.union1d(i, j)] *= 2.0
        valid = (glo > 0) & (ghi < 0)
        # Illinois iterations on the active points
        t = np.where(valid, t1, np.nan)
        last = np.zeros(X.size, dtype=np.int8)  # side replaced last: -1 lo, +1 hi
        active = np.nonzero(valid)[0]
        for _ in range(_MAX_IT):
            if active.size == 0:
                break
            l, h, gl, gh = lo[active], hi[active], glo[active], ghi[active]
            tn = (l * gh - h * gl) / (gh - gl)
            tn = np.clip(tn, l, h)
            gn = g(tn, active)
            conv = (
                (np.abs(tn - t[active]) < _ROW_TOL) | (gn == 0) | ((h - l) < _ROW_TOL)
            )
            t[active] = tn
            pos = gn > 0
            # replace lo where g > 0, hi otherwise; Illinois halving of the kept end
            ip, ineg = active[pos], active[~pos]
            lo[ip], glo[ip] = tn[pos], gn[pos]
            hi[ineg], ghi[ineg] = tn[~pos], gn[~pos]
            ghi[ip[last[ip] == -1]] *= 0.5
            glo[ineg[last[ineg] == 1]] *= 0.5
            last[ip], last[ineg] = -1, 1
            active = active[~conv]
        # column from the across-track angle at the solved time
        col = np.full(X.size, np.nan)
        ok = np.nonzero(np.isfinite(t))[0]
        _, (f, r, d) = self._scan_offset(t[ok], X[ok], Y[ok], Z[ok])
        col[ok] = self._col_from_body(f, r, d)
        return t.reshape(out_shape), col.reshape(out_shape)

    # --------------------------------------------------------------- swath
    def swath(self, height: float = 0.0) -> float:
        """Ground width of the swath on flat terrain at ``Z = height`` (m).

        Computed with the model, for the nominal (still) attitude, as the
        distance between the ground points of the outer pixel edges
        (columns -0.5 and cols - 0.5); equal to
        ``2 (H - height) tan(fov / 2) / cos(tilt)``.
        """
        still = dataclasses.replace(self, attitude=Attitude.still(self.rows))
        X, Y, _ = still.image_to_ground(
            0.0, np.array([-0.5, self.cols - 0.5]), height=height
        )
        return float(np.hypot(X[1] - X[0], Y[1] - Y[0]))


# -------------------------------------------------------------- factories
def _make(
    *,
    fov: float,
    cols: int,
    kind: str,
    tilt: float,
    rows: int,
    height: float,
    speed: float,
    heading: float,
    x0: float,
    y0: float,
    line_time: float | None,
    attitude: Attitude | None,
) -> AirborneScanner:
    if line_time is None:
        # square nadir pixels: along-track line spacing = across-track nadir pixel
        probe = AirborneScanner(
            FlightLine(x0, y0, height, speed, heading, 1.0),
            Attitude.still(rows),
            rows,
            cols,
            fov,
            kind,
            tilt,
        )
        line_time = probe.ground_pixel_size() / speed
    flight = FlightLine(x0, y0, height, speed, heading, line_time)
    return AirborneScanner(
        flight,
        attitude if attitude is not None else Attitude.still(rows),
        rows,
        cols,
        fov,
        kind,
        tilt,
    )


def atm(
    *,
    rows: int = 512,
    cols: int = ATM_COLS,
    height: float = 3000.0,
    speed: float = 70.0,
    heading: float = 0.0,
    x0: float = 0.0,
    y0: float = 0.0,
    line_time: float | None = None,
    attitude: Attitude | None = None,
) -> AirborneScanner:
    """ATM-like whiskbroom scanner: 86 degree field of view, 3000 m.

    Parameters
    ----------
    rows, cols : int
        Image size; ``cols`` defaults to :data:`ATM_COLS` (717, derived from
        the 6.28 m nadir pixel of seed 003 Table 1).
    height, speed, heading, x0, y0 : float
        Flight line (see :class:`FlightLine`).
    line_time : float, optional
        Seconds per line; default gives square nadir pixels.
    attitude : Attitude, optional
        Default: still.

    Returns
    -------
    AirborneScanner
    """
    return _make(
        fov=np.deg2rad(86.0), cols=cols, kind="whiskbroom", tilt=0.0, rows=rows, height=height, speed=speed,
        heading=heading, x0=x0, y0=y0, line_time=line_time, attitude=attitude,
    )  # fmt: skip


def caesar(
    *,
    rows: int = 512,
    cols: int = CAESAR_COLS,
    height: float = 2000.0,
    speed: float = 70.0,
    heading: float = 0.0,
    x0: float = 0.0,
    y0: float = 0.0,
    line_time: float | None = None,
    attitude: Attitude | None = None,
) -> AirborneScanner:
    """CAESAR-like nadir pushbroom: 24.3 degree field of view, 2000 m.

    ``cols`` defaults to :data:`CAESAR_COLS` (1758, derived from the 0.49 m
    nadir pixel of seed 003 Table 1).  Other parameters as :func:`atm`.

    Returns
    -------
    AirborneScanner
    """
    return _make(
        fov=np.deg2rad(24.3), cols=cols, kind="pushbroom", tilt=0.0, rows=rows, height=height, speed=speed,
        heading=heading, x0=x0, y0=y0, line_time=line_time, attitude=attitude,
    )  # fmt: skip


def asas(
    *,
    tilt_deg: float = 0.0,
    rows: int = 448,
    cols: int = ASAS_COLS,
    height: float = 5000.0,
    speed: float = 96.0,
    heading: float = 0.0,
    x0: float = 0.0,
    y0: float = 0.0,
    line_time: float | None = 1.0 / 48.0,
    attitude: Attitude | None = None,
) -> AirborneScanner:
    """ASAS-like pushbroom with along-track tilt: 25 degree FOV, 512 samples, 5000 m.

    Defaults follow seed 003: 25 degree full FOV, 5000 m, 512 samples per
    line (sec. 8), 48 lines per second (sec. 9) and 2 m along track
    (96 m/s / 48 Hz).  The nadir pixel is ``2 * 5000 * tan(12.5 deg) / 512 =
    4.33 m`` (the seed quotes a nominal 4.25 m).

    Parameters
    ----------
    tilt_deg : float
        Along-track tilt in degrees (forward positive), e.g. 15, 30, 45.
    rows, cols, height, speed, heading, x0, y0, line_time, attitude
        As :func:`atm`.

    Returns
    -------
    AirborneScanner
    """
    return _make(
        fov=np.deg2rad(25.0), cols=cols, kind="pushbroom", tilt=np.deg2rad(tilt_deg), rows=rows, height=height,
        speed=speed, heading=heading, x0=x0, y0=y0, line_time=line_time, attitude=attitude,
    )  # fmt: skip


# ------------------------------------------------------------- Table 1
def relief_height_for_one_pixel(
    scanner: AirborneScanner, *, tol: float = 1e-9
) -> float:
    """Terrain height at the swath limit that moves the swath-limit pixel by one column.

    The quantity of seed 003 Table 1, computed with the model (still
    attitude, middle row): the ground point ``G0`` of the last pixel centre
    (column ``cols - 1``) on the datum is raised to height ``h`` and ``h`` is
    solved (secant iteration) so that ``ground_to_image(G0 + h)`` lies one
    column further out.

    Parameters
    ----------
    scanner : AirborneScanner
    tol : float
        Convergence in metres.

    Returns
    -------
    float
        Height in metres.

    Notes
    -----
    To first order ``h = p_across / tan(theta)`` with ``theta`` the look angle
    and ``p_across`` the across-track ground pixel at the swath limit: for a
    whiskbroom ``p_across = H ifov / cos(theta)**2`` (so ``h = H ifov /
    (sin cos)``), for a flat-focal-plane pushbroom the ground pixel is
    constant, ``p_across = H pitch_f`` (so ``h ~ 2 H / (cols + 1)``).  Seed
    003 Table 1 uses ``h = p_limit / tan(fov / 2)`` with its own ``p_limit``:
    for ATM ``p_limit = 8.57 m = 6.28 / cos(43 deg)`` (the ground footprint
    along track, not across track), which is why the model gives 12.6 m
    where the table has 9.19 m (ratio ``1 / cos(43 deg) = 1.367``); for
    CAESAR ``p_limit = 0.77 m`` is not derivable from its 0.49 m nadir pixel
    (0.49 / cos^2(12.15 deg) would be 0.51 m), and the model gives 2.27 m
    where the table has 3.55 m (a flat-focal-plane pushbroom reproduces
    3.55 m only with ~1126 samples per line).
    """
    still = dataclasses.replace(scanner, attitude=Attitude.still(scanner.rows))
    row = (scanner.rows - 1) / 2.0
    col = scanner.cols - 1.0
    X0, Y0, _ = still.image_to_ground(row, col, height=0.0)

    def excess(h: float) -> float:
        return float(still.ground_to_image(X0, Y0, h)[1]) - col - 1.0

    h0, e0 = 0.0, -1.0
    h1 = 0.01 * scanner.flight.height
    e1 = excess(h1)
    for _ in range(100):
        h2 = h1 - e1 * (h1 - h0) / (e1 - e0)
        h0, e0, h1 = h1, e1, h2
        e1 = excess(h1)
        if abs(h1 - h0) < tol:
            break
    return float(h1)
