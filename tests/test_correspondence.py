"""Correspondence of interest points (seed 000 sec. 4.4) on one window with a known field:
the pairs as the interest points place them, and refined by least squares."""

from __future__ import annotations

import numpy as np

from geocoder.kernels.interest import detect
from geocoder.kernels.polynomial import fit_polymap
from geocoder.match.correspondence import PAIR_SIGMA, correspond
from geocoder.simulate.texture import synthetic_ortho
from geocoder.simulate.warp import make_pair


def _window_pair():
    src = synthetic_ortho((352, 352), seed=4)
    pair = make_pair(src, shape=(256, 256), seed=4, max_displacement=6.0, margin=48)
    base, dist = pair.base[0], pair.distorted[0]
    bpts, dpts = detect(base), detect(np.nan_to_num(dist, nan=float(np.nanmean(dist))))
    # the prediction of pass 1: the field's affine part, off by a few pixels where it curves
    ys, xs = np.mgrid[0:256:16, 0:256:16]
    predict = fit_polymap(xs.ravel() * 1.0, ys.ravel() * 1.0, (xs + pair.dx[ys, xs]).ravel(),
                          (ys + pair.dy[ys, xs]).ravel(), order=1, robust=False)
    return pair, base, dist, bpts, dpts, predict


def _errors(pair, tp):
    bx, by = tp.base_x.astype(int), tp.base_y.astype(int)
    return tp.dist_x - (bx + pair.dx[by, bx]), tp.dist_y - (by + pair.dy[by, bx])


def test_unrefined_pairs_sit_on_the_interest_points_and_refinement_moves_them_onto_the_truth():
    pair, base, dist, bpts, dpts, predict = _window_pair()
    coarse, stats = correspond(base, (0, 0), bpts, dist, (0, 0), dpts, predict, refine=False)
    fine, fine_stats = correspond(base, (0, 0), bpts, dist, (0, 0), dpts, predict)
    assert stats.reason == fine_stats.reason == "ok"
    assert stats.robust == fine_stats.robust >= 50 and stats.refined == 0 and fine_stats.refined > 0.8 * stats.robust
    # the unrefined pair is the two interest points: whole pixels, the quantisation's sigma
    assert set(zip(coarse.dist_x, coarse.dist_y)) <= set(zip(dpts.x, dpts.y))
    np.testing.assert_array_equal(coarse.dist_x, np.round(coarse.dist_x))
    assert np.all(coarse.sigma_x == PAIR_SIGMA) and np.all(coarse.sigma_y == PAIR_SIGMA)
    ex, ey = _errors(pair, coarse)
    rms = float(np.sqrt(np.mean(np.r_[ex, ey] ** 2)))
    # two independent whole-pixel positions: sqrt(2 / 12) = 0.41 px per axis if each is within
    # half a pixel of its feature; the Foerstner maxima of warped texture scatter a little more
    assert 0.2 < rms < 0.8, rms
    # the same base points, refined: a hundredth of a pixel
    fx, fy = _errors(pair, fine)
    assert float(np.sqrt(np.mean(np.r_[fx, fy] ** 2))) < 0.05
    assert set(fine.base_x + 1j * fine.base_y) <= set(coarse.base_x + 1j * coarse.base_y)


def test_pass_one_stays_unrefined_only_with_many_points_in_the_overlap():
    from geocoder.kernels.interest import InterestPoints
    from geocoder.pipeline.correspond import UNREFINED_POINTS_PER_TERM, refine_first_pass

    rng = np.random.default_rng(0)
    need = UNREFINED_POINTS_PER_TERM * 6  # the quadratic's six terms
    x, y = rng.uniform(0, 2000, need + 100), rng.uniform(0, 2000, need + 100)
    many = InterestPoints(x, y, np.ones_like(x), np.ones_like(x))
    few = InterestPoints(x[: need - 1], y[: need - 1], np.ones(need - 1), np.ones(need - 1))
    same = fit_polymap(x, y, x, y, order=1, robust=False)
    assert not refine_first_pass(many, same, (2000, 2000), order=2, passes=2)
    assert refine_first_pass(few, same, (2000, 2000), order=2, passes=2)
    assert refine_first_pass(many, same, (2000, 2000), order=2, passes=1)  # its pairs are the tie points
    # the same points, most of them predicted beyond a small distorted scene
    assert refine_first_pass(many, same, (1000, 1000), order=2, passes=2)
    assert refine_first_pass(many, same, (2000, 2000), order=3, passes=2)  # ten terms need more


def test_pass_one_pairs_the_strongest_point_of_every_square_on_a_large_scene():
    from geocoder.kernels.interest import InterestPoints
    from geocoder.pipeline.correspond import FIRST_PASS_MARGIN, UNREFINED_POINTS_PER_TERM, first_pass_points

    rng = np.random.default_rng(1)
    n = 40_000
    x, y = np.round(rng.uniform(0, 8192, n)), np.round(rng.uniform(0, 8192, n))
    w = rng.integers(1, 50, n).astype(np.float64)  # ties included
    order = np.lexsort((x, y))
    pts = InterestPoints(x[order], y[order], w[order], np.ones(n))
    same = fit_polymap(x, y, x, y, order=1, robust=False)
    first = first_pass_points(pts, same, (8192, 8192), order=2, cell=64)
    # one point per occupied square, the strongest, the first of equals; the order kept
    square = (pts.y // 64) * 128 + pts.x // 64
    assert len(first) == len(np.unique(square))
    kept = np.flatnonzero(np.isin(np.stack([pts.x, pts.y], 1).view(complex).ravel(),
                                  np.stack([first.x, first.y], 1).view(complex).ravel()))
    for s in np.unique(square)[:300]:
        mine = np.flatnonzero(square == s)
        assert np.intersect1d(kept, mine).tolist() == [mine[np.argmax(pts.w[mine])]]
    assert np.all(np.diff(first.y * 10_000 + first.x) > 0)
    # the squares are global: a quarter of the scene gives the same choice inside it
    quarter = (pts.x < 4096) & (pts.y < 4096)
    part = InterestPoints(pts.x[quarter], pts.y[quarter], pts.w[quarter], pts.q[quarter])
    mine = first_pass_points(part, same, (8192, 8192), order=1, cell=64)  # three terms: 1,500 needed
    assert FIRST_PASS_MARGIN * UNREFINED_POINTS_PER_TERM * 3 <= len(mine) < len(part)
    in_quarter = (first.x < 4096) & (first.y < 4096)
    np.testing.assert_array_equal(np.stack([mine.x, mine.y]), np.stack([first.x[in_quarter], first.y[in_quarter]]))
    tile = (pts.x >= 1024) & (pts.x < 2048) & (pts.y < 1024)
    few = InterestPoints(pts.x[tile], pts.y[tile], pts.w[tile], pts.q[tile])
    assert len(first_pass_points(few, same, (8192, 8192), order=2, cell=64)) == len(few), "too few squares: all"
    # a scene whose squares give too few for the quadratic keeps every point
    small = first_pass_points(pts, same, (8192, 8192), order=2, cell=512)
    assert len(small) == len(pts)
