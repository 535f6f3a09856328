"""The reduced normal equations solved by (damped) Gauss-Newton (seed 000 sec. 2.4, eqs 3-5).

With the ground points eliminated first, ``S dp = r`` (assembled by
:mod:`geocoder.adjust.normals`) is solved with CHOLMOD if scikit-sparse is importable, else in
a reverse Cuthill-McKee order of the frame graph by banded Cholesky when the band fits in
memory, else by SuperLU; the ground corrections are back-substituted per point.
:func:`gauss_newton` iterates this to convergence (step or MINPACK-style relative test), with
optional Levenberg-Marquardt damping.  The robust and snooping rounds around it are
:mod:`geocoder.adjust.driver`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .layout import Layout
from .normals import Normals, assemble, back_substitute, hold_to_dem, residuals
from .normals import cost as _cost
from .problem import AdjustOptions
from .sensor import SensorModel

try:  # optional, faster and symmetric
    from sksparse.cholmod import cholesky as _cholmod_cholesky  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the environment
    _cholmod_cholesky = None

__all__ = ["GaussNewtonState", "frame_order", "gauss_newton", "solve_reduced"]

_BANDED_MAX_ENTRIES = (
    1 << 26
)  # banded Cholesky when (bandwidth + 1) * unknowns is below this (512 MB)




def frame_order(lay: Layout, pairs: np.ndarray) -> tuple[np.ndarray, int]:
    """Unknown permutation from a reverse Cuthill-McKee ordering of the frame graph, and its bandwidth."""
    nf = lay.n_frames
    adj = sp.coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(nf, nf)
    ).tocsr()
    order = reverse_cuthill_mckee((adj + adj.T).tocsr(), symmetric_mode=True)
    perm = lay.idx[order].ravel()
    perm = perm[perm >= 0]
    pos = np.empty(lay.n_frames, dtype=np.int64)
    pos[order] = np.arange(nf)
    # bandwidth in unknowns: frames coupled at distance d in the order -> < (d + 1) * nmax
    nfree = (lay.idx >= 0).sum(axis=1)
    first = np.zeros(nf + 1, dtype=np.int64)
    first[1:] = np.cumsum(nfree[order])
    pa, pb = pos[pairs[:, 0]], pos[pairs[:, 1]]
    lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
    bw = int(
        np.max(first[hi + 1] - 1 - first[lo], initial=int(nfree.max(initial=1)) - 1)
    )
    return perm, bw


def solve_reduced(
    s: sp.csc_matrix, r: np.ndarray, order: tuple[np.ndarray, int] | None = None
) -> tuple[np.ndarray, str]:
    """Solve the reduced normal equations: CHOLMOD, banded Cholesky (RCM frame order) or SuperLU."""
    n = r.size
    if n == 0:
        return r.copy(), "none"
    if _cholmod_cholesky is not None:  # pragma: no cover - optional dependency
        try:
            return _cholmod_cholesky(s)(r), "cholmod"
        except Exception:  # noqa: BLE001, S110 - not positive definite: use the fallbacks below
            pass
    if order is not None:
        perm, bw = order
        if (bw + 1) * n <= _BANDED_MAX_ENTRIES and bw < n // 2:
            sp_ = s[perm][:, perm].tocoo()
            # frame pairs whose shared observations are all unused are stored zero blocks and
            # may lie outside the band of the coupled pairs
            up = (sp_.row <= sp_.col) & (sp_.col - sp_.row <= bw)
            ab = np.zeros((bw + 1, n))
            ab[bw + sp_.row[up] - sp_.col[up], sp_.col[up]] = sp_.data[up]
            try:
                x = scipy.linalg.solveh_banded(
                    ab, r[perm], overwrite_ab=True, check_finite=False
                )
            except np.linalg.LinAlgError:
                pass
            else:
                out = np.empty(n)
                out[perm] = x
                return out, "banded-cholesky"
    try:
        lu = spla.splu(s, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as exc:
        raise np.linalg.LinAlgError(
            "the reduced normal matrix is singular: add control, priors or fix parameters (datum defect)"
        ) from exc
    return lu.solve(r), "splu"


@dataclass
class GaussNewtonState:
    """Parameters, ground points, residuals and normal equations at the end of :func:`gauss_newton`."""

    params: list[np.ndarray]
    ground: np.ndarray
    res: np.ndarray
    normals: Normals
    iterations: int = 0
    converged: bool = False
    solver: str = "splu"
    convergence: str = ""


def _relative_converged(
    lay: Layout,
    res: np.ndarray,
    nrm: Normals,
    u: np.ndarray,
    dg: np.ndarray,
    new_params: list[np.ndarray],
    new_ground: np.ndarray,
    cost: float,
    new_cost: float,
    rtol: float,
) -> bool:
    """MINPACK-style test: actual and predicted relative reductions of the cost both <= rtol.

    ``u`` is ``J_p dp`` per observation (:func:`geocoder.adjust.normals.back_substitute`).
    """
    if not abs(cost - new_cost) <= rtol * cost:
        return False
    step_img = u + np.einsum("mij,mj->mi", nrm.jg, dg[lay.obs_point])
    lin_res = np.where(nrm.used[:, None], res - step_img, 0.0)  # unused rows may hold NaN
    lin_cost = _cost(lay, lin_res, nrm.w, new_params, new_ground, nrm.valid)
    return cost - lin_cost <= rtol * cost


def gauss_newton(
    lay: Layout,
    models: list[SensorModel],
    params: list[np.ndarray],
    ground: np.ndarray,
    factor: np.ndarray,
    opt: AdjustOptions,
    times: list[float],
) -> GaussNewtonState:
    """Iterate the reduced normal equations from ``params``, ``ground`` with the observation weight ``factor``."""
    hold_to_dem(lay, ground)
    res = residuals(lay, models, params, ground)
    nrm = assemble(lay, models, params, ground, res, factor, keep_jacobians=opt.keep_jacobians)
    cost = _cost(lay, res, nrm.w, params, ground, nrm.valid)
    lam = float(opt.damping)
    state = GaussNewtonState(params, ground, res, nrm)
    for it in range(opt.max_iter):
        t0 = time.perf_counter()
        s = nrm.s
        if lam > 0:
            s = (s + sp.diags(lam * s.diagonal())).tocsc()
        dp, state.solver = solve_reduced(s, nrm.r, frame_order(lay, nrm.frame_pairs))
        dpad = np.zeros((lay.n_frames, lay.nmax))
        sel = lay.idx >= 0
        dpad[sel] = dp[lay.idx[sel]]
        u, dg = back_substitute(lay, models, params, ground, nrm, dpad)
        new_params = []
        for f in range(lay.n_frames):
            p = params[f].copy()
            p[lay.free[f]] += dpad[f, : lay.free[f].size]
            new_params.append(p)
        new_ground = ground + dg
        new_res = residuals(lay, models, new_params, new_ground)
        hold_to_dem(lay, new_ground)  # the DEM misclosure at the new points enters the cost
        new_cost = _cost(lay, new_res, nrm.w, new_params, new_ground, nrm.valid)
        state.iterations = it + 1
        if lam > 0 and not new_cost <= cost:  # NaN (a point lost by a wild step) counts as worse
            # a rejected step that is already negligible: the cost is at its minimum (to rounding)
            at_minimum = (
                opt.rtol > 0
                and np.isfinite(new_cost)
                and _relative_converged(lay, res, nrm, u, dg, new_params, new_ground, cost, new_cost, opt.rtol)
            )
            hold_to_dem(lay, ground)
            times.append(time.perf_counter() - t0)
            if at_minimum:
                state.converged, state.convergence = True, "relative"
                break
            lam *= 10.0
            continue
        lam_used = lam
        if lam > 0:
            lam /= 10.0
        step = max(
            float(np.max(np.abs(dp) * np.sqrt(np.abs(nrm.s.diagonal())), initial=0.0)),
            float(np.max(np.abs(dg) * np.sqrt(np.abs(nrm.ngg_diag)), initial=0.0)),
        )
        relative = opt.rtol > 0 and _relative_converged(
            lay, res, nrm, u, dg, new_params, new_ground, cost, new_cost, opt.rtol / (1.0 + lam_used)
        )
        solver = state.solver
        del nrm, state, u  # keep one set of normal equations in memory
        params, ground, res = new_params, new_ground, new_res
        nrm = assemble(lay, models, params, ground, res, factor, keep_jacobians=opt.keep_jacobians)
        cost = _cost(lay, res, nrm.w, params, ground, nrm.valid)
        state = GaussNewtonState(params, ground, res, nrm, it + 1, False, solver)
        times.append(time.perf_counter() - t0)
        if step < opt.tol or relative:
            state.converged = True
            state.convergence = "step" if step < opt.tol else "relative"
            break
    return state
