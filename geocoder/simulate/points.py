"""Simulated control, check, tie and edge points for (block) rectification.

Follows the experiments of Paderes, Mikhail & Foerstner (1984), sec. 2.5
(a block of 3 strips x 3 frames, ~60 % sidelap, ~15 % overlap along the
strips, control on a 20 km ground grid, check points on the same grid offset
by 10 km, tie points in the overlaps) and sec. 3 (edge points as control,
eqs. 6-7, and the ten edge configurations of Figure 4).

Data model
----------
The observation data model of the block adjustment,
:mod:`geocoder.adjust.observations` (re-exported here): :class:`GroundPoints` (the
simulator keeps the unperturbed truth in ``true_X``, ``true_Y``, ``true_Z``),
:class:`ImageObservations` (``frame`` indexes the list of scanners), :func:`point_weight`
and :func:`edge_weight`.  Coordinates are WGS84 ECEF metres for satellite frames
(:class:`~geocoder.adjust.linescanner_geometry.LineScanner`) and the local ground frame
(``X`` east, ``Y`` north, ``Z`` up) for airborne frames
(:class:`~geocoder.simulate.airborne.AirborneScanner`).

Ground grids
------------
Regular grids are laid out in the local tangent plane (east, north) at an
origin on the ellipsoid and dropped along the ellipsoid normal to the target
height (a constant or ``terrain(lat, lon)``, radians in, metres out); the
scale error of this mapping is below 0.1 % over a few hundred kilometres.
For airborne frames the grid is directly in ``(X, Y)`` with
``Z = terrain(X, Y)``.

Perturbations (sec. 2.5): ground coordinates ``N(0, 15 m)`` per axis; image
coordinates ``U(-0.5, 0.5) + N(0, 0.5)`` pixels per axis (standard deviation
``sqrt(0.25 + 1/12) = 0.577`` px); edge points ``U(-0.5, 0.5) + N(0, 0.5)``
across and ``U(-0.5, 0.5) + N(0, 25)`` along the edge.

Pure numpy, vectorised over points; all randomness takes a ``seed``
(``numpy.random.default_rng``); no file I/O.  The module is over 500 lines because the
point generators of sec. 2.5 and the ten edge configurations of sec. 3 (Figure 4) share their
grid, border and plane helpers; it holds no other concept.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..adjust.linescanner_geometry import LineScanner
from ..adjust.observations import KINDS, ROLES, GroundPoints, ImageObservations, edge_weight, point_weight  # noqa: F401
from ..geodesy import OMEGA_EARTH, ecef_to_geodetic, geodetic_to_ecef
from .satellite import landsat_mss_like

__all__ = [
    "EDGE_CONFIGURATIONS",
    "GroundPoints",
    "ImageObservations",
    "block_of_strips",
    "edge_points",
    "edge_weight",
    "grid_points",
    "observe",
    "perturb_ground",
    "perturbation",
    "point_weight",
    "tie_points",
]

Seed = int | np.random.Generator | None
Heights = float | Callable[[np.ndarray, np.ndarray], Any]

#: The ten edge configurations of seed Figure 4 (sec. 3.2).
EDGE_CONFIGURATIONS = {
    1: "pairs at the same point on a regular grid, edges at 90 deg",
    2: "as 1, angle between the edges uniform in 60..90 deg",
    3: "as 1, angle between the edges uniform in 30..90 deg",
    4: "as 1, arbitrary edge directions",
    5: "as 1, one point of a pair displaced by U(-100, 100) px per axis",
    6: "as 2, one point of a pair displaced by U(-100, 100) px per axis",
    7: "as 3, one point of a pair displaced by U(-100, 100) px per axis",
    8: "as 4, one point of a pair displaced by U(-100, 100) px per axis",
    9: "pairs at the same point, random positions, edges at 90 deg (= one control point)",
    10: "arbitrary positions and directions of every edge point",
}


# --------------------------------------------------------------------------- #
# Perturbations
# --------------------------------------------------------------------------- #
def _f64(a: ArrayLike) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


def perturbation(
    shape: int | tuple[int, ...], *, sigma: ArrayLike = 0.5, uniform: ArrayLike = 0.0, seed: Seed
) -> np.ndarray:
    """Random errors ``U(-uniform, uniform) + N(0, sigma)``.

    Parameters
    ----------
    shape : int or tuple of int
        Output shape.
    sigma : array_like
        Standard deviation of the normal part (broadcast against ``shape``).
    uniform : array_like
        Half range of the uniform part (broadcast against ``shape``).
    seed : int or Generator or None
        For ``numpy.random.default_rng``.

    Returns
    -------
    ndarray
        Errors with mean 0 and variance ``sigma^2 + uniform^2 / 3``.
    """
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1.0, 1.0, shape) * _f64(uniform)
    return u + rng.standard_normal(shape) * _f64(sigma)


def perturb_ground(ground: GroundPoints, *, sigma: ArrayLike = 15.0, seed: Seed) -> GroundPoints:
    """Perturb the a-priori ground coordinates: ``true + N(0, sigma)`` per axis.

    The perturbation replaces any previous one (it starts from the truth).
    The a-priori ``sigma`` field is left unchanged.

    Parameters
    ----------
    ground : GroundPoints
    sigma : array_like
        Standard deviation (m), scalar or per axis ``(3,)``; 15 m in sec. 2.5.
    seed : int or Generator or None

    Returns
    -------
    GroundPoints
    """
    d = perturbation((len(ground), 3), sigma=np.broadcast_to(_f64(sigma), (3,)), seed=seed)
    return dataclasses.replace(ground, X=ground.true_X + d[:, 0], Y=ground.true_Y + d[:, 1], Z=ground.true_Z + d[:, 2])


# --------------------------------------------------------------------------- #
# Geometry helpers (satellite ECEF or airborne local frame)
# --------------------------------------------------------------------------- #
def _is_ecef(scanner: Any) -> bool:
    return isinstance(scanner, LineScanner)


def _image_to_ground(scanner: Any, row: ArrayLike, col: ArrayLike, heights: Heights) -> tuple[np.ndarray, ...]:
    if callable(heights):
        return scanner.image_to_ground(row, col, terrain=heights)
    return scanner.image_to_ground(row, col, height=float(heights))


def _inside(scanner: Any, row: np.ndarray, col: np.ndarray, margin: float) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(row)
            & np.isfinite(col)
            & (row >= margin)
            & (row <= scanner.rows - 1 - margin)
            & (col >= margin)
            & (col <= scanner.cols - 1 - margin)
        )


class _Plane:
    """Local (east, north) plane: tangent plane at an ellipsoid origin (ECEF) or the airborne ``(X, Y)``."""

    def __init__(self, ecef: bool, origin: tuple[float, float]) -> None:
        self.ecef = ecef
        self.origin = origin
        if ecef:
            lat, lon = np.deg2rad(origin[0]), np.deg2rad(origin[1])
            self.O = np.array(geodetic_to_ecef(lat, lon, 0.0))
            sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
            self.e = np.array([-so, co, 0.0])
            self.n = np.array([-sl * co, -sl * so, cl])

    def to_plane(self, X: np.ndarray, Y: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.ecef:
            return X - self.origin[0], Y - self.origin[1]
        d = np.stack([X, Y, Z], axis=-1) - self.O
        return d @ self.e, d @ self.n

    def from_plane(self, E: np.ndarray, N: np.ndarray, heights: Heights) -> tuple[np.ndarray, ...]:
        if not self.ecef:
            X, Y = E + self.origin[0], N + self.origin[1]
            Z = heights(X, Y) if callable(heights) else heights
            return X, Y, np.broadcast_to(_f64(Z), X.shape).copy()
        Q = self.O + E[..., None] * self.e + N[..., None] * self.n
        lat, lon, _ = ecef_to_geodetic(Q[..., 0], Q[..., 1], Q[..., 2])
        h = heights(lat, lon) if callable(heights) else heights
        return geodetic_to_ecef(lat, lon, np.broadcast_to(_f64(h), lat.shape))


def _default_origin(scanner: Any) -> tuple[float, float]:
    """Ground point of the frame centre at height 0: (lat, lon) degrees or (X, Y)."""
    X, Y, Z = scanner.image_to_ground((scanner.rows - 1) / 2.0, (scanner.cols - 1) / 2.0, height=0.0)
    if not _is_ecef(scanner):
        return float(X), float(Y)
    lat, lon, _ = ecef_to_geodetic(X, Y, Z)
    return float(np.rad2deg(lat)), float(np.rad2deg(lon))


def _border(scanner: Any, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 1.0, n)
    r1, c1 = scanner.rows - 1.0, scanner.cols - 1.0
    row = np.concatenate([0 * t, t * r1, 0 * t + r1, (1 - t) * r1])
    col = np.concatenate([t * c1, 0 * t + c1, (1 - t) * c1, 0 * t])
    return row, col


def _as_list(scanners: Any) -> list:
    return list(scanners) if isinstance(scanners, (list, tuple)) else [scanners]


# --------------------------------------------------------------------------- #
# Point generators
# --------------------------------------------------------------------------- #
def grid_points(
    scanners: Any,
    *,
    spacing: float,
    role: str,
    offset: tuple[float, float] = (0.0, 0.0),
    heights: Heights = 0.0,
    origin: tuple[float, float] | None = None,
    margin: float = 0.0,
    id_start: int = 0,
    sigma: ArrayLike = 15.0,
) -> GroundPoints:
    """Points of a regular ground grid that fall inside one or more frames.

    Grid nodes are ``(offset[0] + i spacing, offset[1] + j spacing)`` in the
    local (east, north) plane at ``origin`` (see the module docstring); nodes
    whose true projection lies inside at least one frame
    (``margin <= row <= rows - 1 - margin``, likewise columns) are kept.
    The returned points are unperturbed (``X = true_X``); see
    :func:`perturb_ground`.

    Parameters
    ----------
    scanners : LineScanner or AirborneScanner, or a list of them
        The frames (all of one type).
    spacing : float
        Grid spacing (m), e.g. 20 km.
    role : {"control", "check", "tie"}
        Role of all points.
    offset : tuple of float
        Grid offset (east, north) in metres, e.g. ``(10e3, 10e3)`` for the
        check points of sec. 2.5.
    heights : float or callable
        Ellipsoidal height (m), or ``terrain(lat, lon)`` (radians) for
        satellite frames, ``terrain(X, Y)`` for airborne frames.
    origin : tuple of float, optional
        Grid origin: ``(lat, lon)`` in degrees (satellite) or ``(X, Y)``
        (airborne).  Default: the centre of the first frame at height 0, so
        grids built from the same frames share the origin.
    margin : float
        Keep points at least this many pixels inside a frame.
    id_start : int
        Id of the first point (ids are consecutive).
    sigma : array_like
        A-priori standard deviation per axis (m), scalar or ``(3,)``.

    Returns
    -------
    GroundPoints
    """
    if not spacing > 0:
        raise ValueError("spacing must be > 0")
    sc = _as_list(scanners)
    ecef = _is_ecef(sc[0])
    plane = _Plane(ecef, origin if origin is not None else _default_origin(sc[0]))
    Es, Ns = [], []
    for s in sc:
        r, c = _border(s)
        for h in (0.0, 10e3):  # heights span the relief of any reasonable terrain
            E, N = plane.to_plane(*s.image_to_ground(r, c, height=h))
            Es.append(E)
            Ns.append(N)
    E, N = np.concatenate(Es), np.concatenate(Ns)
    i = np.arange(np.floor((np.nanmin(E) - offset[0]) / spacing) - 1, np.ceil((np.nanmax(E) - offset[0]) / spacing) + 2)
    j = np.arange(np.floor((np.nanmin(N) - offset[1]) / spacing) - 1, np.ceil((np.nanmax(N) - offset[1]) / spacing) + 2)
    EE, NN = np.meshgrid(offset[0] + i * spacing, offset[1] + j * spacing, indexing="xy")
    X, Y, Z = plane.from_plane(EE.ravel(), NN.ravel(), heights)
    keep = np.zeros(X.shape, dtype=bool)
    for s in sc:
        row, col = s.ground_to_image(X, Y, Z)
        keep |= _inside(s, row, col, margin)
    X, Y, Z = X[keep], Y[keep], Z[keep]
    n = X.size
    return GroundPoints(
        id=id_start + np.arange(n), X=X, Y=Y, Z=Z, role=np.full(n, role), true_X=X, true_Y=Y, true_Z=Z, sigma=sigma
    )


def observe(
    scanners: Any,
    ground: GroundPoints,
    *,
    seed: Seed,
    image_uniform: float = 0.5,
    image_sigma: float = 0.5,
    weight_sigma: float = 0.5,
    margin: float = 0.0,
) -> ImageObservations:
    """Project every ground point into every frame it falls in, and perturb.

    The *true* ground point is projected with ``ground_to_image``; it is
    observed in a frame if the true image point lies inside it (see
    :func:`grid_points` for ``margin``).  The measured coordinates are the
    true ones plus ``U(-image_uniform, image_uniform) + N(0, image_sigma)``
    per axis, so they may fall up to a few pixels outside the frame.
    Observations are ordered by frame, then by point.

    Parameters
    ----------
    scanners : scanner or list of scanners
        True frame geometry; ``frame`` indexes this list.
    ground : GroundPoints
    seed : int or Generator or None
        For the image perturbation.
    image_uniform : float
        Half range of the uniform error (px); 0.5 in the seed (discretisation).
    image_sigma : float
        Standard deviation of the normal error (px); 0.5 in the seed.
    weight_sigma : float
        Standard deviation used for the weight matrix ``I / weight_sigma^2``
        (the seed's nominal 0.5 px; the actual error has
        ``sqrt(image_sigma^2 + image_uniform^2 / 3)``).
    margin : float
        Observe only points at least this many pixels inside a frame.

    Returns
    -------
    ImageObservations
    """
    sc = _as_list(scanners)
    fr, pt, rr, cc = [], [], [], []
    for k, s in enumerate(sc):
        row, col = s.ground_to_image(ground.true_X, ground.true_Y, ground.true_Z)
        ok = _inside(s, row, col, margin)
        fr.append(np.full(int(ok.sum()), k))
        pt.append(ground.id[ok])
        rr.append(row[ok])
        cc.append(col[ok])
    row, col = np.concatenate(rr), np.concatenate(cc)
    m = row.size
    d = perturbation((m, 2), sigma=image_sigma, uniform=image_uniform, seed=seed)
    return ImageObservations(
        frame=np.concatenate(fr),
        point=np.concatenate(pt),
        row=row + d[:, 1],
        col=col + d[:, 0],
        true_row=row,
        true_col=col,
        weight=point_weight(weight_sigma),
        kind=np.full(m, "point"),
        theta=np.full(m, np.nan),
    )


def _grid_fractions(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid of ``n = k^2`` or quincunx of ``n = k^2 + (k-1)^2`` points, fractions of the frame."""
    k = round(np.sqrt(n))
    if k * k == n:
        f = (np.arange(k) + 0.5) / k
        a, b = np.meshgrid(f, f, indexing="ij")
        return a.ravel(), b.ravel()
    k = round((1 + np.sqrt(2 * n - 1)) / 2)
    if k >= 2 and k * k + (k - 1) ** 2 == n:
        a1, b1 = _grid_fractions(k * k)
        g = np.arange(1, k) / k
        a2, b2 = np.meshgrid(g, g, indexing="ij")
        return np.concatenate([a1, a2.ravel()]), np.concatenate([b1, b2.ravel()])
    raise ValueError(f"grid configurations need n_pairs = k^2 or k^2 + (k-1)^2 (25, 41, 61, ...), got {n}")


