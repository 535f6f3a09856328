"""Least-squares block adjustment of scanner frames with points eliminated first (seed 000 sec. 2.4).

The linearised observation equations (seed eq 3) of every image observation ``i`` of ground
point ``p`` in frame ``f`` are ``J_p,i dp_f + J_g,i dg_p = f_i - v_i`` with ``f_i`` the observed
minus the projected image coordinates.  Frames and points can carry pseudo-observations (prior
weights).  The normal equations (eq 4)

    [ N_ff  N_fg ] [dp]   [t_p]
    [ N_gf  N_gg ] [dg] = [t_g]

are reduced by eliminating the ground points first (eq 5): ``N_gg`` is block diagonal with one
3x3 block per point, so ``S = N_ff - N_fg N_gg^-1 N_gf`` is a sparse matrix with one ``n x n``
block for every pair of frames that share a point.  ``S dp = t_p - N_fg N_gg^-1 t_g`` is solved with
a sparse factorisation and the ground corrections are back-substituted per point.

The assembly of ``S`` (:mod:`geocoder.adjust.normals`) streams the observations in chunks of
whole frames, so the working memory is bounded by ``AdjustOptions.block_size``; the precision
figures live in :mod:`geocoder.adjust.statistics`.  Everything is vectorised over observations
and points; the only Python loops are over frames (one model call and one GEMM each), chunks,
buckets of frame pairs of similar size, and iterations.

References
----------
Paderes, Mikhail & Foerstner (1984), Rectification of single and multiple frames of satellite
scanner imagery using points and edges as control, eqs 3-5 (block adjustment), eqs 20b and 22b
(robust weight functions).

The modules: the data types in :mod:`geocoder.adjust.problem`, the sensor-model protocol and
the numeric Jacobian in :mod:`geocoder.adjust.sensor`, the Gauss-Newton iterations on the
reduced system in :mod:`geocoder.adjust.gauss_newton`, the robust and snooping driver
(:func:`adjust`) in :mod:`geocoder.adjust.driver`.  This module gathers the public names.
"""

from __future__ import annotations

from .driver import adjust
from .problem import AdjustOptions, AdjustResult, Frame, Problem
from .sensor import SensorModel, numeric_jacobians

__all__ = [
    "AdjustOptions",
    "AdjustResult",
    "Frame",
    "Problem",
    "SensorModel",
    "adjust",
    "numeric_jacobians",
]
