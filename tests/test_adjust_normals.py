"""Tests of the streamed assembly of the reduced normal equations (geocoder.adjust.normals)."""

from __future__ import annotations

import numpy as np
import pytest
from test_adjust_solver import affine_block, dense_normals

from geocoder.adjust import normals
from geocoder.adjust.solver import AdjustOptions, Problem, adjust


def _mixed_problem() -> Problem:
    """Four frames with tie and control points, plus what exercises the special paths: a point
    observed twice in one frame (two rank-1 edge weights), and a tie point seen once (dropped)."""
    blk = affine_block(6, n_tie=60, n_ctrl=10)
    prob = blk["problem"]
    i = 0  # first observation: a control point
    n = np.array([0.6, 0.8])
    w_edge = np.outer(n, n) / blk["sigma"] ** 2  # rank 1
    g_new = np.array([[5000.0, 5000.0, 100.0]])
    return Problem(
        prob.frames,
        np.r_[prob.ground, g_new],
        np.r_[prob.ground_prior, g_new],
        np.r_[prob.ground_weight, np.zeros((1, 3, 3))],
        np.r_[prob.obs_frame, prob.obs_frame[i], 0],
        np.r_[prob.obs_point, prob.obs_point[i], prob.ground.shape[0]],
        np.r_[prob.obs_xy, prob.obs_xy[i : i + 1] + 0.2, [[170.0, 160.0]]],
        np.r_[prob.obs_weight, w_edge[None], prob.obs_weight[:1]],
    )


def _reduced_dense(prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Schur complement of the full dense normal equations, without the point seen once (the
    last point and the last observation), which the solver drops."""
    prob = Problem(prob.frames, prob.ground[:-1], prob.ground_prior[:-1], prob.ground_weight[:-1],
                   prob.obs_frame[:-1], prob.obs_point[:-1], prob.obs_xy[:-1], prob.obs_weight[:-1])
    params = [fr.params for fr in prob.frames]
    n, t, _, offs = dense_normals(prob, params, prob.ground)
    npar = offs[-1]
    a, b, d = n[:npar, :npar], n[:npar, npar:], n[npar:, npar:]
    return a - b @ np.linalg.solve(d, b.T), t[:npar] - b @ np.linalg.solve(d, t[npar:])


@pytest.mark.parametrize("block_size", [1, 40, 10**9])
def test_streamed_assembly_equals_dense_schur_complement(block_size: int) -> None:
    prob = _mixed_problem()
    lay = normals.layout(prob, block_size)
    if block_size == 1:
        assert lay.n_chunks == len(prob.frames)
        assert np.any(lay.obs_done > np.searchsorted(lay.chunk_lo, np.arange(lay.obs_frame.size), "right") - 1)
    models = [fr.model for fr in prob.frames]
    params = [fr.params for fr in prob.frames]
    res = normals.residuals(lay, models, params, prob.ground)
    nrm = normals.assemble(lay, models, params, prob.ground, res, np.ones(lay.obs_frame.size))
    s_ref, r_ref = _reduced_dense(prob)
    np.testing.assert_allclose(nrm.s.toarray(), s_ref, rtol=1e-9, atol=1e-9 * np.abs(s_ref).max())
    np.testing.assert_allclose(nrm.r, r_ref, rtol=1e-9, atol=1e-9 * np.abs(r_ref).max())
    assert not nrm.valid[-1] and nrm.valid[:-1].all()
    assert (nrm.jp_chunks is None) == (lay.n_chunks > 1)


@pytest.mark.parametrize("keep", [0, 1 << 30])
def test_block_size_does_not_change_the_adjustment(keep: int) -> None:
    """One chunk per frame (points buffered across chunks; Jacobians re-evaluated or kept) against
    one chunk for everything: the same solution, statistics and robust decisions to rounding."""
    prob = _mixed_problem()
    opt = {"robust": True, "snooping": True}
    one = adjust(prob, AdjustOptions(block_size=None, **opt))
    many = adjust(prob, AdjustOptions(block_size=1, keep_jacobians=keep, **opt))
    assert one.converged and many.converged and one.iterations == many.iterations
    for p, q in zip(one.params, many.params):
        np.testing.assert_allclose(q, p, rtol=1e-9, atol=1e-12)
    ok = one.point_valid
    np.testing.assert_array_equal(many.point_valid, ok)
    np.testing.assert_allclose(many.ground[ok], one.ground[ok], rtol=1e-9, atol=1e-7)
    np.testing.assert_array_equal(many.obs_active, one.obs_active)
    assert many.sigma0 == pytest.approx(one.sigma0, rel=1e-9)
    np.testing.assert_allclose(many.redundancy, one.redundancy, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(many.normalized_residuals, one.normalized_residuals, rtol=1e-7)
    for p, q in zip(one.param_cov, many.param_cov):
        np.testing.assert_allclose(q, p, rtol=1e-7, atol=1e-12 * np.abs(p).max())
