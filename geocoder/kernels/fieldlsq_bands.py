"""Every pixel of a window matched on several co-registered bands at once (seed 003 sec. 11).

The multispectral form of :func:`geocoder.kernels.fieldlsq.field_lsq` with the template's
gradients (its default): each band ``b`` has its own template ``T_b``, resampled image ``I_b``
and radiometry ``alpha_b, beta_b``; the geometry (the shift and the affine correction of a
pixel) is one for all bands::

    T_b(x) ~ alpha_b I_b(x + qbar(x)) + beta_b + gx_Tb (sx + c11 u + c12 v) + gy_Tb (sy + c21 u + c22 v)

Every band's window sums and 8x8 normal equations are made exactly as for one band
(:mod:`geocoder.kernels.window_sums`); its two radiometric unknowns are eliminated (the Schur
complement of its 2x2 block), the reduced geometric systems of all bands are added and solved
with the same factor (:func:`~geocoder.kernels.window_sums._ldl_solve8`, the radiometric rows
left as an identity), and each band's radiometry is back-substituted: the least-squares
solution of the joint system. ``sigma0^2`` pools the residuals of all bands over
``sum npix_b - 6 - 2 n`` degrees of freedom; ``rho`` pools the bands' covariances of
template and image, each about its own means. The rounds, the smoothing of the field, the
noise gain and the acceptance are those of ``field_lsq``.

The bands must come with unit noise in grey values (each scaled by its noise over the whole
image, the same for every tile: :func:`geocoder.kernels.alsc_bands.band_scales`); nothing here
rescales them per window, which would weigh the bands differently in different tiles. A
pixel is solved when the gain weighted by each band's template contrast is positive (a band
without texture has no defined gain).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .fieldlsq import (
    _ACCEPTED,
    _B11,
    _B12,
    _B21,
    _B22,
    _CODE,
    _COV_XY,
    _DX,
    _DY,
    _GAIN,
    _NOT_TRIED,
    _OFFSET,
    _OUTSIDE,
    _RHO,
    _SIGMA_X,
    _SIGMA_Y,
    _SINGULAR,
    FieldLsqResult,
    _accept,
    _move,
    _noise_gain,
    round_windows,
    smoothed_positions,
)
from .resample import LANCZOS_TABLE
from .window_sums import (
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
    _row_planes,
    _sample_lanczos,
)

__all__ = ["field_lsq_bands"]

# the radiometric rows of the normal equations (alpha, beta), and the geometric ones
_RA, _RB = _P6, _P7
_GEO = (_P0, _P1, _P2, _P3, _P4, _P5)


@numba.njit(nogil=True, cache=True)
def _solve_window_bands(t, iw, tgx, tgy, px, py, weight, region, rx, ry, min_count, final, sol, stats):
    # pragma: no cover - compiled
    """:func:`geocoder.kernels.fieldlsq._solve_window` with the template's gradients, on ``n`` bands
    (``t, iw, tgx, tgy`` of shape (n, h, w)); ``sol[_GAIN]`` gets the first band's gain."""
    nb, h, w = t.shape
    r0, r1, c0, c1 = region
    a0 = max(c0 - rx, 0)
    a1 = min(c1 + rx, w)
    ncols = a1 - a0
    nring = 2 * ry + 1
    nplanes = _NPLANES_SOLVE
    ring = np.zeros((nb, nring, nplanes, ncols))
    vsum = np.zeros((nb, 3, nplanes, ncols))
    pre = np.empty((nplanes, ncols + 1))
    s = np.empty((nb, _NSUMS))
    nmat = np.empty((nb, 8, 8))
    rhs = np.empty((nb, 8))
    red = np.empty((8, 8))
    rrhs = np.empty(8)
    p = np.empty(8)
    rad = np.empty((nb, 2))
    npix = float((2 * rx + 1) * (2 * ry + 1))
    base_row = r0 - ry
    for r in range(r0 - ry, r1 + ry):
        slot = (r - base_row) % nring
        for b in range(nb):
            if r - base_row >= nring:  # the row leaving the window
                _add_row(vsum[b], ring[b, slot], -1.0, float(r - nring - base_row), ncols, nplanes)
            if 0 <= r < h:
                _row_planes(t[b], iw[b], tgx[b], tgy[b], iw[b], iw[b], px, py, 0.0, 0.0, weight, r, a0, a1, rx, nplanes,
                            False, pre, ring[b, slot])
            else:
                ring[b, slot, :, :] = 0.0
            _add_row(vsum[b], ring[b, slot], 1.0, float(r - base_row), ncols, nplanes)
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
            cnt = 0.0
            short = False
            for b in range(nb):
                _centred_sums(vsum[b], rrel, j, s[b])
                cnt += s[b, S_W]
                if s[b, S_W] < min_count * npix or s[b, S_W] <= 8.0:
                    short = True
            if short:
                continue
            # every band's normal equations, its radiometry eliminated, the rest added up
            for i in range(8):
                rrhs[i] = 0.0
                for k in range(8):
                    red[i, k] = 0.0
            singular = False
            for b in range(nb):
                _assemble(s[b], 0.0, 0.0, nmat[b], rhs[b])
                n = nmat[b]
                r00, r01, r11 = n[_RA, _RA], n[_RA, _RB], n[_RB, _RB]
                det = r00 * r11 - r01 * r01
                if not (det > 0.0 and r00 > 0.0):
                    singular = True
                    break
                i00, i01, i11 = r11 / det, -r01 / det, r00 / det
                ra = i00 * rhs[b, _RA] + i01 * rhs[b, _RB]
                rb = i01 * rhs[b, _RA] + i11 * rhs[b, _RB]
                for gi in _GEO:
                    ca = n[gi, _RA] * i00 + n[gi, _RB] * i01
                    cb = n[gi, _RA] * i01 + n[gi, _RB] * i11
                    rrhs[gi] += rhs[b, gi] - n[gi, _RA] * ra - n[gi, _RB] * rb
                    for gk in _GEO:
                        red[gi, gk] += n[gi, gk] - ca * n[gk, _RA] - cb * n[gk, _RB]
            if singular:
                stats[_CODE, rc, c] = _SINGULAR
                continue
            red[_RA, _RA] = 1.0
            red[_RB, _RB] = 1.0
            ok, d6, d7, lxy = _ldl_solve8(red, rrhs, p, True)
            if not ok:
                stats[_CODE, rc, c] = _SINGULAR
                continue
            # each band's radiometry from the shared geometry; the contrast-weighted gain must be
            # positive (a band without texture has no defined gain)
            gain = 0.0
            for b in range(nb):
                n = nmat[b]
                r00, r01, r11 = n[_RA, _RA], n[_RA, _RB], n[_RB, _RB]
                det = r00 * r11 - r01 * r01
                ea = rhs[b, _RA]
                eb = rhs[b, _RB]
                for gi in _GEO:
                    ea -= n[_RA, gi] * p[gi]
                    eb -= n[_RB, gi] * p[gi]
                rad[b, 0] = (r11 * ea - r01 * eb) / det
                rad[b, 1] = (r00 * eb - r01 * ea) / det
                gain += (s[b, S_TT] - s[b, S_T] * s[b, S_T] / s[b, S_W]) * rad[b, 0]
            if not (gain > 0.0):
                stats[_CODE, rc, c] = _SINGULAR
                continue
            sol[_DX, rc, c] = p[_P0]
            sol[_DY, rc, c] = p[_P1]
            sol[_GAIN, rc, c] = rad[0, 0]
            sol[_OFFSET, rc, c] = rad[0, 1]
            stats[_CODE, rc, c] = _ACCEPTED
            if not final:
                continue
            sol[_B11, rc, c] = p[_P2]
            sol[_B12, rc, c] = p[_P3]
            sol[_B21, rc, c] = p[_P4]
            sol[_B22, rc, c] = p[_P5]
            ssr = 0.0
            num = 0.0
            vt = 0.0
            vi = 0.0
            for b in range(nb):
                ssr += s[b, S_TT] - rad[b, 0] * rhs[b, _RA] - rad[b, 1] * rhs[b, _RB]
                for gi in _GEO:
                    ssr -= p[gi] * rhs[b, gi]
                cb = s[b, S_W]
                st, stt, sti, si, sii = s[b, S_T], s[b, S_TT], s[b, S_TR], s[b, S_R], s[b, S_RR]
                num += sti - st * si / cb
                vt += stt - st * st / cb
                vi += sii - si * si / cb
            s02 = max(ssr, 0.0) / (cnt - 6.0 - 2.0 * nb)
            stats[_SIGMA_X, rc, c] = math.sqrt(max(s02 * (1.0 / d6 + lxy * lxy / d7), 0.0))
            stats[_SIGMA_Y, rc, c] = math.sqrt(max(s02 / d7, 0.0))
            stats[_COV_XY, rc, c] = -s02 * lxy / d7
            stats[_RHO, rc, c] = num / math.sqrt(vt * vi) if vt > 0.0 and vi > 0.0 else np.nan


