"""Blocks of frames: from point sets to an adjustment problem, and accuracy at check points.

Glue between point sets (:mod:`geocoder.adjust.observations`, from the simulator or from files) and :func:`geocoder.adjust.solver.adjust`:
ground points are indexed by id, control points get a prior weight of ``1/sigma^2`` per
axis (infinite sigma -> free), tie points are free except, optionally, their height.
Check points never enter the adjustment: :func:`check_errors` intersects their image
observations with the terrain through the adjusted model of their frame ("mono-plotting")
and compares with the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geodesy import ecef_to_geodetic, geodetic_to_ecef
from .observations import GroundPoints, ImageObservations
from .problem import Frame, Problem


def ground_weights(sigma: np.ndarray) -> np.ndarray:
    """(P, 3, 3) diagonal weights ``1/sigma^2``; infinite sigma gives weight 0 (free)."""
    s = np.asarray(sigma, dtype=np.float64)
    with np.errstate(divide="ignore"):
        w = np.where(np.isfinite(s) & (s > 0), 1.0 / s**2, 0.0)
    out = np.zeros((len(s), 3, 3))
    out[:, [0, 1, 2], [0, 1, 2]] = w
    return out


def height_only_weights(ground: GroundPoints, sigma_h: float) -> np.ndarray:
    """(P, 3, 3) weights that hold only the ellipsoidal height of ECEF points to its prior."""
    lat, lon, _ = ecef_to_geodetic(ground.X, ground.Y, ground.Z)
    up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=1)
    return up[:, :, None] * up[:, None, :] / sigma_h**2


def build_problem(frames: list[Frame], ground: GroundPoints, obs: ImageObservations, *,
                  tie_height_sigma: float | None = 15.0) -> tuple[Problem, np.ndarray]:
    """An adjustment problem from point sets; also returns the ground ids in problem order.

    Observations of points that are not in ``ground`` (e.g. check points) are left out.
    """
    index = {int(i): k for k, i in enumerate(ground.id)}
    keep = np.array([int(p) in index for p in obs.point], dtype=bool)
    obs = obs.subset(keep)
    weight = ground_weights(ground.sigma)
    if tie_height_sigma is not None:
        tie = ground.role == "tie"
        if tie.any():
            weight[tie] = height_only_weights(ground.subset(tie), tie_height_sigma)
    problem = Problem(
        frames=frames,
        ground=ground.xyz.copy(),
        ground_prior=ground.xyz.copy(),
        ground_weight=weight,
        obs_frame=np.asarray(obs.frame, dtype=np.int64),
        obs_point=np.array([index[int(p)] for p in obs.point], dtype=np.int64),
        obs_xy=np.stack([obs.col, obs.row], axis=1),
        obs_weight=np.asarray(obs.weight, dtype=np.float64),
    )
    return problem, np.asarray(ground.id)


def intersect(model, params: np.ndarray, xy: np.ndarray, heights: np.ndarray, *, start: np.ndarray,
              iterations: int = 20, tol: float = 1e-4) -> np.ndarray:
    """Ground points (ECEF) at the given ellipsoidal heights that ``model`` projects onto ``xy``.

    Newton on (lat, lon) per point, vectorised, from ``start`` (ECEF approximations).
    """
    lat, lon, _ = ecef_to_geodetic(*np.asarray(start, dtype=np.float64).T)
    h = np.asarray(heights, dtype=np.float64)
    d = 1e-7  # radians, ~0.6 m
    for _ in range(iterations):
        g0 = np.stack(geodetic_to_ecef(lat, lon, h), axis=1)
        p0 = model.project(params, g0)
        pl = model.project(params, np.stack(geodetic_to_ecef(lat + d, lon, h), axis=1))
        pn = model.project(params, np.stack(geodetic_to_ecef(lat, lon + d, h), axis=1))
        jac = np.stack([(pl - p0) / d, (pn - p0) / d], axis=2)  # (m, 2, 2)
        step = np.linalg.solve(jac, (xy - p0)[..., None])[..., 0]
        lat, lon = lat + step[:, 0], lon + step[:, 1]
        if np.nanmax(np.abs(step)) < tol * 1e-7:
            break
    return np.stack(geodetic_to_ecef(lat, lon, h), axis=1)


@dataclass(frozen=True)
class CheckErrors:
    """Horizontal errors (m) of check points, with the frame of each observation."""

    frame: np.ndarray
    error: np.ndarray

    def rms(self, frame: int | None = None) -> float:
        e = self.error if frame is None else self.error[self.frame == frame]
        e = e[np.isfinite(e)]
        return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def check_errors(frames: list[Frame], params: list[np.ndarray], check: GroundPoints, obs: ImageObservations) -> CheckErrors:
    """Mono-plot every check observation through its frame's adjusted model, at the check
    point's a-priori (perturbed) height, and measure the horizontal distance to the truth."""
    index = {int(i): k for k, i in enumerate(check.id)}
    keep = np.array([int(p) in index for p in obs.point], dtype=bool)
    obs = obs.subset(keep)
    rows = np.array([index[int(p)] for p in obs.point], dtype=np.int64)
    err = np.full(len(obs), np.nan)
    for f in np.unique(obs.frame):
        m = obs.frame == f
        k = rows[m]
        _, _, h = ecef_to_geodetic(check.X[k], check.Y[k], check.Z[k])
        xy = np.stack([obs.col[m], obs.row[m]], axis=1)
        g = intersect(frames[f].model, params[f], xy, h, start=check.xyz[k])
        tlat, tlon, th = ecef_to_geodetic(check.true_X[k], check.true_Y[k], check.true_Z[k])
        t = np.stack(geodetic_to_ecef(tlat, tlon, h), axis=1)  # truth moved to the same height
        err[m] = np.linalg.norm(g - t, axis=1)
    return CheckErrors(np.asarray(obs.frame), err)
