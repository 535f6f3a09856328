"""Least-squares matching of every pixel of a window at once, on a field-warped image.

:mod:`geocoder.kernels.alsc` matches one template at a time: each evaluation resamples the
distorted image under that template's own affine, so a pixel costs 4-6 evaluations of 357
samples. When a displacement field ``d0`` is already known to a fraction of a pixel (the
region growing's lattice, interpolated along the scan lines), the distorted image and its
gradients can instead be resampled ONCE per iteration for the whole window at
``p + d(p)``; every template then sees the same warped image ``I``, and all of its normal
equations are window sums of products of per-pixel images, which sliding sums give at
O(1) per pixel whatever the template size.

Per template (``(2 rx + 1) x (2 ry + 1)`` pixels centred on ``p``, offsets ``u, v``) the
model is the Otto-Chau/Gruen one, linearised about the current position ``q(x)`` of EVERY
template pixel ``x`` (not about the centre's), with the radiometry made linear by scaling the
geometric unknowns with the gain::

    T(x) ~ alpha y_p(x) + beta + gx (sx + c11 u + c12 v) + gy (sy + c21 u + c22 v)
    y_p(x) = I(x + q(x)) - g(x) . (q(x) - q(p))

(``T`` the base template, ``I`` the distorted image, ``g = (gx, gy)`` the slopes of its
bilinear interpolant at ``x + q(x)``: the exact derivatives, so that ``I + g . dq`` IS the
interpolant wherever ``dq`` stays in the same cell, which makes the solution that of ALSC
sampled at its own affine, not a function of how rough the neighbours' positions are).
The unknowns are linear: the position of ``p`` moves by ``(sx, sy) / alpha`` and its affine
by ``c / alpha``; ``alpha, beta`` are gain and offset. The centring on ``q(p)`` is done
algebraically from the same window sums, so one set of sums serves every template. The
statistics are those of the last evaluation, as in ALSC: ``sigma0^2 = e.e / (n - 8)`` of the
residuals in the template's grey values, the shift covariance
``sigma0^2 [N^-1]_ss / alpha^2`` (the shift block of the full inverse) and ``rho``, the
correlation coefficient of ``T`` and ``I`` over the template.

The window sums ``sum u^a v^b f`` (``a + b <= 2``) come from prefix sums along each row
(moments about the centre from those of the column index) and a direct sum over the
``2 ry + 1`` rows, kept in a ring buffer of rows, so memory is a few rows per channel
(:mod:`geocoder.kernels.window_sums`, with the normal equations made from them; this
module, a little over 500 lines, is the solve per window, the rounds and the acceptance).

That is ``gradients="image"``. The default, ``gradients="template"``, takes the design's
slopes from the base template (its central differences: fixed, and free of the resampled
image's noise, which the interpolant's slopes carry into the design and which biases their
fixed point on smooth texture) and needs no linearisation about each centre: every round
averages the field over the template's box, resamples the image at that smooth field, solves

    T(x) ~ alpha I(x + qbar(x)) + beta + gx_T (sx + c11 u + c12 v) + gy_T (sy + c21 u + c22 v)

(the template's move in its own grey values: no division by the gain) and moves the pixel to
``qbar(p) + (sx, sy)``. A pixel's own noise so never feeds back except through the box mean;
the fixed point's remaining noise gain (1.16 for 51 x 7) is folded into sigma. The image is
sampled there with a Lanczos-3 kernel, not bilinearly: a bilinear sample smooths the image's
detail (which the template keeps, so sharp texture leaves a residual that inflates sigma and
pulls the shift) and averages its noise by a share that changes with the position's fraction
(which makes sigma optimistic). On the nine cases of ``benchmarks/bench_dense_cases.py`` the
matched pixels' RMSE fell 4-45 % with it (Landsat 0.030 -> 0.020 px, aerial 0.028 -> 0.019 px),
for about 5 % more of the pass's time (24 ms more per round of a 1024 tile; issue 14's notes).

Dependencies are local: after ``n`` iterations a pixel depends on ``d0`` within ``n`` template
half-sizes of it (``2 n`` with the template's gradients: the box, then the template), and on
the images one template further, so a tile computed with that halo gives the same result for
any tiling. Exit codes are those of :class:`geocoder.kernels.alsc.Exit`, decided in the same order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .alsc import Exit
from .resample import LANCZOS_TABLE
from .window_sums import (
    _NPLANES,
    _NPLANES_SOLVE,
    _NSUMS,
    _P0,
    _P1,
    _P2,
    _P3,
    _P4,
    _P5,
    _P6,
    _P7,
    S_R,
    S_RR,
    S_T,
    S_TR,
    S_TT,
    S_W,
    _add_row,
    _assemble,
    _centred_sums,
    _ldl_solve8,
    _precision_sums,
    _row_planes,
    _sample,
    _sample_lanczos,
    _warp,
)

__all__ = ["FieldLsqResult", "field_lsq", "template_solution_reference"]

# Planes of ``sol`` (8, h, w) and ``stats`` (5, h, w), the per-pixel results of a round (see
# :func:`_solve_window`): the move and the affine correction, the radiometry; sigma, rho, exit code.
_DX, _DY, _B11, _B12, _B21, _B22, _GAIN, _OFFSET = range(8)
_SIGMA_X, _SIGMA_Y, _COV_XY, _RHO, _CODE = range(5)

_ACCEPTED = int(Exit.ACCEPTED)
_OUTSIDE = int(Exit.OUTSIDE)
_SINGULAR = int(Exit.SINGULAR)
_NOT_CONVERGED = int(Exit.NOT_CONVERGED)
_MOVED = int(Exit.MOVED)
_DEGENERATE = int(Exit.DEGENERATE)
_LOW_CORRELATION = int(Exit.LOW_CORRELATION)
_IMPRECISE = int(Exit.IMPRECISE)
_NOT_TRIED = -1


@numba.njit(nogil=True, cache=True)
def _solve_window(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, region, rx, ry, min_count, final, template,
                  sol, stats):  # pragma: no cover - compiled
    """Solve the normal equations of every template centred in ``region``.

    ``sol`` (8, h, w) gets ``(dx, dy, b11, b12, b21, b22, gain, offset)``: the move of the
    position, the affine correction (both divided by the gain) and the radiometry in the
    normalised grey values; ``stats`` (5, h, w) gets ``sigma_x, sigma_y, cov_xy, rho, code``
    (code: 0 solved, OUTSIDE, SINGULAR). Only the move and the radiometry, and no
    statistics, unless ``final``.
    """
    h, w = t.shape
    r0, r1, c0, c1 = region
    a0 = max(c0 - rx, 0)
    a1 = min(c1 + rx, w)
    ncols = a1 - a0
    nring = 2 * ry + 1
    nplanes = _NPLANES if final and not template else _NPLANES_SOLVE
    ring = np.zeros((nring, nplanes, ncols))
    vsum = np.zeros((3, nplanes, ncols))
    pre = np.empty((nplanes, ncols + 1))
    s = np.empty(_NSUMS)
    s2 = np.empty(_NSUMS)
    rhs2 = np.empty(8)
    nmat = np.empty((8, 8))
    e = np.empty(8)
    rhs = np.empty(8)
    p = np.empty(8)
    npix = float((2 * rx + 1) * (2 * ry + 1))
    base_row = r0 - ry
    for r in range(r0 - ry, r1 + ry):
        slot = (r - base_row) % nring
        if r - base_row >= nring:  # the row leaving the window
            _add_row(vsum, ring[slot], -1.0, float(r - nring - base_row), ncols, nplanes)
        if 0 <= r < h:
            _row_planes(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, r, a0, a1, rx, nplanes, not template, pre,
                        ring[slot])
        else:
            ring[slot, :, :] = 0.0
        _add_row(vsum, ring[slot], 1.0, float(r - base_row), ncols, nplanes)
        rc = r - ry  # the row whose window is now complete
        if rc < r0:
            continue
        rrel = float(rc - base_row)
        for c in range(c0, c1):
            j = c - a0
            stats[_CODE, rc, c] = _OUTSIDE
            if rc - ry < 0 or rc + ry >= h or j - rx < 0 or j + rx >= ncols:
                continue
            if not weight[rc, c]:
                continue
            _centred_sums(vsum, rrel, j, s)
            cnt = s[S_W]
            if cnt < min_count * npix or cnt <= 8.0:
                continue
            if template:
                _assemble(s, 0.0, 0.0, nmat, rhs)
            else:
                _assemble(s, px[rc, c] - c - qx, py[rc, c] - rc - qy, nmat, rhs)
            ok, d6, d7, lxy = _ldl_solve8(nmat, rhs, p, final)
            if not ok:
                stats[_CODE, rc, c] = _SINGULAR
                continue
            alpha = p[_P6]
            if not (alpha > 0.0):
                stats[_CODE, rc, c] = _SINGULAR
                continue
            # the geometric unknowns: the template's move (template gradients) or alpha times the image's
            scale = 1.0 if template else alpha
            sol[_DX, rc, c] = p[_P0] / scale
            sol[_DY, rc, c] = p[_P1] / scale
            sol[_GAIN, rc, c] = alpha
            sol[_OFFSET, rc, c] = p[_P7]
            stats[_CODE, rc, c] = _ACCEPTED
            if not final:
                continue
            sol[_B11, rc, c] = p[_P2] / scale
            sol[_B12, rc, c] = p[_P3] / scale
            sol[_B21, rc, c] = p[_P4] / scale
            sol[_B22, rc, c] = p[_P5] / scale
            ssr = s[S_TT]
            for k in range(8):
                ssr -= p[k] * rhs[k]
            s02 = max(ssr, 0.0) / (cnt - 8.0) / (scale * scale)
            if template:
                # the template's smooth gradients are the design: the shift block of its own inverse
                stats[_SIGMA_X, rc, c] = math.sqrt(max(s02 * (1.0 / d6 + lxy * lxy / d7), 0.0))
                stats[_SIGMA_Y, rc, c] = math.sqrt(max(s02 / d7, 0.0))
                stats[_COV_XY, rc, c] = -s02 * lxy / d7
                st, stt, sti, si, sii = s[S_T], s[S_TT], s[S_TR], s[S_R], s[S_RR]
                vt = stt - st * st / cnt
                vi = sii - si * si / cnt
                stats[_RHO, rc, c] = (sti - st * si / cnt) / math.sqrt(vt * vi) if vt > 0.0 and vi > 0.0 else np.nan
                continue
            # the precision from the normal matrix of the smooth gradients, as in ALSC: the
            # slopes of the interpolant carry twice the noise and would make sigma optimistic
            _precision_sums(vsum, rrel, j, s2)
            _assemble(s2, 0.0, 0.0, nmat, rhs2)
            ok, d6, d7, lxy = _ldl_solve8(nmat, rhs2, e, False)
            if not ok:
                stats[_CODE, rc, c] = _SINGULAR
                continue
            # shift block of N^-1 = (L22 D2 L22^T)^-1 for the last 2x2 blocks of the factor
            cxx = s02 * (1.0 / d6 + lxy * lxy / d7)
            cxy = -s02 * lxy / d7
            cyy = s02 / d7
            stats[_SIGMA_X, rc, c] = math.sqrt(max(cxx, 0.0))
            stats[_SIGMA_Y, rc, c] = math.sqrt(max(cyy, 0.0))
            stats[_COV_XY, rc, c] = cxy
            st, stt, sti, si, sii = s[S_T], s[S_TT], s[S_TR], s[S_R], s[S_RR]
            vt = stt - st * st / cnt
            vi = sii - si * si / cnt
            stats[_RHO, rc, c] = (sti - st * si / cnt) / math.sqrt(vt * vi) if vt > 0.0 and vi > 0.0 else np.nan


@dataclass(frozen=True)
class FieldLsqResult:
    """Per-pixel result of :func:`field_lsq` on the window grid.

    Attributes
    ----------
    x, y : float64 (h, w)
        Final positions in the distorted window's frame (the start where never updated).
    affine : float64 (4, h, w)
        ``b11, b12, b21, b22``, the Jacobian of the position minus the identity, of the last evaluation.
    gain, offset : float64 (h, w)
        Radiometry of the last evaluation, ``base ~ gain dist + offset`` as in ALSC.
    sigma_x, sigma_y, rho : float64 (h, w)
    step : float64 (h, w)
        Length of the last ``(x, y)`` update.
    code : int8 (h, w)
        :class:`~geocoder.kernels.alsc.Exit` code, -1 where not tried.
    """

    x: np.ndarray
    y: np.ndarray
    affine: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    rho: np.ndarray
    step: np.ndarray
    code: np.ndarray


@numba.njit(nogil=True, cache=True)
def _accept(sol, stats, px, py, x0, y0, step, eligible, region, tol, max_shift, min_rho, max_sigma, min_det,
            code):  # pragma: no cover - compiled
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            if not eligible[r, c]:
                code[r, c] = _NOT_TRIED
                continue
            k = int(stats[_CODE, r, c])
            if k != _ACCEPTED:
                code[r, c] = k
                continue
            if not (step[r, c] < tol):
                code[r, c] = _NOT_CONVERGED
                continue
            dx = px[r, c] - x0[r, c]
            dy = py[r, c] - y0[r, c]
            if dx * dx + dy * dy > max_shift * max_shift:
                code[r, c] = _MOVED
                continue
            det = (1.0 + sol[_B11, r, c]) * (1.0 + sol[_B22, r, c]) - sol[_B12, r, c] * sol[_B21, r, c]  # I + Jacobian of q
            if not (det >= min_det and det * min_det <= 1.0):
                code[r, c] = _DEGENERATE
                continue
            if not (stats[_RHO, r, c] >= min_rho):
                code[r, c] = _LOW_CORRELATION
                continue
            sx = stats[_SIGMA_X, r, c]
            sy = stats[_SIGMA_Y, r, c]
            cxy = stats[_COV_XY, r, c]
            half = 0.5 * (sx * sx - sy * sy)
            largest = 0.5 * (sx * sx + sy * sy) + math.sqrt(half * half + cxy * cxy)
            if not (largest <= max_sigma * max_sigma):
                code[r, c] = _IMPRECISE
                continue
            code[r, c] = _ACCEPTED


@numba.njit(nogil=True, cache=True)
def _update(sol, stats, px, py, step, region):  # pragma: no cover - compiled
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            if stats[_CODE, r, c] == _ACCEPTED:
                tx = sol[_DX, r, c]
                ty = sol[_DY, r, c]
                px[r, c] += tx
                py[r, c] += ty
                step[r, c] = math.sqrt(tx * tx + ty * ty)
            else:
                step[r, c] = np.inf


def field_lsq(
    base: np.ndarray,
    dist: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    eligible: np.ndarray,
    region: tuple[int, int, int, int],
    *,
    radius: int = 25,
    radius_y: int = 3,
    iterations: int = 3,
    tol: float = 0.1,
    max_shift: float = 0.5,
    min_rho: float = 0.7,
    max_sigma: float = 0.1,
    min_det: float = 0.5,
    min_fill: float = 0.5,
    gradients: str = "template",
) -> FieldLsqResult:
    """Least-squares match of every eligible pixel of ``region``, starting from ``(x0, y0)``.

    Parameters
    ----------
    base : 2-D float array (h, w)
        Base window; templates are cut from it.
    dist : 2-D float array
        Distorted window.
    x0, y0 : float (h, w)
        Start positions in the distorted window's frame for every pixel of the base window
        (needed wherever a template of a pixel of ``region`` may reach after ``iterations``
        rounds, i.e. ``region`` grown by ``iterations`` template half-sizes).
    eligible : bool (h, w)
        Pixels whose start is trusted: only they take part in templates and are matched.
    region : (row0, row1, col0, col1)
        The pixels whose result is wanted (half open).
    radius, radius_y : int
        Template half-width (columns) and half-height (rows).
    iterations : int
        Resampling rounds; each moves every solved pixel of a region that shrinks by one
        template half-size per round, so the result inside ``region`` depends only on data
        within ``iterations`` half-sizes of it.
    tol : float
        Largest length (px) of the last move of an accepted pixel.
    max_shift, min_rho, max_sigma, min_det : float
        Acceptance tests as in :class:`geocoder.kernels.alsc.AlscOptions` (``max_shift``
        measured from the start, ``min_det`` on ``det(I + c / alpha)``, the affine correction).
    min_fill : float
        Smallest share of a template's pixels that must be eligible (with finite samples);
        the others are left out of its sums.
    gradients : {"template", "image"}
        The design's slopes. ``"template"``: the base template's central differences (the
        inverse-compositional form: free of the resampled image's noise, which biases the
        image's slopes on smooth texture); each round samples the image (Lanczos-3) on the
        field smoothed over the template's box and moves a pixel to that mean plus its
        template's shift, so a round reaches two half-sizes, and sigma carries the fixed
        point's noise gain (:func:`_noise_gain`). ``"image"``: the slopes of the distorted
        image's bilinear interpolant at every template pixel's own position, each template
        linearised about its centre (one half-size per round).

    Returns
    -------
    FieldLsqResult
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    if gradients not in ("image", "template"):
        raise ValueError(f"gradients must be 'image' or 'template', got {gradients!r}")
    template = gradients == "template"
    h, w = base.shape
    t = np.asarray(base, dtype=np.float64)
    # grey values of O(1) keep the window sums well conditioned (gain and offset absorb the scale)
    tm, ts = _location_scale(t)
    t = (t - tm) / ts
    d = np.asarray(dist, dtype=np.float64)
    dm, ds = _location_scale(d)
    d = (d - dm) / ds
    px = np.array(x0, dtype=np.float64)
    py = np.array(y0, dtype=np.float64)
    weight = np.asarray(eligible, dtype=np.bool_) & np.isfinite(px) & np.isfinite(py)
    cols = np.arange(w)[None, :]
    rows = np.arange(h)[:, None]
    # the image design is linearised about the field's median offset (not used by the template's)
    qx = float(np.median((px - cols)[weight])) if weight.any() and not template else 0.0
    qy = float(np.median((py - rows)[weight])) if weight.any() and not template else 0.0
    iw = np.full((h, w), np.nan)
    sol = np.full((8, h, w), np.nan)
    stats = np.full((5, h, w), np.nan)
    step = np.full((h, w), np.inf)
    r0, r1, c0, c1 = region
    if template:
        _template_rounds(t, d, px, py, weight, region, radius, radius_y, iterations, min_fill, iw, sol, stats, step)
        stats[_SIGMA_X : _SIGMA_Y + 1] *= _noise_gain(radius, radius_y)
        stats[_COV_XY] *= _noise_gain(radius, radius_y) ** 2
    else:
        cgy, cgx = np.gradient(d)  # the smooth gradients of the precision (NaN spreads to neighbours)
        gxw = np.full((h, w), np.nan)
        gyw = np.full((h, w), np.nan)
        cxw = np.full((h, w), np.nan)
        cyw = np.full((h, w), np.nan)
    for it in range(0 if template else iterations):
        grow = iterations - 1 - it
        reg, warp = round_windows(region, grow, radius, radius_y, (h, w))
        final = it == iterations - 1
        _warp(d, px, py, warp, iw, gxw, gyw)
        if final:
            _sample(cgx, px, py, warp, cxw)
            _sample(cgy, px, py, warp, cyw)
        _solve_window(t, iw, gxw, gyw, cxw, cyw, px, py, qx, qy, weight, reg, radius, radius_y, min_fill, final,
                      False, sol, stats)
        _update(sol, stats, px, py, step, reg)
    code = np.full((h, w), _NOT_TRIED, dtype=np.int8)
    x0f = np.asarray(x0, dtype=np.float64)
    y0f = np.asarray(y0, dtype=np.float64)
    _accept(sol, stats, px, py, x0f, y0f, step, weight, np.array(region, dtype=np.int64), tol, max_shift, min_rho,
            max_sigma, min_det, code)
    sl = (slice(r0, r1), slice(c0, c1))
    gain = sol[_GAIN][sl] * ts / ds  # base ~ gain dist + offset, as in ALSC
    offset = tm + ts * sol[_OFFSET][sl] - gain * dm
    return FieldLsqResult(
        px[sl], py[sl], sol[_B11 : _B22 + 1, r0:r1, c0:c1], gain, offset, stats[_SIGMA_X][sl], stats[_SIGMA_Y][sl], stats[_RHO][sl], step[sl],
        code[sl],
    )


@numba.njit(nogil=True, cache=True)
def smoothed_positions(px, py, weight, rx, ry, work, sx, sy):  # pragma: no cover - compiled
    """The field smoothed over the template's box: ``sx, sy`` get every pixel's column and row
    plus the mean displacement ``(px - col, py - row)`` of the ``weight`` pixels of its box
    ((2 ry + 1) x (2 rx + 1), clipped at the border); NaN where the box holds none.

    Running sums along the rows into ``work`` (3, h, w), then down the columns; the counts are
    exact integers. Writes only into its arguments (no per-call planes).
    """
    h, w = weight.shape
    for r in range(h):
        ax = ay = n = 0.0
        for c in range(-rx, w + rx):
            enter = c + rx
            if enter < w and weight[r, enter]:
                ax += px[r, enter] - enter
                ay += py[r, enter] - r
                n += 1.0
            leave = c - rx - 1
            if leave >= 0 and weight[r, leave]:
                ax -= px[r, leave] - leave
                ay -= py[r, leave] - r
                n -= 1.0
            if 0 <= c < w:
                work[0, r, c] = ax
                work[1, r, c] = ay
                work[2, r, c] = n
    acc = np.zeros((3, w))
    for r in range(-ry, h + ry):
        enter = r + ry
        leave = r - ry - 1
        for c in range(w):
            if enter < h:
                for k in range(3):
                    acc[k, c] += work[k, enter, c]
            if leave >= 0:
                for k in range(3):
                    acc[k, c] -= work[k, leave, c]
            if 0 <= r < h:
                n = acc[2, c]
                if n > 0.5:
                    sx[r, c] = c + acc[0, c] / n
                    sy[r, c] = r + acc[1, c] / n
                else:
                    sx[r, c] = np.nan
                    sy[r, c] = np.nan


def round_windows(region, grow: int, rx: int, ry: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The pixels a round solves (``region`` grown by ``grow`` template half-sizes) and the
    window it resamples (those plus one half-size), both clipped to ``shape``, int64[4]."""
    (r0, r1, c0, c1), (h, w) = region, shape
    reg = np.array([max(r0 - grow * ry, 0), min(r1 + grow * ry, h), max(c0 - grow * rx, 0), min(c1 + grow * rx, w)],
                   dtype=np.int64)
    warp = np.array([max(reg[0] - ry, 0), min(reg[1] + ry, h), max(reg[2] - rx, 0), min(reg[3] + rx, w)], dtype=np.int64)
    return reg, warp


def _template_rounds(t, d, px, py, weight, region, rx, ry, iterations, min_fill, iw, sol, stats, step):
    """The rounds of ``gradients="template"``: smooth the field over the template's box,
    resample the image there, and move every pixel to the smoothed field plus its template's shift.

    The smoothing is what keeps the templates independent of their neighbours' noise: the
    samples follow the box mean of the field (whose noise is that of many matches), and the
    new position of a pixel is that mean plus ITS template's own shift, so no pixel's noise
    is carried into the next round except through the mean. Round ``k`` of ``n`` solves the
    pixels within ``2 (n - 1 - k)`` half-sizes of ``region`` (the box, then the template).
    """
    h, w = t.shape
    tgy, tgx = np.gradient(t)
    work = np.empty((3, h, w))
    sx = np.empty((h, w))
    sy = np.empty((h, w))
    for it in range(iterations):
        grow = 2 * (iterations - 1 - it)
        reg, warp = round_windows(region, grow, rx, ry, (h, w))
        smoothed_positions(px, py, weight, rx, ry, work, sx, sy)
        _sample_lanczos(d, sx, sy, warp, LANCZOS_TABLE, iw)
        _solve_window(t, iw, tgx, tgy, iw, iw, sx, sy, 0.0, 0.0, weight, reg, rx, ry, min_fill, it == iterations - 1,
                      True, sol, stats)
        _move(sol, stats, sx, sy, px, py, step, reg)


@numba.njit(nogil=True, cache=True)
def _move(sol, stats, sx, sy, px, py, step, region):  # pragma: no cover - compiled
    """A solved pixel goes to the smoothed field plus its template's shift; ``step`` is how far it moved."""
    r0, r1, c0, c1 = region
    for r in range(r0, r1):
        for c in range(c0, c1):
            if stats[_CODE, r, c] == _ACCEPTED:
                nx = sx[r, c] + sol[_DX, r, c]
                ny = sy[r, c] + sol[_DY, r, c]
                ex = nx - px[r, c]
                ey = ny - py[r, c]
                px[r, c] = nx
                py[r, c] = ny
                step[r, c] = math.sqrt(ex * ex + ey * ey)
            else:
                step[r, c] = np.inf


_GAINS: dict[tuple[int, int], float] = {}


def _noise_gain(rx: int, ry: int) -> float:
    """Standard-deviation gain of the template rounds' fixed point over one template's noise.

    At the fixed point ``q = B q + B (t - B q)`` (``B`` the template's box mean) noise that
    enters as the box-smoothed noise of single matches leaves with the transfer
    ``1 / (1 - B + B^2)`` (at most 4/3); the gain is the ratio of the two spectra's powers,
    from the box's transfer function on a 512 x 512 grid.
    """
    key = (int(rx), int(ry))
    if key not in _GAINS:
        def box(n: int, size: int = 512) -> np.ndarray:
            k = np.zeros(size)
            k[:n] = 1.0 / n
            return np.real(np.fft.fft(np.roll(k, -(n // 2))))

        b = box(2 * key[1] + 1)[:, None] * box(2 * key[0] + 1)[None, :]
        p = b * b
        _GAINS[key] = float(np.sqrt((p / (1.0 - b + b * b) ** 2).sum() / p.sum()))
    return _GAINS[key]


def _location_scale(a: np.ndarray) -> tuple[float, float]:
    v = a[np.isfinite(a)]
    if v.size == 0:
        return 0.0, 1.0
    m = float(v.mean())
    s = float(v.std())
    return m, (s if s > 0 else 1.0)


def template_solution_reference(t, iw, gxw, gyw, px, py, row: int, col: int, radius: int, radius_y: int):
    """The least-squares solution of one template from its design matrix (numpy; for tests).

    Same model and inputs as the kernel (normalised grey values, warped image and slopes);
    returns ``(dx, dy, b11, b12, b21, b22, gain, offset)`` as the kernel's ``sol``.
    """
    sl = (slice(row - radius_y, row + radius_y + 1), slice(col - radius, col + radius + 1))
    v, u = np.mgrid[-radius_y : radius_y + 1, -radius : radius + 1]
    r, c = np.mgrid[sl]
    gx, gy, tt, i, x, y = (np.asarray(a, dtype=np.float64)[sl].ravel() for a in (gxw, gyw, t, iw, px, py))
    qx = x - c.ravel() - (px[row, col] - col)
    qy = y - r.ravel() - (py[row, col] - row)
    yp = i - gx * qx - gy * qy
    u, v = u.ravel().astype(float), v.ravel().astype(float)
    a = np.column_stack([gx, gy, u * gx, v * gx, u * gy, v * gy, yp, np.ones_like(tt)])
    theta = np.linalg.lstsq(a, tt, rcond=None)[0]
    alpha = theta[6]
    return np.r_[theta[:6] / alpha, alpha, theta[7]]