def edge_points(
    scanner: Any,
    *,
    n_pairs: int,
    seed: Seed,
    configuration: int,
    frame: int = 0,
    heights: Heights = 0.0,
    sigma_p: float = 0.5,
    sigma_l: float = 25.0,
    image_uniform: float = 0.5,
    displacement: float = 100.0,
    margin: float = 0.0,
    id_start: int = 0,
    sigma: ArrayLike = 15.0,
) -> tuple[GroundPoints, ImageObservations]:
    """Pairs of edge points as control, one of the ten configurations of sec. 3.2.

    See :data:`EDGE_CONFIGURATIONS`.  In configurations 1-4 and 9 both edge
    points of a pair lie at the same image point and share one ground point
    (two observations of it), so configuration 9 is exactly one control
    point per pair.  Otherwise every edge point is its own ground point.
    Grid configurations (1-8) place the pairs at cell centres of a ``k x k``
    grid over the frame (``n_pairs = k^2``) or of a quincunx
    (``n_pairs = k^2 + (k-1)^2``, e.g. 25, 41, 61, 85, 113, 145 as in Table 6).
    Angles: the first edge of a pair has a uniform direction in ``[0, pi)``.

    The measured image point is moved *along* the edge by
    ``U(-u, u) + N(0, sigma_l)`` (it stays on the same edge up to the
    across error) and *across* by ``U(-u, u) + N(0, sigma_p)``; the weight is
    :func:`edge_weight` with ``sigma_p`` and ``kappa = sigma_l / sigma_p``.
    Ground points are unperturbed (see :func:`perturb_ground`), role
    ``"control"``.

    Parameters
    ----------
    scanner : LineScanner or AirborneScanner
        True geometry of the frame.
    n_pairs : int
        Number of edge pairs.
    seed : int or Generator or None
    configuration : int
        1..10.
    frame : int
        Frame index stored in the observations.
    heights : float or callable
        Terrain (see :func:`grid_points`).
    sigma_p, sigma_l : float
        Normal error across / along the edge (px): 0.5 and 25 in the seed.
    image_uniform : float
        Half range of the uniform error in both directions (px).
    displacement : float
        Configurations 5-8: half range (px) of the displacement of the second
        point of a pair (clipped to the frame).
    margin : float
        Keep true edge points at least this many pixels inside the frame.
    id_start : int
        First ground point id.
    sigma : array_like
        A-priori ground standard deviation (m).

    Returns
    -------
    ground : GroundPoints
    obs : ImageObservations
        ``2 * n_pairs`` edge observations; pair ``i`` is observations ``2i, 2i+1``.
    """
    if configuration not in EDGE_CONFIGURATIONS:
        raise ValueError(f"configuration must be 1..10, got {configuration}")
    rng = np.random.default_rng(seed)
    n = int(n_pairs)
    r_lo, r_hi = margin, scanner.rows - 1 - margin
    c_lo, c_hi = margin, scanner.cols - 1 - margin
    base = (configuration - 1) % 4 + 1 if configuration <= 8 else (1 if configuration == 9 else 4)
    # positions
    if configuration <= 8:
        fa, fb = _grid_fractions(n)
        r1, c1 = r_lo + fa * (r_hi - r_lo), c_lo + fb * (c_hi - c_lo)
    else:
        r1, c1 = rng.uniform(r_lo, r_hi, n), rng.uniform(c_lo, c_hi, n)
    if configuration in (5, 6, 7, 8):
        r2 = np.clip(r1 + rng.uniform(-displacement, displacement, n), r_lo, r_hi)
        c2 = np.clip(c1 + rng.uniform(-displacement, displacement, n), c_lo, c_hi)
    elif configuration == 10:
        r2, c2 = rng.uniform(r_lo, r_hi, n), rng.uniform(c_lo, c_hi, n)
    else:
        r2, c2 = r1, c1
    shared = configuration in (1, 2, 3, 4, 9)
    # directions
    th1 = rng.uniform(0.0, np.pi, n)
    if base == 1:
        th2 = th1 + np.pi / 2
    elif base in (2, 3):
        lo = np.deg2rad(60.0 if base == 2 else 30.0)
        th2 = th1 + rng.choice([-1.0, 1.0], n) * rng.uniform(lo, np.pi / 2, n)
    else:
        th2 = rng.uniform(0.0, np.pi, n)
    th2 = np.remainder(th2, np.pi)
    # interleave pairs: observation 2i, 2i+1
    tr = np.stack([r1, r2], axis=1).ravel()
    tc = np.stack([c1, c2], axis=1).ravel()
    th = np.stack([th1, th2], axis=1).ravel()
    # ground points
    if shared:
        X, Y, Z = _image_to_ground(scanner, r1, c1, heights)
        ids = id_start + np.arange(n)
        obs_pt = np.repeat(ids, 2)
    else:
        X, Y, Z = _image_to_ground(scanner, tr, tc, heights)
        ids = id_start + np.arange(2 * n)
        obs_pt = ids
    ground = GroundPoints(
        id=ids, X=X, Y=Y, Z=Z, role=np.full(ids.size, "control"), true_X=X, true_Y=Y, true_Z=Z, sigma=sigma
    )
    # perturbation along (cos, sin) and across (-sin, cos), (x, y) order
    along = perturbation(2 * n, sigma=sigma_l, uniform=image_uniform, seed=rng)
    across = perturbation(2 * n, sigma=sigma_p, uniform=image_uniform, seed=rng)
    c, s = np.cos(th), np.sin(th)
    obs = ImageObservations(
        frame=np.full(2 * n, frame),
        point=obs_pt,
        row=tr + along * s + across * c,
        col=tc + along * c - across * s,
        true_row=tr,
        true_col=tc,
        weight=edge_weight(th, sigma_p=sigma_p, kappa=sigma_l / sigma_p),
        kind=np.full(2 * n, "edge"),
        theta=th,
    )
    return ground, obs


