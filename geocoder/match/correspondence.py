"""Correspondence of interest points within one tile (seed 000 sec. 4.3-4.4).

Pure function of in-memory windows: candidate pairs within ``d_max`` of the prediction,
correlation of the base patch with the distorted patch sampled through the prediction's
local affine, pair weights (eq 29), robust shift then robust affine (eq 20b, then 22b),
ambiguities resolved by the smaller residual, and a least-squares refinement of the
distorted position of every surviving pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..kernels.correlate import correlation, extract_patches, pair_weight, refine_shift, warped_patches
from ..kernels.interest import InterestPoints
from ..kernels.polynomial import PolyMap, fit_polymap
from ..kernels.robust import StopReason, robust_fit
from .tiepoints import TiePoints

#: Standard deviation (px, per axis) of an unrefined pair, at least: both interest points lie on
#: whole pixels, each within half a pixel of its feature (uniform), so their difference scatters
#: by sqrt(2 / 12) from that alone (0.53-0.59 px measured in tests/test_correspondence.py, where
#: the maxima of the warped texture move too).
PAIR_SIGMA = float(np.sqrt(2.0 / 12.0))


@dataclass(frozen=True)
class CorrespondenceOptions:
    """Options of the correspondence step.

    d_max : largest distance (distorted pixels) between a candidate and its prediction.
    rho_min : smallest correlation coefficient of a candidate pair (seed: 0.5).
    patch : radius of the correlation patch (patch of ``2 patch + 1`` pixels square).
    refine : radius of the least-squares refinement template.
    min_pairs : fewest pairs a tile needs for its robust affine.
    rho_final : smallest correlation after refinement.
    max_move : largest move (px) of the refinement away from the robust prediction.
    """

    d_max: float = 24.0
    rho_min: float = 0.5
    patch: int = 7
    refine: int = 8
    min_pairs: int = 6
    rho_final: float = 0.6
    max_move: float = 2.0

    @property
    def margin(self) -> int:
        return max(self.patch, self.refine) + 3


@dataclass(frozen=True)
class TileMatchStats:
    base_points: int = 0
    candidates: int = 0
    correlated: int = 0
    robust: int = 0
    refined: int = 0
    reason: str = ""


def _unique_best(keys: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Mask keeping, for every key, only the entry of smallest score."""
    order = np.lexsort((score, keys))
    first = np.r_[True, keys[order][1:] != keys[order][:-1]]
    keep = np.zeros(keys.size, dtype=bool)
    keep[order[first]] = True
    return keep


def correspond(
    base: np.ndarray,
    base_origin: tuple[int, int],
    base_points: InterestPoints,
    dist: np.ndarray,
    dist_origin: tuple[int, int],
    dist_points: InterestPoints,
    predict: PolyMap,
    opts: CorrespondenceOptions = CorrespondenceOptions(),
    *,
    refine: bool = True,
) -> tuple[TiePoints, TileMatchStats]:
    """Find and refine point pairs for the base points of one tile.

    Parameters
    ----------
    base, dist : ndarray, shape (h, w)
        Windows of the base and distorted image (NaN = nodata); ``*_origin`` is the global
        (row, col) of their first pixel.
    base_points, dist_points : InterestPoints
        Interest points (global coordinates) of the tile and of the distorted window.
    predict : PolyMap
        Current prediction, base pixel -> distorted pixel (global frames).
    refine : bool
        Refine every pair by least squares. False: the pairs as the interest points place them
        (whole pixels, sigma :data:`PAIR_SIGMA`), for a polynomial that only predicts where a
        later guided pass refines every base point (:func:`correspond_guided`).

    Returns
    -------
    TiePoints, TileMatchStats
    """
    stats = {"base_points": len(base_points)}
    empty = TiePoints.empty()
    if len(base_points) < opts.min_pairs or len(dist_points) == 0:
        return empty, TileMatchStats(**stats, reason="too few interest points")
    br0, bc0 = base_origin
    dr0, dc0 = dist_origin
    tmpl = extract_patches(base, base_points.x - bc0, base_points.y - br0, opts.patch)
    px, py = predict(base_points.x, base_points.y)
    jac = predict.jacobian(base_points.x, base_points.y)
    tree = cKDTree(np.stack([dist_points.x, dist_points.y], axis=1))
    lists = tree.query_ball_point(np.stack([px, py], axis=1), r=opts.d_max)
    counts = np.fromiter((len(c) for c in lists), dtype=np.int64, count=len(lists))
    ii = np.repeat(np.arange(len(lists)), counts)
    jj = np.fromiter((j for c in lists for j in c), dtype=np.int64, count=int(counts.sum()))
    ok = np.isfinite(tmpl[ii]).all(axis=1)
    ii, jj = ii[ok], jj[ok]
    stats["candidates"] = int(ii.size)
    if ii.size < opts.min_pairs:
        return empty, TileMatchStats(**stats, reason="too few candidate pairs")
    patches = warped_patches(dist, dist_points.x[jj] - dc0, dist_points.y[jj] - dr0, jac[ii], opts.patch)
    rho = correlation(tmpl[ii], patches)
    keep = rho > opts.rho_min
    ii, jj, rho, patches = ii[keep], jj[keep], rho[keep], patches[keep]
    stats["correlated"] = int(ii.size)
    if ii.size < opts.min_pairs:
        return empty, TileMatchStats(**stats, reason="too few correlated pairs")
    weight = pair_weight(rho, tmpl[ii].std(axis=1), patches.std(axis=1), base_points.w[ii], dist_points.w[jj])
    weight = np.where(np.isfinite(weight), weight, np.nanmax(np.where(np.isfinite(weight), weight, 0)))
    obs = np.stack([dist_points.x[jj] - px[ii], dist_points.y[jj] - py[ii]], axis=1)
    shift = robust_fit(np.ones((ii.size, 1)), obs, weight, min_points=opts.min_pairs)
    if shift.reason == StopReason.TOO_FEW:
        return empty, TileMatchStats(**stats, reason="robust shift failed")
    start = np.vstack([shift.coef, np.zeros((2, 2))])  # the shift, as an affine
    local = fit_polymap(base_points.x[ii], base_points.y[ii], obs[:, 0], obs[:, 1], order=1, weights=weight,
                        min_points=opts.min_pairs, start=start)
    affine = local.fit_info
    if affine.reason == StopReason.TOO_FEW:
        return empty, TileMatchStats(**stats, reason="robust affine failed")
    good = affine.inliers
    resid = np.hypot(*affine.residuals.T)
    good &= _unique_best(np.where(good, ii, -1 - np.arange(ii.size)), resid)
    good &= _unique_best(np.where(good, jj, -1 - np.arange(jj.size)), resid)
    ii, jj = ii[good], jj[good]
    stats["robust"] = int(ii.size)
    if ii.size == 0:
        return empty, TileMatchStats(**stats, reason="no pair survived")
    if not refine:
        sigma = np.full(ii.size, PAIR_SIGMA)
        tp = TiePoints.build(base_x=base_points.x[ii], base_y=base_points.y[ii], dist_x=dist_points.x[jj],
                             dist_y=dist_points.y[jj], weight=weight[good], rho=rho[good], sigma_x=sigma, sigma_y=sigma)
        return tp, TileMatchStats(**stats, reason="ok")
    # refine from the paired distorted point; the tile affine's linear part corrects the
    # local geometry of the prediction
    lin = local.jacobian(base_points.x[ii], base_points.y[ii])  # d(correction)/d(x, y)
    tp, refined = _refine(base, base_origin, base_points, ii, dist, dist_origin,
                          dist_points.x[jj], dist_points.y[jj], jac[ii] + lin, weight[good], opts)
    stats["refined"] = refined
    return tp, TileMatchStats(**stats, reason="ok")


