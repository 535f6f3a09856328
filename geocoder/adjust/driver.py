"""The block adjustment's driver: plain, robust (seed eqs 20b, 22b) and data-snooping rounds.

:func:`adjust` runs :func:`~geocoder.adjust.gauss_newton.gauss_newton` on the reduced normal
equations, re-weights the observations between rounds, rejects blunders and collects the
precision figures (:mod:`geocoder.adjust.statistics`) into an
:class:`~geocoder.adjust.problem.AdjustResult`.

References
----------
Paderes, Mikhail & Foerstner (1984), Rectification of single and multiple frames of satellite
scanner imagery using points and edges as control, eqs 3-5 (block adjustment), eqs 20b and 22b
(robust weight functions).
"""

from __future__ import annotations

import numpy as np

from ..kernels.robust import weight_exp, weight_l1
from .gauss_newton import gauss_newton
from .layout import layout
from .problem import AdjustOptions, AdjustResult, Problem
from .statistics import robust_scale, statistics

__all__ = ["adjust"]


def adjust(problem: Problem, options: AdjustOptions | None = None) -> AdjustResult:
    """Least-squares block adjustment with the ground points eliminated first (seed eqs 3-5).

    Parameters
    ----------
    problem : Problem
        Frames, ground points and image observations.
    options : AdjustOptions, optional
        Iteration, robust estimation, data snooping and covariance options.

    Returns
    -------
    AdjustResult

    Notes
    -----
    * Gauss-Newton (optionally Levenberg-Marquardt damped) on the reduced normal equations
      ``S dp = r``; ``S`` is assembled as a sparse matrix from one ``n x n`` block per pair of
      frames sharing points and factorised with CHOLMOD if scikit-sparse is importable, else
      ordered by a reverse Cuthill-McKee numbering of the frames (seed sec. 2.4: proper
      numbering makes the reduced system banded) and solved by banded Cholesky
      (``scipy.linalg.solveh_banded``) when the band fits in memory, else by SuperLU
      (``scipy.sparse.linalg.splu``).
    * Points with a singular 3x3 normal block (a tie point seen once and without prior, all of
      its observations rejected...) are left out together with their observations
      (``point_valid``).
    * Robust estimation (``options.robust``) runs after a plain adjustment: each observation
      gets ``w(v)`` of its normalised residual ``v = sqrt(r^T W r / rank(W)) / sigma0``; eq 20b
      for ``robust_l1_iterations`` rounds with a median based (approximately redundancy
      corrected) ``sigma0``, then eq 22b for ``robust_exp_iterations`` rounds with the ``sigma0``
      of the observations kept in the previous round.  Weights are recomputed for every observation
      in every round; factors below ``robust_min_weight`` in the last round reject the
      observation.  The final adjustment uses the original weights of the kept observations.
    * Data snooping (``options.snooping``) rejects the observation with the largest test
      statistic ``sqrt(v^T W v) / (sigma0 sqrt(r_i))`` above ``snooping_threshold`` and
      re-adjusts, at most ``max_snoop_rounds`` times.
    * Redundancy numbers, normalised residuals, covariances and snooping need the dense inverse
      of ``S``; when there are more than ``options.max_dense_unknowns`` reduced unknowns they are
      skipped: ``redundancy``, ``normalized_residuals``, ``param_cov`` and ``ground_cov`` are
      None and no snooping takes place.
    * The frame parameters' fixed entries (``Frame.free``) are removed from the unknowns.
    """
    opt = AdjustOptions() if options is None else options
    lay = layout(problem, opt.block_size)
    models = [fr.model for fr in problem.frames]
    params = [np.asarray(fr.params, dtype=np.float64).copy() for fr in problem.frames]
    ground = np.asarray(problem.ground, dtype=np.float64).copy()
    m = lay.obs_frame.size
    times: list[float] = []
    active = np.ones(m, bool)
    rweight = np.ones(m)
    st = gauss_newton(lay, models, params, ground, active.astype(float), opt, times)
    if opt.robust:
        kinds = [weight_l1] * opt.robust_l1_iterations + [
            weight_exp
        ] * opt.robust_exp_iterations
        for rnd, wfun in enumerate(
            kinds
        ):  # weights are recomputed for every observation in every round
            raw, sig = robust_scale(
                lay, st.params, st.ground, st.res, st.normals, trimmed=wfun is weight_exp and rnd > 0
            )
            rweight = wfun(raw / sig)
            active = rweight >= opt.robust_min_weight
            rweight[~active] = 0.0
            st = gauss_newton(lay, models, st.params, st.ground, rweight, opt, times)
        st = gauss_newton(
            lay, models, st.params, st.ground, active.astype(float), opt, times
        )
    dense = lay.n_unknowns <= opt.max_dense_unknowns
    n_snooped = 0
    stats = statistics(
        lay, models, st.params, st.ground, st.res, st.normals, dense=dense and (opt.snooping or opt.covariance)
    )
    if opt.snooping and dense:
        for _ in range(opt.max_snoop_rounds):
            wt = np.where(np.isfinite(stats.wtest), stats.wtest, -np.inf)
            worst = int(np.argmax(wt)) if m else 0
            if m == 0 or wt[worst] <= opt.snooping_threshold:
                break
            active[worst] = False
            rweight[worst] = 0.0
            n_snooped += 1
            st = gauss_newton(
                lay, models, st.params, st.ground, active.astype(float), opt, times
            )
            stats = statistics(lay, models, st.params, st.ground, st.res, st.normals, dense=True)
    full = dense and (opt.covariance or opt.snooping)

    def back(x: np.ndarray | None) -> np.ndarray | None:
        if x is None:
            return None
        y = np.empty_like(x)
        y[lay.order] = x
        return y

    return AdjustResult(
        params=st.params,
        ground=st.ground,
        residuals=back(st.res),
        sigma0=stats.sigma0,
        iterations=st.iterations,
        converged=st.converged,
        convergence=st.convergence,
        obs_active=back(active),
        obs_robust_weight=back(rweight),
        redundancy=back(stats.redundancy) if full else None,
        normalized_residuals=back(stats.wtest) if full else None,
        param_cov=stats.param_cov if (full and opt.covariance) else None,
        ground_cov=stats.ground_cov if (full and opt.covariance) else None,
        time_per_iteration=times,
        solver=st.solver,
        point_valid=st.normals.valid.copy(),
        total_redundancy=float(stats.dof),
        pseudo_redundancy=stats.pseudo_redundancy if full else None,
        n_snooped=n_snooped,
    )