# --------------------------------------------------------------------------- #
# Block of strips
# --------------------------------------------------------------------------- #
def _re_epoch(scanner: LineScanner, t_f: float) -> LineScanner:
    """The same physical orbit with the epoch moved to ``t_f`` (s after the old one).

    ``M0' = M0 + n t_f`` and ``raan' = raan - OMEGA_EARTH t_f`` (the ECI frame
    coinciding with ECEF at the new epoch); ``t0`` is relative to the new epoch.
    """
    o = scanner.orbit
    orbit = dataclasses.replace(
        o,
        mean_anomaly0=float(o.mean_anomaly0 + o.mean_motion * t_f),
        raan=float(np.remainder(o.raan - OMEGA_EARTH * t_f, 2 * np.pi)),
    )
    return scanner.replace(orbit=orbit)


def block_of_strips(
    *,
    strips: int = 3,
    frames: int = 3,
    sidelap: float = 0.6,
    overlap: float = 0.15,
    seed: int | None,
    lat0: float = 58.5,
    lon0: float = -98.0,
    rows: int = 2340,
    cols: int = 3240,
    altitude: float = 917e3,
    swath: float = 185e3,
    line_spacing: float = 79.0,
    kind: str = "pushbroom",
    descending: bool = True,
    position_sigma: float = 15.0,
    attitude_sigma: float = 5e-5,
) -> list[LineScanner]:
    """Satellite frames of a block of strips (sec. 2.5: 3 x 3 frames at 58.5 deg N).

    Strip ``s`` is a LANDSAT-MSS-like orbit (:func:`landsat_mss_like`) that
    passes at its epoch over the ground point of the *central* strip's centre
    frame at row ``(rows - 1) / 2`` and column
    ``(cols - 1) / 2 + (s - (strips - 1) / 2) (1 - sidelap) cols``, i.e. the
    neighbouring orbit shifted across track by ``1 - sidelap`` swaths.  Frame
    ``f`` of a strip is the time window of the same orbit centred at
    ``t_f = (f - (frames - 1) / 2) (1 - overlap) rows line_time``; its orbit
    elements are re-referenced to the epoch ``t_f`` (same physical orbit,
    ``M0 += n t_f``, ``raan -= OMEGA_EARTH t_f``) so that each frame's time
    (and its deviation polynomials) is centred on the frame.  The image size
    does not affect the cost of the point simulation.

    Parameters
    ----------
    strips, frames : int
        Number of strips and frames per strip.
    sidelap, overlap : float
        Fractions of the swath shared by neighbouring strips and of the frame
        length shared by consecutive frames.
    seed : int or None
        Random cubic deviations per frame, drawn in frame order from one
        generator with the scales of :func:`landsat_mss_like` (coefficient
        ``k`` of a position / attitude component has standard deviation
        ``position_sigma / T^k`` / ``attitude_sigma / T^k``, ``T`` half the
        frame duration); ``None``: ideal frames.
    lat0, lon0 : float
        Block centre (degrees).
    rows, cols, altitude, swath, line_spacing, kind, descending : optional
        Frame geometry, see :func:`landsat_mss_like`.
    position_sigma, attitude_sigma : float
        Scales of the random deviations.

    Returns
    -------
    list of LineScanner
        ``strips * frames`` frames, numbered along the strips: frame
        ``s * frames + f``.
    """
    if not (0 <= sidelap < 1 and 0 <= overlap < 1):
        raise ValueError("sidelap and overlap must be in [0, 1)")
    geom: dict[str, Any] = {
        "rows": rows, "cols": cols, "altitude": altitude, "swath": swath, "line_spacing": line_spacing,
        "kind": kind, "descending": descending, "position_sigma": position_sigma, "attitude_sigma": attitude_sigma,
    }  # fmt: skip
    centre = landsat_mss_like(lat0=lat0, lon0=lon0, **geom)
    rng = np.random.default_rng(seed)
    half = max(rows * centre.orbit.line_time / 2.0, 1e-3)
    dev_scale = np.repeat([position_sigma, attitude_sigma], 3)[:, None] / half ** np.arange(4)[None, :]
    out: list[LineScanner] = []
    for s in range(strips):
        dc = (s - (strips - 1) / 2.0) * (1.0 - sidelap) * cols
        X, Y, Z = centre.image_to_ground((rows - 1) / 2.0, centre.centre_col + dc, height=0.0)
        lat, lon, _ = ecef_to_geodetic(X, Y, Z)
        strip = landsat_mss_like(lat0=float(np.rad2deg(lat)), lon0=float(np.rad2deg(lon)), **geom)
        for f in range(frames):
            t_f = (f - (frames - 1) / 2.0) * (1.0 - overlap) * rows * strip.orbit.line_time
            sc = _re_epoch(strip, t_f)
            if seed is not None:
                sc = sc.replace(deviations=rng.standard_normal((6, 4)) * dev_scale)
            out.append(sc)
    return out