def field_lsq_bands(
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
) -> FieldLsqResult:
    """Least-squares match of every eligible pixel of ``region`` on all bands at once.

    Parameters
    ----------
    base, dist : 3-D float arrays (n, h, w) and (n, h', w')
        The bands of the base and distorted windows, in comparable grey values (see the
        module's docstring).
    x0, y0, eligible, region, radius, radius_y, iterations, tol, max_shift, min_rho, max_sigma, min_det, min_fill
        As for :func:`geocoder.kernels.fieldlsq.field_lsq` (``gradients="template"``).

    Returns
    -------
    FieldLsqResult
        Gain and offset of the first band.
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    t = np.ascontiguousarray(base, dtype=np.float64)
    d = np.ascontiguousarray(dist, dtype=np.float64)
    if t.ndim != 3 or d.ndim != 3 or t.shape[0] != d.shape[0]:
        raise ValueError(f"base and dist must be (bands, rows, cols) with the same bands, got {t.shape} and {d.shape}")
    nb, h, w = t.shape
    rx, ry = radius, radius_y
    px = np.array(x0, dtype=np.float64)
    py = np.array(y0, dtype=np.float64)
    weight = np.asarray(eligible, dtype=np.bool_) & np.isfinite(px) & np.isfinite(py)
    tg = [np.gradient(band) for band in t]
    tgy = np.ascontiguousarray(np.stack([g[0] for g in tg]))
    tgx = np.ascontiguousarray(np.stack([g[1] for g in tg]))
    iw = np.full((nb, h, w), np.nan)
    sol = np.full((8, h, w), np.nan)
    stats = np.full((5, h, w), np.nan)
    step = np.full((h, w), np.inf)
    r0, r1, c0, c1 = region
    work = np.empty((3, h, w))
    sx = np.empty((h, w))
    sy = np.empty((h, w))
    for it in range(iterations):
        grow = 2 * (iterations - 1 - it)
        reg, warp = round_windows(region, grow, rx, ry, (h, w))
        smoothed_positions(px, py, weight, rx, ry, work, sx, sy)
        for b in range(nb):
            _sample_lanczos(d[b], sx, sy, warp, LANCZOS_TABLE, iw[b])
        _solve_window_bands(t, iw, tgx, tgy, sx, sy, weight, reg, rx, ry, min_fill, it == iterations - 1, sol, stats)
        _move(sol, stats, sx, sy, px, py, step, reg)
    stats[_SIGMA_X : _SIGMA_Y + 1] *= _noise_gain(rx, ry)
    stats[_COV_XY] *= _noise_gain(rx, ry) ** 2
    code = np.full((h, w), _NOT_TRIED, dtype=np.int8)
    x0f = np.asarray(x0, dtype=np.float64)
    y0f = np.asarray(y0, dtype=np.float64)
    _accept(sol, stats, px, py, x0f, y0f, step, weight, np.array(region, dtype=np.int64), tol, max_shift, min_rho,
            max_sigma, min_det, code)
    sl = (slice(r0, r1), slice(c0, c1))
    # base ~ gain dist + offset of the first band (in the grey values given), as in ALSC
    gain = sol[_GAIN][sl]
    offset = sol[_OFFSET][sl]
    return FieldLsqResult(
        px[sl], py[sl], sol[_B11 : _B22 + 1, r0:r1, c0:c1], gain, offset, stats[_SIGMA_X][sl], stats[_SIGMA_Y][sl], stats[_RHO][sl], step[sl],
        code[sl],
    )
