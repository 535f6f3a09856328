"""The mosaic's block adjustment: control and tie matches -> one :class:`~geocoder.adjust.solver.Problem`.

Each scene is a :class:`~geocoder.adjust.models.MapPolynomial` (map coordinates of the
output CRS -> scene pixel), or a sensor model of what the scene carries (a line scanner or
an RPC, :mod:`geocoder.mosaic.sensors`). Control points are reference matches (known map
position, the scene pixel observed); tie points are matches between two overlapping scenes
(unknown map position, observed in both). Heights come from a DEM (0 without one): a control
point's is known, a tie point's is held to the DEM at its position. The problem goes to the
existing Schur-reduced solver (seed 000 eq 5), gathered on one node.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..adjust.models import MapPolynomial
from ..adjust.solver import AdjustOptions, AdjustResult, Frame, Problem, adjust


@dataclass(frozen=True)
class Matches:
    """Matched points: ``a`` in scene ``i`` (or the map, ``i = -1``), ``b`` in scene ``j``.

    ``sigma`` is the matching precision ``(sigma_x, sigma_y)`` in pixels of scene ``j`` (and
    ``i``): the standard deviations of the least-squares match (its covariance has no
    ``x``/``y`` correlation term in :class:`~geocoder.match.tiepoints.TiePoints`).
    ``ground_sigma`` (control points only, ``(n,)``, map units): the standard deviation of
    each point's map coordinates; None: the problem's ``control_sigma``.
    """

    i: int
    j: int
    a: np.ndarray  # (n, 2)
    b: np.ndarray  # (n, 2)
    sigma: np.ndarray  # (n, 2)
    ground_sigma: np.ndarray | None = None  # (n,)

    def __len__(self) -> int:
        return len(self.sigma)


def connected_scenes(n: int, control: list[Matches], ties: list[Matches], *, min_points: int,
                     min_given: int = 3) -> np.ndarray:
    """Scenes tied, directly or through neighbours, to a scene with enough control points.

    A reference match set anchors its scene's group with ``min_points`` points; points given
    by hand (matches with a ``ground_sigma``) with ``min_given`` in the whole group (three
    points fix a plane's position, scale and rotation; the ties carry the rest).
    """
    parent = list(range(n))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for t in ties:
        if len(t) >= min_points:
            parent[root(t.i)] = root(t.j)
    anchored = {root(c.j) for c in control if c.ground_sigma is None and len(c) >= min_points}
    given = np.zeros(n, dtype=np.int64)
    for c in control:
        if c.ground_sigma is not None:
            given[root(c.j)] += len(c)
    anchored |= {k for k in range(n) if given[k] >= min_given}
    return np.array([root(k) in anchored for k in range(n)], dtype=bool)


def scene_model(order: int, shape: tuple[int, int], to_map: Callable, *, samples: int = 9) -> tuple[MapPolynomial, np.ndarray]:
    """A scene's model, centred on its footprint, and start values fitted to ``to_map`` (pixel -> map)."""
    h, w = shape
    ys, xs = np.meshgrid(np.linspace(0, h - 1, samples), np.linspace(0, w - 1, samples), indexing="ij")
    ex, ny = to_map(xs.ravel(), ys.ravel())
    centre = (float(np.mean(ex)), float(np.mean(ny)))
    scale = float(max(np.ptp(ex), np.ptp(ny), 1e-6) / 2)
    model = MapPolynomial(order, centre, scale)
    ground = np.column_stack([ex, ny, np.zeros(ex.size)])
    return model, model.fit(ground, np.column_stack([xs.ravel(), ys.ravel()]))


def build_problem(shapes: list[tuple[int, int]], approx: list[Callable], control: list[Matches], ties: list[Matches], *,
                  order: int = 2, control_sigma: float = 1e-3, min_sigma: float = 0.02, models: list | None = None,
                  height: Callable | None = None) -> Problem:
    """The block: one frame per scene, one ground point per control or tie match.

    Parameters
    ----------
    shapes : list of (rows, cols)
    approx : list of callables
        Approximate scene pixel -> map mapping of every scene (start values only).
    control : list of Matches
        ``i = -1``: ``a`` map coordinates, ``b`` pixels of scene ``j``.
    ties : list of Matches
        ``a`` pixels of scene ``i``, ``b`` pixels of scene ``j``.
    order : int
        Polynomial order of every scene's model.
    control_sigma : float
        Standard deviation of the control points' map coordinates (map units; the
        reference's pixels are the truth here, their matching error is in the scenes), for
        the matches without their own ``ground_sigma``.
    min_sigma : float
        Floor of the matching sigmas (pixels) in the observation weights.
    models : list of (model, params), optional
        Every scene's sensor model and its start values; default a :class:`MapPolynomial`
        of ``order`` fitted to ``approx``.
    height : callable, optional
        ``height(E, N) -> h``: the DEM; heights are 0 without it.

    Returns
    -------
    Problem
        Every image observation weighted by the inverse of its match's 2 x 2 covariance,
        ``diag(sigma_x^-2, sigma_y^-2)`` (each sigma floored at ``min_sigma``).
    """
    def heights(e: np.ndarray, n: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(e)) if height is None else np.asarray(height(e, n), dtype=np.float64)

    frames = []
    for k, (shape, f) in enumerate(zip(shapes, approx)):
        model, params = scene_model(order, shape, f) if models is None else models[k]
        frames.append(Frame(model=model, params=np.array(params, dtype=np.float64)))
    ground, gweight, ofr, opt, oxy, osig = [], [], [], [], [], []
    wxy = 1.0 / control_sigma**2
    # a tie point's height is held to the DEM (or 0) with a sigma of 1 m: the polynomial ignores
    # it, and the weight keeps the point's 3 x 3 normal block well conditioned
    wz_tie = 1.0
    n = 0
    for c in control:
        m = len(c)
        ground.append(np.column_stack([c.a, heights(c.a[:, 0], c.a[:, 1])]))
        if c.ground_sigma is None:
            gweight.append(np.broadcast_to(np.diag([wxy, wxy, wxy]), (m, 3, 3)))
        else:  # the height as known as the reference's control (the DEM's); x, y as the point says
            g = np.zeros((m, 3, 3))
            g[:, 0, 0] = g[:, 1, 1] = 1.0 / np.asarray(c.ground_sigma, dtype=np.float64) ** 2
            g[:, 2, 2] = wxy
            gweight.append(g)
        ofr.append(np.full(m, c.j))
        opt.append(n + np.arange(m))
        oxy.append(c.b)
        osig.append(c.sigma)
        n += m
    # multi-ray ties: a point of scene i matched in several neighbours (the same interest point,
    # the same coordinates) is one ground point seen by all of them
    linked: dict[tuple[int, float, float], int] = {}
    for t in ties:
        m = len(t)
        ids = np.empty(m, dtype=np.int64)
        fresh = []
        for q, (x, y) in enumerate(t.a):
            key = (t.i, float(x), float(y))
            if key not in linked:
                linked[key] = n + len(fresh)
                fresh.append(q)
            ids[q] = linked[key]
        fresh = np.asarray(fresh, dtype=np.int64)
        if fresh.size:
            ex, ny = approx[t.i](t.a[fresh, 0], t.a[fresh, 1])
            ground.append(np.column_stack([ex, ny, heights(ex, ny)]))
            gweight.append(np.broadcast_to(np.diag([0.0, 0.0, wz_tie]), (fresh.size, 3, 3)))
            ofr.append(np.full(fresh.size, t.i))
            opt.append(ids[fresh])
            oxy.append(t.a[fresh])
            osig.append(t.sigma[fresh])
            n += fresh.size
        ofr.append(np.full(m, t.j))
        opt.append(ids)
        oxy.append(t.b)
        osig.append(t.sigma)
    g = np.concatenate(ground) if ground else np.zeros((0, 3))
    sig = np.maximum(np.concatenate(osig), min_sigma) if osig else np.zeros((0, 2))
    return Problem(
        frames=frames,
        ground=g.copy(),
        ground_prior=g.copy(),
        ground_weight=np.ascontiguousarray(np.concatenate(gweight)) if gweight else np.zeros((0, 3, 3)),
        obs_frame=np.concatenate(ofr).astype(np.int64) if ofr else np.zeros(0, np.int64),
        obs_point=np.concatenate(opt).astype(np.int64) if opt else np.zeros(0, np.int64),
        obs_xy=np.concatenate(oxy).astype(np.float64) if oxy else np.zeros((0, 2)),
        obs_weight=np.eye(2)[None] / (sig**2)[:, :, None],
    )


def solve(problem: Problem, *, robust: bool = True, height: Callable | None = None) -> AdjustResult:
    """Adjust the block (robust re-weighting, eq 20b then 22b, then Baarda's data snooping), with
    covariances, redundancy numbers and the snooping when the block is small enough for the
    dense inverse (:class:`~geocoder.adjust.solver.AdjustOptions` ``max_dense_unknowns``).

    With ``height`` (the DEM), the tie points' heights are held to the DEM where the first
    adjustment put them, and the block is adjusted once more from there.
    """
    options = AdjustOptions(max_iter=20, tol=1e-8, robust=robust, damping=1e-6, snooping=robust)
    result = adjust(problem, options)
    if height is None:
        return result
    tie = problem.ground_weight[:, 0, 0] == 0
    if not tie.any():
        return result
    prior = problem.ground_prior.copy()
    g = result.ground[tie]
    prior[tie, 2] = height(g[:, 0], g[:, 1])
    again = replace(problem, frames=[replace(f, params=p) for f, p in zip(problem.frames, result.params)],
                    ground=result.ground.copy(), ground_prior=prior)
    return adjust(again, options)


#: :func:`point_table` columns, in this order.
POINT_COLUMNS = ("x", "y", "control", "rays", "sigma_x", "sigma_y", "max_w")


def point_table(problem: Problem, result: AdjustResult, pixel_size: float) -> np.ndarray:
    """Every ground point of the adjusted block with its precision.

    Parameters
    ----------
    problem, result : Problem, AdjustResult
        The block and its adjustment.
    pixel_size : float
        Map units per reference pixel (the precisions are given in reference pixels).

    Returns
    -------
    ndarray (P, 7)
        :data:`POINT_COLUMNS`: the adjusted map position; 1 for a control point (its map
        position observed), 0 for a tie point; the scenes whose kept observations see it; the
        standard deviations of its adjusted map position (reference px; NaN without the
        covariances: a block too large for the dense inverse); the largest normalised residual
        (Baarda's w) of its kept observations (NaN without).
    """
    npts = len(problem.ground_prior)
    control = problem.ground_weight[:, 0, 0] > 0
    keep = result.obs_active
    rays = np.bincount(problem.obs_point[keep], minlength=npts)
    sigma = np.full((npts, 2), np.nan)
    if result.ground_cov is not None:
        var = np.stack([result.ground_cov[:, 0, 0], result.ground_cov[:, 1, 1]], axis=1)
        sigma = np.sqrt(np.clip(var, 0.0, None)) / pixel_size
    max_w = np.full(npts, np.nan)
    if result.normalized_residuals is not None:
        np.fmax.at(max_w, problem.obs_point, np.where(keep, result.normalized_residuals, np.nan))
    return np.column_stack([result.ground[:, 0], result.ground[:, 1], control.astype(float), rays.astype(float),
                            sigma, max_w])
