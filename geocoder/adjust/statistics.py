"""Precision of a block adjustment: sigma0, covariances, redundancy numbers, robust scale.

Everything that needs the Jacobians is computed group by group
(:func:`geocoder.adjust.normals.point_groups`), so, like the assembly, it works in memory
bounded by the block size and the reduced system (here its dense inverse).

References
----------
Paderes, Mikhail & Foerstner (1984), Rectification of single and multiple frames of satellite
scanner imagery using points and edges as control, sec. 2.4 (precision, data snooping).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from .normals import (
    _GEMM_BUDGET,
    Layout,
    Normals,
    _frame_runs,
    cost,
    point_groups,
    ranks,
    same_point_pairs,
    sum_by,
)

__all__ = ["Stats", "redundancy_total", "robust_scale", "statistics"]


def redundancy_total(lay: Layout, nrm: Normals) -> float:
    """Rank-counted observations and pseudo-observations minus unknowns.

    Parameters
    ----------
    lay : Layout
    nrm : Normals

    Returns
    -------
    float
    """
    n_obs = float(lay.obs_rank[nrm.used].sum())
    n_pseudo = float(lay.prior_rank + lay.ground_rank[nrm.valid].sum())
    return n_obs + n_pseudo - lay.n_unknowns - 3.0 * float(nrm.valid.sum())


@dataclass
class Stats:
    """What :func:`statistics` finds (the arrays only with ``dense``).

    Attributes
    ----------
    sigma0, dof : float
    redundancy, wtest : ndarray, shape (M,), or None
        Redundancy numbers and normalised residuals (layout order).
    param_cov : list of ndarray or None
    ground_cov : ndarray, shape (P, 3, 3), or None
    pseudo_redundancy : float or None
    """

    sigma0: float
    dof: float
    redundancy: np.ndarray | None = None
    wtest: np.ndarray | None = None
    param_cov: list[np.ndarray] | None = None
    ground_cov: np.ndarray | None = None
    pseudo_redundancy: float | None = None


def _groups(
    lay: Layout, models: Sequence[Any], params: Sequence[np.ndarray], ground: np.ndarray, nrm: Normals
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    return point_groups(lay, nrm.jacobian_source(lay, models, params, ground))


def statistics(
    lay: Layout,
    models: Sequence[Any],
    params: Sequence[np.ndarray],
    ground: np.ndarray,
    res: np.ndarray,
    nrm: Normals,
    *,
    dense: bool,
) -> Stats:
    """sigma0 and, with ``dense``, covariances, redundancy numbers and normalised residuals.

    Parameters
    ----------
    lay : Layout
    models : sequence of SensorModel
    params : sequence of ndarray
    ground : ndarray, shape (P, 3)
        The point of linearisation of ``nrm``.
    res : ndarray, shape (M, 2)
    nrm : Normals
    dense : bool
        Invert ``S`` densely and compute the per-observation figures.

    Returns
    -------
    Stats

    Notes
    -----
    With ``Q = S^-1`` and, per observation, ``Y_i = Q[:, f_i]^T``-weighted couplings through
    its point, the covariance of the predicted observation is
    ``B = G Q G^T + J_g N_gg^-1 J_g^T`` with ``G = J_p - J_g N_gg^-1 N_gp``; the redundancy
    number is ``rank(W_i) - tr(W_i B_i)``.
    """
    omega = cost(lay, res, nrm.w, params, ground, nrm.valid)
    dof = redundancy_total(lay, nrm)
    sigma0 = float(np.sqrt(omega / dof)) if dof > 0 else float("nan")
    out = Stats(sigma0, dof)
    if not dense:
        return out
    s2 = sigma0**2 if np.isfinite(sigma0) else 1.0
    nu, nf, nmax = lay.n_unknowns, lay.n_frames, lay.nmax
    sdense = nrm.s.toarray()
    if nu:
        try:
            q = scipy.linalg.cho_solve(scipy.linalg.cho_factor(sdense), np.eye(nu))
        except np.linalg.LinAlgError:
            q = np.linalg.inv(sdense)
    else:
        q = np.zeros((0, 0))
    qpad = np.zeros((nu + 1, nu + 1))
    qpad[:nu, :nu] = q
    idx = np.where(lay.idx >= 0, lay.idx, nu)
    qdiag = qpad[idx[:, :, None], idx[:, None, :]]  # (F, n, n)
    m = lay.obs_frame.size
    red = np.full(m, np.nan)
    wt = np.full(m, np.nan)
    qgg = nrm.ninv.copy()  # points without observations: their prior alone
    s0_ok = sigma0 if np.isfinite(sigma0) else 1.0
    for obs, jp, jg in _groups(lay, models, params, ground, nrm):
        pt, frm = lay.obs_point[obs], lay.obs_frame[obs]
        upt, loc = np.unique(pt, return_inverse=True)
        loc = loc.ravel()
        w, used = nrm.w[obs], nrm.used[obs]
        ct = np.matmul(np.matmul(w, jg).transpose(0, 2, 1), jp)  # N_gp per observation (3, n)
        # Yt_i = (Q[f_i, :] N_fg[:, p_i])^T = sum_b C_b^T Q[f_b, f_i]   (3, n)
        a, b = same_point_pairs(np.flatnonzero(used), loc, ordered=True)
        yt = np.zeros((obs.size, 3, nmax))
        step = max(1, _GEMM_BUDGET // max(nmax, 1))
        for j in range(0, a.size, step):  # chunks of pairs, bounded memory
            aa, bb = a[j : j + step], b[j : j + step]
            qb = qpad[idx[frm[bb]][:, :, None], idx[frm[aa]][:, None, :]]
            np.add.at(yt, aa, np.matmul(ct[bb], qb))
        # V_p = N_gp Q N_fg[:, p] = sum_b C_b^T Y_b
        v = sum_by(loc, np.einsum("min,mjn->mij", ct, yt), upt.size)
        del ct
        ninv = nrm.ninv[upt]
        qgg[upt] = ninv + np.matmul(np.matmul(ninv, v), ninv)
        k = np.matmul(jg, ninv[loc])  # (m, 2, 3)
        jq = np.zeros_like(jp)
        for f, s0, s1 in zip(*_frame_runs(frm)):  # one small GEMM per frame
            jq[s0:s1] = jp[s0:s1] @ qdiag[f]
        jy = np.matmul(jp, yt.transpose(0, 2, 1))  # Jp Y  (m, 2, 3)
        bmat = np.matmul(jq, jp.transpose(0, 2, 1)) - np.matmul(jy, k.transpose(0, 2, 1))
        bmat -= np.matmul(k, jy.transpose(0, 2, 1))
        bmat += np.matmul(np.matmul(k, v[loc]), k.transpose(0, 2, 1))
        bmat += np.matmul(k, jg.transpose(0, 2, 1))
        wb = np.einsum("mij,mji->m", w, bmat)
        r = np.where(used, lay.obs_rank[obs] - wb, np.nan)
        vwv = np.einsum("mi,mij,mj->m", res[obs], w, res[obs])
        with np.errstate(invalid="ignore", divide="ignore"):
            wt[obs] = np.where(used & (r > 1e-10), np.sqrt(vwv / r) / s0_ok, np.nan)
        red[obs] = r
    # pseudo-observations
    pseudo = 0.0
    for f in range(nf):  # O(frames)
        if lay.prior_w[f] is not None:
            kf = lay.free[f].size
            pw = lay.prior_w[f]
            pseudo += float(ranks(pw[None])[0]) - float(np.sum(pw * qdiag[f, :kf, :kf]))
    vg = nrm.valid
    pseudo += float(lay.ground_rank[vg].sum() - np.einsum("pij,pji->", lay.ground_weight[vg], qgg[vg]))
    param_cov = []
    for f in range(nf):
        n_all = params[f].size
        c = np.zeros((n_all, n_all))
        fi = lay.free[f]
        c[np.ix_(fi, fi)] = s2 * qdiag[f, : fi.size, : fi.size]
        param_cov.append(c)
    gcov = s2 * qgg
    gcov[~vg] = np.nan
    out.redundancy, out.wtest, out.param_cov, out.ground_cov, out.pseudo_redundancy = red, wt, param_cov, gcov, pseudo
    return out


def robust_scale(
    lay: Layout,
    params: Sequence[np.ndarray],
    ground: np.ndarray,
    res: np.ndarray,
    nrm: Normals,
    *,
    trimmed: bool,
) -> tuple[np.ndarray, float]:
    """Per-observation ``sqrt(r^T W r / rank)`` (nominal weights) and a robust sigma0 estimate.

    Parameters
    ----------
    lay : Layout
    params : sequence of ndarray
    ground : ndarray, shape (P, 3)
    res : ndarray, shape (M, 2)
    nrm : Normals
        Of the last adjustment round.
    trimmed : bool
        sigma0 of the observations kept in the last round (those with a positive weight
        factor), with their nominal weights, ``sqrt(Omega / redundancy)``.  Otherwise
        (resistant to any fraction of gross errors below one half, somewhat low): the median
        of the residuals standardised with an approximate redundancy fraction per point,
        ``1 - 3 / (components observed at the point + rank of its prior)``, divided by the
        median of ``sqrt(chi2_k / k)`` (k = rank of the weight).

    Returns
    -------
    raw : ndarray, shape (M,)
    sigma0 : float
    """
    rk = np.maximum(lay.obs_rank, 1)
    vwv = np.einsum("mi,mij,mj->m", res, lay.obs_weight, res)
    raw = np.sqrt(vwv / rk)
    if trimmed:
        omega = cost(lay, res, lay.obs_weight * nrm.used[:, None, None], params, ground, nrm.valid)
        dof = redundancy_total(lay, nrm)
        if dof > 0 and omega > 0:
            return raw, float(np.sqrt(omega / dof))
    pt = lay.obs_point
    use = nrm.valid[pt] & (lay.obs_rank > 0)
    ncomp = np.bincount(pt[use], weights=lay.obs_rank[use], minlength=lay.n_points) + lay.ground_rank
    frac = 1.0 - 3.0 / np.maximum(ncomp, 1.0)
    use &= frac[pt] > 0.05
    if not use.any():
        return raw, 1.0
    # medians of sqrt(chi2_k / k): k = 1 -> 0.6745, k = 2 -> sqrt(ln 2) = 0.8326
    med = np.where(lay.obs_rank[use] >= 2, np.sqrt(np.log(2.0)), 0.6745)
    sig = float(np.median(raw[use] / np.sqrt(frac[pt[use]]) / med))
    return raw, max(sig, np.finfo(float).tiny)
