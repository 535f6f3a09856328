"""Tests of the block adjustment solver (geocoder.adjust.solver) with small self-contained models."""

from __future__ import annotations

import numpy as np
import pytest

from geocoder.adjust.solver import (
    AdjustOptions,
    Frame,
    Problem,
    adjust,
    numeric_jacobians,
)

# --------------------------------------------------------------------------------------------
# test models
# --------------------------------------------------------------------------------------------


class AffineZ:
    """``xy = A @ (X, Y) + t + kz * Z``; params ``(a11, a12, a21, a22, tx, ty)``, ``kz`` fixed."""

    n_params = 6

    def __init__(self, kz: np.ndarray) -> None:
        self.kz = np.asarray(kz, dtype=float)

    def project(self, p: np.ndarray, g: np.ndarray) -> np.ndarray:
        a = p[:4].reshape(2, 2)
        return g[:, :2] @ a.T + p[4:6] + g[:, 2:3] * self.kz

    def jacobians(self, p: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = g.shape[0]
        jp = np.zeros((m, 2, 6))
        jp[:, 0, 0], jp[:, 0, 1], jp[:, 0, 4] = g[:, 0], g[:, 1], 1.0
        jp[:, 1, 2], jp[:, 1, 3], jp[:, 1, 5] = g[:, 0], g[:, 1], 1.0
        jg = np.zeros((m, 2, 3))
        jg[:, :, :2] = p[:4].reshape(2, 2)
        jg[:, :, 2] = self.kz
        return jp, jg


def _rot(om: float, ph: float, ka: float) -> np.ndarray:
    co, so, cp, s_p, ck, sk = (
        np.cos(om),
        np.sin(om),
        np.cos(ph),
        np.sin(ph),
        np.cos(ka),
        np.sin(ka),
    )
    rx = np.array([[1, 0, 0], [0, co, -so], [0, so, co]])
    ry = np.array([[cp, 0, s_p], [0, 1, 0], [-s_p, 0, cp]])
    rz = np.array([[ck, -sk, 0], [sk, ck, 0], [0, 0, 1]])
    return rx @ ry @ rz


class Collinearity:
    """Frame camera (collinearity equations); params ``(X0, Y0, Z0, omega, phi, kappa)``."""

    n_params = 6

    def __init__(
        self, c: float = 1000.0, pp: tuple[float, float] = (500.0, 500.0)
    ) -> None:
        self.c, self.pp = c, pp

    def project(self, p: np.ndarray, g: np.ndarray) -> np.ndarray:
        d = (g - p[:3]) @ _rot(*p[3:6])  # R^T (X - X0)
        return np.stack(
            [
                self.pp[0] - self.c * d[:, 0] / d[:, 2],
                self.pp[1] + self.c * d[:, 1] / d[:, 2],
            ],
            axis=1,
        )

    def jacobians(self, p: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return numeric_jacobians(self, p, g, step_ground=0.01)


# --------------------------------------------------------------------------------------------
# synthetic blocks
# --------------------------------------------------------------------------------------------


def affine_block(
    seed: int = 0,
    *,
    n_tie: int = 80,
    n_ctrl: int = 6,
    sigma: float = 0.3,
    perturb: bool = True,
    size: float = 18000.0,
) -> dict:
    """Four overlapping ``size`` m frames (2 x 2) over 30 km of an AffineZ model, tie and control points."""
    rng = np.random.default_rng(seed)
    o1 = 30000.0 - size
    origins = np.array([[0, 0], [o1, 0], [0, o1], [o1, o1]], dtype=float)
    frames_truth, models = [], []
    for o in origins:
        ang = rng.normal(0, 0.02)
        a = (
            (1 / 30)
            * (1 + rng.normal(0, 0.01))
            * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        )
        t = -a @ o + rng.normal(0, 5, 2)
        frames_truth.append(np.r_[a.ravel(), t])
        models.append(AffineZ(rng.uniform(-0.02, 0.02, 2)))
    npts = n_tie + n_ctrl
    truth = np.c_[rng.uniform(500, 29500, (npts, 2)), rng.uniform(0, 800, npts)]
    vis = np.all(
        (truth[None, :, :2] >= origins[:, None])
        & (truth[None, :, :2] < origins[:, None] + size),
        axis=2,
    )
    ctrl = np.zeros(npts, bool)
    ctrl[:n_ctrl] = True
    keep = ctrl | (vis.sum(0) >= 2)
    keep &= vis.sum(0) >= 1
    truth, vis, ctrl = truth[keep], vis[:, keep], ctrl[keep]
    npts = truth.shape[0]
    of, op = np.nonzero(vis)
    xy = np.empty((of.size, 2))
    for f in range(4):
        s = of == f
        xy[s] = models[f].project(frames_truth[f], truth[op[s]])
    xy += rng.normal(0, sigma, xy.shape)
    w = np.broadcast_to(np.eye(2) / sigma**2, (of.size, 2, 2)).copy()
    gprior = truth.copy()
    gprior[ctrl] += rng.normal(0, 15, (ctrl.sum(), 3))
    gw = np.zeros((npts, 3, 3))
    gw[ctrl] = np.eye(3) / 15.0**2
    ground0 = gprior.copy()
    start = [p.copy() for p in frames_truth]
    if perturb:
        ground0[~ctrl] = truth[~ctrl] + rng.normal(0, 60, ((~ctrl).sum(), 3))
        for p in start:
            p[:4] *= 1 + rng.normal(0, 2e-3, 4)
            p[4:] += rng.normal(0, 5, 2)
    frames = [Frame(models[f], start[f]) for f in range(4)]
    prob = Problem(frames, ground0, gprior, gw, of, op, xy, w)
    return {
        "problem": prob,
        "truth_params": frames_truth,
        "truth_ground": truth,
        "ctrl": ctrl,
        "sigma": sigma,
    }


def dense_normals(
    problem: Problem,
    params: list[np.ndarray],
    ground: np.ndarray,
    free: list[np.ndarray] | None = None,
):
    """Full (params + all ground coordinates) normal equations, one observation at a time."""
    nfr = len(problem.frames)
    free = free or [np.arange(fr.model.n_params) for fr in problem.frames]
    offs = np.cumsum([0] + [f.size for f in free])
    npar = offs[-1]
    npt = ground.shape[0]
    nu = npar + 3 * npt
    n = np.zeros((nu, nu))
    t = np.zeros(nu)
    omega = 0.0
    for i in range(problem.obs_frame.size):
        f, p = problem.obs_frame[i], problem.obs_point[i]
        mdl = problem.frames[f].model
        g = ground[p][None]
        jp, jg = mdl.jacobians(params[f], g)
        a = np.zeros((2, nu))
        a[:, offs[f] : offs[f + 1]] = jp[0][:, free[f]]
        a[:, npar + 3 * p : npar + 3 * p + 3] = jg[0]
        r = problem.obs_xy[i] - mdl.project(params[f], g)[0]
        w = problem.obs_weight[i]
        n += a.T @ w @ a
        t += a.T @ w @ r
        omega += r @ w @ r
    for p in range(npt):
        sl = slice(npar + 3 * p, npar + 3 * p + 3)
        d = problem.ground_prior[p] - ground[p]
        n[sl, sl] += problem.ground_weight[p]
        t[sl] += problem.ground_weight[p] @ d
        omega += d @ problem.ground_weight[p] @ d
    for f in range(nfr):
        fr = problem.frames[f]
        if fr.prior_weight is not None:
            pw = fr.prior_weight[np.ix_(free[f], free[f])]
            pv = fr.params if fr.prior_value is None else fr.prior_value
            d = (pv - params[f])[free[f]]
            sl = slice(offs[f], offs[f + 1])
            n[sl, sl] += pw
            t[sl] += pw @ d
            omega += d @ pw @ d
    return n, t, omega, offs


# --------------------------------------------------------------------------------------------
# tests
# --------------------------------------------------------------------------------------------


def test_numeric_jacobians_match_analytic():
    rng = np.random.default_rng(1)
    mdl = AffineZ([0.01, -0.005])
    p = np.r_[0.03, 0.001, -0.002, 0.031, 12.0, -40.0]
    g = np.c_[rng.uniform(0, 3e4, (20, 2)), rng.uniform(0, 500, 20)]
    jp, jg = numeric_jacobians(mdl, p, g)
    ap, ag = mdl.jacobians(p, g)
    np.testing.assert_allclose(jp, ap, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(jg, ag, rtol=1e-8, atol=1e-10)


def test_single_frame_control_only_equals_weighted_lstsq():
    rng = np.random.default_rng(2)
    mdl = AffineZ([0.004, -0.01])
    truth = np.r_[1 / 30, 0.001, -0.0012, 1 / 31, 20.0, -35.0]
    npt = 25
    g = np.c_[rng.uniform(0, 3e4, (npt, 2)), rng.uniform(0, 600, npt)]
    xy = mdl.project(truth, g) + rng.normal(0, 0.5, (npt, 2))
    # full (correlated) observation weights and control-point pseudo-observations
    lw = rng.normal(0, 0.3, (npt, 2, 2)) + 2 * np.eye(2)
    w = lw @ lw.transpose(0, 2, 1)
    gw = np.broadcast_to(np.eye(3) / 15.0**2, (npt, 3, 3)).copy()
    gprior = g + rng.normal(0, 15, g.shape)
    prob = Problem(
        [Frame(mdl, truth + 0.01)],
        gprior.copy(),
        gprior,
        gw,
        np.zeros(npt, int),
        np.arange(npt),
        xy,
        w,
    )
    res = adjust(prob)
    assert res.converged
    # the same problem as one linearised least-squares system at the solution: the correction is 0
    n, t, _, _ = dense_normals(prob, res.params, res.ground)
    assert np.abs(np.linalg.solve(n, t)).max() < 1e-7
    # with (nearly) fixed control the adjustment is the plain weighted affine fit of the control points
    prob_fixed = Problem(
        [Frame(mdl, truth + 0.01)],
        g.copy(),
        g,
        gw * 1e12,
        np.zeros(npt, int),
        np.arange(npt),
        xy,
        w,
    )
    res_fixed = adjust(prob_fixed)
    a = np.zeros((2 * npt, 6))
    a[0::2, 0], a[0::2, 1], a[0::2, 4] = g[:, 0], g[:, 1], 1
    a[1::2, 2], a[1::2, 3], a[1::2, 5] = g[:, 0], g[:, 1], 1
    obs = (xy - g[:, 2:3] * mdl.kz).ravel()
    sw = np.zeros(
        (2 * npt, 2 * npt)
    )  # block-diagonal square root of the weights (W = L L^T)
    for i in range(npt):
        sw[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = np.linalg.cholesky(w[i]).T
    coef = np.linalg.lstsq(sw @ a, sw @ obs, rcond=None)[0]
    np.testing.assert_allclose(res_fixed.params[0], coef, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(res_fixed.ground, g, atol=1e-4)


def test_block_converges_recovers_truth_and_sigma0():
    blk = affine_block(3, n_tie=150)
    prob = blk["problem"]
    res = adjust(prob)
    assert res.converged and res.iterations < 10
    assert res.solver in ("splu", "cholmod")
    assert res.point_valid.all()
    assert 0.8 < res.sigma0 < 1.2
    for f in range(4):
        err = res.params[f] - blk["truth_params"][f]
        std = np.sqrt(np.diag(res.param_cov[f]))
        assert np.all(np.abs(err) < 5 * std)
    # image residuals at the noise level
    assert np.sqrt(np.mean(res.residuals**2)) < 1.2 * blk["sigma"]


def test_schur_step_equals_full_dense_normal_equations():
    blk = affine_block(4, n_tie=40)
    prob = blk["problem"]
    start = [fr.params.copy() for fr in prob.frames]
    n, t, _, offs = dense_normals(prob, start, prob.ground)
    dx = np.linalg.solve(n, t)
    res = adjust(prob, AdjustOptions(max_iter=1, covariance=False))
    for f in range(4):
        np.testing.assert_allclose(
            res.params[f] - start[f],
            dx[offs[f] : offs[f + 1]],
            rtol=1e-8,
            atol=1e-10 * np.abs(start[f]).max(),
        )
    np.testing.assert_allclose(
        res.ground - prob.ground, dx[offs[-1] :].reshape(-1, 3), rtol=1e-8, atol=1e-7
    )
    # Levenberg-Marquardt damping reaches the same solution
    plain = adjust(prob, AdjustOptions(covariance=False))
    damped = adjust(prob, AdjustOptions(damping=1.0, covariance=False))
    assert damped.converged
    for f in range(4):
        np.testing.assert_allclose(
            damped.params[f], plain.params[f], rtol=1e-7, atol=1e-9
        )


def test_strip_uses_banded_cholesky_and_equals_dense():
    """A long strip: frames renumbered (RCM) give a banded reduced system (seed sec. 2.4)."""
    rng = np.random.default_rng(14)
    nfr = 12
    order = rng.permutation(nfr)  # frame numbering scrambled on purpose
    frames, truth = [], []
    for k in range(nfr):
        pos = order[k] * 10000.0
        p = (
            np.r_[1 / 30, 0.0, 0.0, 1 / 30, -pos / 30, 0.0]
            + np.r_[rng.normal(0, 1e-4, 4), rng.normal(0, 2, 2)]
        )
        truth.append(p)
        frames.append(
            Frame(
                AffineZ(rng.uniform(-0.02, 0.02, 2)), p + np.r_[np.zeros(4), 1.0, -1.0]
            )
        )
    pts = np.c_[
        rng.uniform(0, 10000 * nfr + 5000, 600),
        rng.uniform(0, 15000, 600),
        rng.uniform(0, 500, 600),
    ]
    lo = order * 10000.0
    vis = (pts[None, :, 0] >= lo[:, None]) & (pts[None, :, 0] < lo[:, None] + 15000)
    of, op = np.nonzero(vis)
    xy = np.empty((of.size, 2))
    for f in range(nfr):
        xy[of == f] = frames[f].model.project(truth[f], pts[op[of == f]])
    xy += rng.normal(0, 0.3, xy.shape)
    gw = np.zeros((600, 3, 3))
    gw[:, 2, 2] = 1 / 50.0**2  # tie heights constrained to an a-priori value
    gw[::25] = np.eye(3) / 15.0**2  # control
    prior = pts.copy()
    prior[:, 2] = 250.0
    prior[::25] = pts[::25]
    prob = Problem(
        frames,
        prior.copy(),
        prior,
        gw,
        of,
        op,
        xy,
        np.broadcast_to(np.eye(2) / 0.09, (of.size, 2, 2)).copy(),
    )
    res = adjust(prob, AdjustOptions(max_iter=1, covariance=False))
    assert res.solver == "banded-cholesky"
    start = [fr.params for fr in frames]
    n, t, _, offs = dense_normals(prob, start, prob.ground)
    dx = np.linalg.solve(n, t)
    for f in range(nfr):
        np.testing.assert_allclose(
            res.params[f] - start[f], dx[offs[f] : offs[f + 1]], rtol=1e-7, atol=1e-9
        )
    assert adjust(prob).converged


def test_covariances_and_redundancy_equal_dense_inverse():
    blk = affine_block(5, n_tie=40)
    prob = blk["problem"]
    prob.frames[1].prior_weight = np.diag(
        [1e6, 1e6, 1e6, 1e6, 1.0, 1.0]
    )  # pseudo-observations on a frame
    res = adjust(prob)
    n, _, omega, offs = dense_normals(prob, res.params, res.ground)
    q = np.linalg.inv(n)
    npar = offs[-1]
    m = prob.obs_frame.size
    dof = 2 * m + 6 + 3 * blk["ctrl"].sum() - n.shape[0]
    assert res.total_redundancy == pytest.approx(dof)
    assert res.sigma0 == pytest.approx(np.sqrt(omega / dof), rel=1e-8)
    s2 = res.sigma0**2
    for f in range(4):
        np.testing.assert_allclose(
            res.param_cov[f],
            s2 * q[offs[f] : offs[f + 1], offs[f] : offs[f + 1]],
            rtol=1e-6,
        )
    qg = np.stack(
        [
            q[npar + 3 * p : npar + 3 * p + 3, npar + 3 * p : npar + 3 * p + 3]
            for p in range(res.ground.shape[0])
        ]
    )
    np.testing.assert_allclose(
        res.ground_cov, s2 * qg, rtol=1e-6, atol=1e-9 * np.abs(qg).max()
    )
    # redundancy numbers r_i = 2 - tr(W_i A_i Q A_i^T)
    red = np.empty(m)
    for i in range(m):
        f, p = prob.obs_frame[i], prob.obs_point[i]
        jp, jg = prob.frames[f].model.jacobians(res.params[f], res.ground[p][None])
        a = np.zeros((2, n.shape[0]))
        a[:, offs[f] : offs[f + 1]] = jp[0]
        a[:, npar + 3 * p : npar + 3 * p + 3] = jg[0]
        red[i] = 2 - np.trace(prob.obs_weight[i] @ a @ q @ a.T)
    np.testing.assert_allclose(res.redundancy, red, atol=1e-8)
    assert np.nansum(res.redundancy) + res.pseudo_redundancy == pytest.approx(
        dof, rel=1e-8
    )


def _edge_weight(normal: np.ndarray, sigma: float, k: float) -> np.ndarray:
    """R diag(1/(k s)^2, 1/s^2) R^T with the edge direction first (k = inf: rank 1)."""
    nrm = normal / np.linalg.norm(normal)
    d = np.array([-nrm[1], nrm[0]])
    along = 0.0 if np.isinf(k) else 1.0 / (k * sigma) ** 2
    return along * np.outer(d, d) + np.outer(nrm, nrm) / sigma**2


@pytest.mark.parametrize("k", [np.inf, 1e4])
def test_crossing_edges_act_like_control_points(k):
    blk = affine_block(6, n_tie=60, n_ctrl=10)
    prob, ctrl, sigma = blk["problem"], blk["ctrl"], blk["sigma"]
    ref = adjust(prob)
    rng = np.random.default_rng(7)
    # every observation of a control point becomes two edge points on perpendicular edges,
    # shifted arbitrarily along their edges (rank-1 weights ignore that component)
    sel = ctrl[prob.obs_point]
    i_c = np.flatnonzero(sel)
    ang = rng.uniform(0, np.pi, i_c.size)
    n1 = np.c_[np.cos(ang), np.sin(ang)]
    n2 = np.c_[-np.sin(ang), np.cos(ang)]
    shift = 0.0 if np.isfinite(k) else 1.0
    xy1 = (
        prob.obs_xy[i_c] + shift * rng.uniform(-20, 20, (i_c.size, 1)) * n2
    )  # along edge 1 (direction n2)
    xy2 = prob.obs_xy[i_c] + shift * rng.uniform(-20, 20, (i_c.size, 1)) * n1
    w1 = np.stack([_edge_weight(v, sigma, k) for v in n1])
    w2 = np.stack([_edge_weight(v, sigma, k) for v in n2])
    keep = np.flatnonzero(~sel)
    edge = Problem(
        prob.frames,
        prob.ground,
        prob.ground_prior,
        prob.ground_weight,
        np.r_[prob.obs_frame[keep], prob.obs_frame[i_c], prob.obs_frame[i_c]],
        np.r_[prob.obs_point[keep], prob.obs_point[i_c], prob.obs_point[i_c]],
        np.r_[prob.obs_xy[keep], xy1, xy2],
        np.r_[prob.obs_weight[keep], w1, w2],
    )
    res = adjust(edge)
    assert res.converged
    tol = 1e-8 if np.isinf(k) else 1e-5
    for f in range(4):
        np.testing.assert_allclose(
            res.params[f],
            ref.params[f],
            rtol=tol,
            atol=tol * np.abs(ref.params[f]).max(),
        )
    np.testing.assert_allclose(
        res.ground, ref.ground, atol=1e-4 if np.isinf(k) else 1e-2
    )
    if np.isinf(
        k
    ):  # rank-1 observations: same statistics, redundancy numbers within [0, 1]
        assert res.sigma0 == pytest.approx(ref.sigma0, rel=1e-6)
        r_edge = res.redundancy[keep.size :]
        assert np.all((r_edge >= -1e-9) & (r_edge <= 1 + 1e-9))
        assert res.total_redundancy == pytest.approx(ref.total_redundancy)


def test_robust_and_snooping_reject_displaced_tie_observations():
    blk = affine_block(8, n_tie=300, size=22000.0)
    prob = blk["problem"]
    clean = adjust(prob)
    rng = np.random.default_rng(9)
    # a displacement of one of only two rays is partly absorbed by the point: use points seen >= 3 times
    views = np.bincount(prob.obs_point)[prob.obs_point]
    tie_obs = np.flatnonzero(~blk["ctrl"][prob.obs_point] & (views >= 3))
    bad = rng.choice(tie_obs, int(0.05 * tie_obs.size), replace=False)
    ang = rng.uniform(0, 2 * np.pi, bad.size)
    xy = prob.obs_xy.copy()
    xy[bad] += rng.uniform(5, 50, (bad.size, 1)) * np.c_[np.cos(ang), np.sin(ang)]
    dirty = Problem(
        prob.frames,
        prob.ground,
        prob.ground_prior,
        prob.ground_weight,
        prob.obs_frame,
        prob.obs_point,
        xy,
        prob.obs_weight,
    )
    res = adjust(dirty, AdjustOptions(robust=True, snooping=True))
    assert not res.obs_active[bad].any()
    false_alarms = (~res.obs_active).sum() - bad.size
    assert false_alarms <= 0.02 * prob.obs_frame.size
    assert np.all(res.obs_robust_weight[bad] == 0)
    for f in range(4):
        std = np.sqrt(np.diag(clean.param_cov[f]))
        assert np.all(np.abs(res.params[f] - clean.params[f]) < std)
    assert 0.7 < res.sigma0 < 1.2
    r = res.redundancy
    assert np.all(np.isnan(r[~res.obs_active]))
    ra = r[res.obs_active] / 2  # per component
    assert np.all((ra >= -1e-9) & (ra <= 1 + 1e-9))
    assert np.nansum(r) + res.pseudo_redundancy == pytest.approx(
        res.total_redundancy, rel=1e-8
    )
    assert np.all(res.normalized_residuals[res.obs_active] < 3.29 + 1e-9)


def test_snooping_alone_finds_a_single_blunder():
    blk = affine_block(10, n_tie=100)
    prob = blk["problem"]
    tie_obs = np.flatnonzero(
        ~blk["ctrl"][prob.obs_point]
        & (np.bincount(prob.obs_point)[prob.obs_point] >= 3)
    )
    i = tie_obs[0]
    prob.obs_xy[i] += [8.0, -6.0]
    res = adjust(prob, AdjustOptions(snooping=True))
    assert not res.obs_active[i]
    assert res.n_snooped >= 1 and (~res.obs_active).sum() <= 3


def test_tie_point_seen_once_is_dropped():
    blk = affine_block(11, n_tie=40)
    prob = blk["problem"]
    ref = adjust(prob)
    g_new = np.array([[5000.0, 5000.0, 100.0]])
    prob2 = Problem(
        prob.frames,
        np.r_[prob.ground, g_new],
        np.r_[prob.ground_prior, g_new],
        np.r_[prob.ground_weight, np.zeros((1, 3, 3))],
        np.r_[prob.obs_frame, 0],
        np.r_[prob.obs_point, prob.ground.shape[0]],
        np.r_[prob.obs_xy, [[170.0, 160.0]]],
        np.r_[prob.obs_weight, prob.obs_weight[:1]],
    )
    res = adjust(prob2)
    assert not res.point_valid[-1] and res.point_valid[:-1].all()
    np.testing.assert_array_equal(res.ground[-1], g_new[0])
    assert np.isnan(res.redundancy[-1])
    for f in range(4):
        np.testing.assert_allclose(res.params[f], ref.params[f], rtol=1e-9)
    assert res.sigma0 == pytest.approx(ref.sigma0, rel=1e-9)


def test_fixed_parameters_stay_and_match_dense_solution():
    blk = affine_block(12, n_tie=40)
    prob = blk["problem"]
    free = np.array([True, True, True, True, False, True])
    prob.frames[2].free = free
    fixed_value = prob.frames[2].params[4]
    res = adjust(prob, AdjustOptions(max_iter=1))
    assert res.params[2][4] == fixed_value
    start = [fr.params for fr in prob.frames]
    frees = [np.arange(6)] * 4
    frees[2] = np.flatnonzero(free)
    n, t, _, offs = dense_normals(prob, start, prob.ground, frees)
    dx = np.linalg.solve(n, t)
    np.testing.assert_allclose(
        res.params[2][free] - start[2][free],
        dx[offs[2] : offs[3]],
        rtol=1e-8,
        atol=1e-12,
    )
    assert np.all(res.param_cov[2][4] == 0) and np.all(res.param_cov[2][:, 4] == 0)
    full = adjust(prob)
    assert full.converged and full.params[2][4] == fixed_value


def _collinearity_strip(mdl: Collinearity) -> tuple[Problem, list[np.ndarray]]:
    """Three overlapping frames, 12 control points, ties, 0.2 px noise, perturbed start."""
    rng = np.random.default_rng(13)
    truth = [
        np.r_[1000.0 + 2000.0 * k, 2500.0, 5000.0, rng.normal(0, 0.01, 3)]
        for k in range(3)
    ]
    pts = np.c_[
        rng.uniform(-1000, 7000, (400, 1)),
        rng.uniform(0, 5000, (400, 1)),
        rng.uniform(0, 300, (400, 1)),
    ]
    of, op, xy = [], [], []
    for f in range(3):
        im = mdl.project(truth[f], pts)
        ok = np.all((im > 0) & (im < 1000), axis=1)
        of.append(np.full(ok.sum(), f))
        op.append(np.flatnonzero(ok))
        xy.append(im[ok])
    of, op, xy = np.concatenate(of), np.concatenate(op), np.concatenate(xy)
    seen = np.bincount(op, minlength=400)
    ctrl = np.zeros(400, bool)
    ctrl[rng.choice(np.flatnonzero(seen >= 1), 12, replace=False)] = True
    use = ctrl | (seen >= 2)
    remap = np.cumsum(use) - 1
    sel = use[op]
    of, op, xy = of[sel], remap[op[sel]], xy[sel] + rng.normal(0, 0.2, (sel.sum(), 2))
    pts, ctrl = pts[use], ctrl[use]
    gw = np.zeros((pts.shape[0], 3, 3))
    gw[ctrl] = np.eye(3) / 0.5**2
    ground0 = pts + rng.normal(0, 20, pts.shape) * ~ctrl[:, None]
    start = [p + np.r_[rng.normal(0, 30, 3), rng.normal(0, 0.005, 3)] for p in truth]
    prob = Problem(
        [Frame(mdl, s) for s in start],
        ground0,
        pts.copy(),
        gw,
        of,
        op,
        xy,
        np.broadcast_to(np.eye(2) / 0.2**2, (of.size, 2, 2)).copy(),
    )
    return prob, truth


def test_collinearity_strip_converges_from_perturbed_start():
    prob, truth = _collinearity_strip(Collinearity())
    res = adjust(prob)
    assert res.converged
    assert 0.8 < res.sigma0 < 1.2
    for f in range(3):
        err = res.params[f] - truth[f]
        assert np.all(np.abs(err) < 5 * np.sqrt(np.diag(res.param_cov[f])))
    assert np.abs(res.residuals).max() < 6 * 0.2


class NoisyCollinearity(Collinearity):
    """The frame camera with a deterministic 1e-10 px evaluation noise (like an iterative solve)."""

    def project(self, p: np.ndarray, g: np.ndarray) -> np.ndarray:
        xy = super().project(p, g)
        phase = 1e9 * (p.sum() + g.sum(axis=1))  # changes at every parameter or ground change
        return xy + 1e-10 * np.sin(phase)[:, None] * np.array([1.0, -1.0])


def test_relative_convergence_works_below_the_model_noise():
    """The absolute step test cannot pass below a model's evaluation noise; the relative one does.

    With ``tol`` below the noise of the numeric Jacobians (1e-10 px / 0.01 m steps), the
    absolute test never fires (``rtol = 0`` runs to ``max_iter``); the relative test stops after a
    few iterations at the same solution.  So does a bilinear affine block with ``tol = 0``.
    """
    prob, _ = _collinearity_strip(NoisyCollinearity())
    ref, _ = _collinearity_strip(Collinearity())
    exact = adjust(ref, AdjustOptions(covariance=False))
    absolute = adjust(prob, AdjustOptions(tol=1e-12, rtol=0.0, max_iter=12, covariance=False))
    assert not absolute.converged and absolute.iterations == 12 and absolute.convergence == ""
    relative = adjust(prob, AdjustOptions(tol=1e-12, covariance=False))
    assert relative.converged and relative.convergence == "relative" and relative.iterations <= 8
    for f in range(3):
        np.testing.assert_allclose(relative.params[f], exact.params[f], rtol=0, atol=1e-4)
    # Levenberg-Marquardt kept: the damped run reaches the same solution by the relative test
    damped = adjust(prob, AdjustOptions(tol=1e-12, damping=1.0, covariance=False))
    assert damped.converged and damped.convergence == "relative"
    for f in range(3):
        np.testing.assert_allclose(damped.params[f], exact.params[f], rtol=0, atol=1e-4)
    linear = adjust(affine_block(3, n_tie=150)["problem"], AdjustOptions(tol=0.0, covariance=False))
    assert linear.converged and linear.convergence == "relative" and linear.iterations <= 5