def _refine(base, base_origin, base_points, ii, dist, dist_origin, x0, y0, jac, weight, opts):
    """Least-squares refinement of the distorted positions of base points ``ii``."""
    br0, bc0 = base_origin
    dr0, dc0 = dist_origin
    if min(np.shape(dist)[-2:]) < 3:  # the distorted window is a sliver along the image's edge
        return TiePoints.empty(), 0
    big = extract_patches(base, base_points.x[ii] - bc0, base_points.y[ii] - br0, opts.refine)
    fine = refine_shift(big, dist, x0 - dc0, y0 - dr0, jac, opts.refine, max_move=opts.max_move)
    acc = fine.ok & (fine.rho > opts.rho_final) & np.isfinite(big).all(axis=1)
    tp = TiePoints.build(
        base_x=base_points.x[ii][acc],
        base_y=base_points.y[ii][acc],
        dist_x=fine.x[acc] + dc0,
        dist_y=fine.y[acc] + dr0,
        weight=weight[acc],
        rho=fine.rho[acc],
        sigma_x=fine.sigma_x[acc],
        sigma_y=fine.sigma_y[acc],
    )
    return tp, int(acc.sum())


def correspond_guided(
    base: np.ndarray,
    base_origin: tuple[int, int],
    base_points: InterestPoints,
    dist: np.ndarray,
    dist_origin: tuple[int, int],
    predict: PolyMap,
    opts: CorrespondenceOptions = CorrespondenceOptions(),
) -> tuple[TiePoints, TileMatchStats]:
    """Match every base point at its prediction (once a good mapping is known).

    Used after the first pass: the prediction is then accurate to a pixel or better, so
    each base interest point is refined by least squares straight from ``predict(p)``
    (seed 003's second tie-point set on the pre-warped image). A robust affine of the
    tile's refinements against the prediction removes blunders.
    """
    stats = {"base_points": len(base_points)}
    if len(base_points) == 0:
        return TiePoints.empty(), TileMatchStats(**stats, reason="no interest points")
    px, py = predict(base_points.x, base_points.y)
    jac = predict.jacobian(base_points.x, base_points.y)
    ii = np.arange(len(base_points))
    weight = np.sqrt(base_points.w)  # texture only: there is no pair correlation yet
    tp, refined = _refine(base, base_origin, base_points, ii, dist, dist_origin, px, py, jac, weight, opts)
    stats.update(candidates=len(base_points), correlated=refined, refined=refined)
    if len(tp) >= opts.min_pairs:
        qx, qy = predict(tp.base_x, tp.base_y)
        fit = fit_polymap(tp.base_x, tp.base_y, tp.dist_x - qx, tp.dist_y - qy, order=1, min_points=opts.min_pairs)
        if fit.fit_info.reason != StopReason.TOO_FEW:
            tp = tp.select(fit.fit_info.inliers)
    stats["robust"] = len(tp)
    return tp, TileMatchStats(**stats, reason="ok")