def tie_points(
    scanners: Any,
    *,
    per_overlap: int,
    seed: Seed,
    heights: Heights = 0.0,
    candidates: int | None = None,
    min_fraction: float = 0.02,
    margin: float = 0.0,
    id_start: int = 0,
    sigma: ArrayLike = (np.inf, np.inf, 15.0),
) -> GroundPoints:
    """Tie points: random ground points in the overlaps of pairs of frames.

    For each frame ``i``, ``candidates`` image points are drawn uniformly over
    the frame and intersected with the terrain; for every later frame ``j``
    the candidates that project inside ``j`` form the overlap ``(i, j)``.
    Overlaps covering less than ``min_fraction`` of frame ``i`` are skipped;
    otherwise up to ``per_overlap`` unused candidates are taken.  Every tie
    point is thus inside at least two frames (more where overlaps overlap).
    The points are unperturbed; by default the a-priori sigma leaves ``X, Y``
    free and constrains the height with 15 m (sec. 2.5: "the ground elevation
    of tie points were constrained to its a-priori value").

    Parameters
    ----------
    scanners : list of scanners
    per_overlap : int
        Points per overlapping pair.
    seed : int or Generator or None
    heights : float or callable
        Terrain (see :func:`grid_points`).
    candidates : int, optional
        Candidates per frame; default ``50 * per_overlap``.
    min_fraction : float
        Minimum overlap (fraction of the candidates of frame ``i``).
    margin : float
        Keep points at least this many pixels inside both frames.
    id_start : int
        First point id.
    sigma : array_like
        A-priori standard deviation per axis (m).

    Returns
    -------
    GroundPoints
        Role ``"tie"``, ordered by overlap ``(i, j)``.
    """
    sc = _as_list(scanners)
    rng = np.random.default_rng(seed)
    K = int(candidates) if candidates is not None else 50 * int(per_overlap)
    Xs, Ys, Zs = [], [], []
    for i, si in enumerate(sc):
        r = rng.uniform(margin, si.rows - 1 - margin, K)
        c = rng.uniform(margin, si.cols - 1 - margin, K)
        X, Y, Z = _image_to_ground(si, r, c, heights)
        used = ~np.isfinite(X)
        for sj in sc[i + 1 :]:
            row, col = sj.ground_to_image(X, Y, Z)
            hit = _inside(sj, row, col, margin)
            if hit.mean() < min_fraction:
                continue
            idx = np.flatnonzero(hit & ~used)[: int(per_overlap)]
            used[idx] = True
            Xs.append(X[idx])
            Ys.append(Y[idx])
            Zs.append(Z[idx])
    X, Y, Z = (np.concatenate(a) if a else np.zeros(0) for a in (Xs, Ys, Zs))
    n = X.size
    return GroundPoints(
        id=id_start + np.arange(n), X=X, Y=Y, Z=Z, role=np.full(n, "tie"), true_X=X, true_Y=Y, true_Z=Z, sigma=sigma
    )
