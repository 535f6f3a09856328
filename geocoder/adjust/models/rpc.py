"""Rational polynomial coefficients (RPC00B) and the RPC sensor model with an affine bias.

:class:`RPC` holds the 90 coefficients and offsets/scales and projects geodetic or ECEF
points; :func:`fit_rpc` fits one to any sensor (terrain-independent, on a 3-D grid);
:class:`RPCModel` adjusts an affine bias compensation in image space (6 parameters), the
usual block adjustment of RPC imagery.  Follows :class:`~geocoder.adjust.sensor.SensorModel`.
Pure numpy; ``rasterio`` is imported lazily only by the :class:`RPC` conversions.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ...geodesy import ecef_to_geodetic
from ..linescanner_geometry import LineScanner
from ..sensor import as_ground, as_params, central_difference

__all__ = ["RPC", "RPCModel", "fit_rpc", "rpc_terms"]


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
        g = as_ground(ground)
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
        p = as_params(params, 6)
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
        p = as_params(params, 6)
        g = as_ground(ground)
        xy = self.rpc.project_ecef(g)
        m = xy.shape[0]
        Jp = np.zeros((m, 2, 6))
        Jp[:, 0, 0] = 1.0
        Jp[:, 0, 1] = xy[:, 0]
        Jp[:, 0, 2] = xy[:, 1]
        Jp[:, 1, 3] = 1.0
        Jp[:, 1, 4] = xy[:, 0]
        Jp[:, 1, 5] = xy[:, 1]
        J_rpc = central_difference(self.rpc.project_ecef, g, np.full(3, self.ground_step))
        B = np.eye(2) + np.array([[p[1], p[2]], [p[4], p[5]]])
        return Jp, B @ J_rpc
