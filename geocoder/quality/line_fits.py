"""Fits along the scan lines (issue 14): the smooth part the global polynomial leaves, and each line's own fit.

* :func:`term_sums` and :func:`smooth_fit`: what the global polynomial leaves is not one
  shift per line only; it also errs smoothly along the lines (most at the scene's edges).
  A polynomial ``P`` of the line coordinate (:data:`TERMS`) is fitted to every line's
  residuals about that line's mean, by least squares over all lines, and taken off the
  lines' sums before :func:`geocoder.quality.lines.line_corrections`.
* :func:`fit_sums` and :func:`line_fits`: a low-order polynomial of the line coordinate per
  line, fitted to its matches with a prior from all lines, and :func:`shrink_block`, which
  shrinks every match toward its line's fit by how far the lines stray from their fits
  beyond the matches' noise.

Row sums are computed per tile and added over a row band, as in :mod:`geocoder.quality.lines`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .shrinkage import random_effects, shrink

#: Quantities :func:`fit_sums` returns per row, all added over the blocks of a row band: the
#: moments ``sum(u^k)`` of the line coordinate of the matches, ``sum(r u^k)`` of their residuals
#: in x and y, the residuals' squares and the matches' variances.
FIT_SUMS = ("u0", "u1", "u2", "u3", "u4", "xu0", "xu1", "xu2", "yu0", "yu1", "yu2", "xx", "yy", "vx", "vy")


def line_coordinate(cols: np.ndarray, width: int) -> np.ndarray:
    """Column -> ``u`` in [-1, 1] across the scene's width (the fits' coordinate along a line)."""
    half = max(0.5 * (width - 1), 1.0)
    return (np.asarray(cols, np.float64) - 0.5 * (width - 1)) / half


#: ``z`` of the test a coefficient's spread across the lines must pass (:func:`shrink_coefficients`).
SPREAD_SIGNIFICANCE = 2.0

#: Terms of the smooth part along the lines, as powers ``(a, b)`` of ``u`` (the column,
#: :func:`line_coordinate`) and ``v`` (the row, likewise across the height): how the global
#: model errs along the lines. No term in ``v`` alone: each line's own shift holds that.
TERMS = ((1, 0), (2, 0), (1, 1))
_PAIRS = tuple((i, j) for i in range(len(TERMS)) for j in range(i, len(TERMS)))
#: Rows of :func:`term_sums`: per term its sum, the sums of the products of two terms (upper
#: triangle), the sums of term times residual in x, then in y.
NTERM_SUMS = 3 * len(TERMS) + len(_PAIRS)
_UMAX = max(a for a, _ in TERMS)


def terms(cols: np.ndarray, rows: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The :data:`TERMS` at (broadcast) ``cols`` and ``rows`` of a scene of ``shape``, (len(TERMS), ...)."""
    u = line_coordinate(cols, shape[1])
    v = line_coordinate(rows, shape[0])
    return np.stack([u**a * v**b for a, b in TERMS])


def term_sums(rx: np.ndarray, ry: np.ndarray, usable: np.ndarray, *, row0: int, col0: int,
              shape: tuple[int, int]) -> np.ndarray:
    """Per row of a block: the moments of the :data:`TERMS` over its usable pixels (:data:`NTERM_SUMS`).

    Parameters
    ----------
    rx, ry : ndarray (h, w)
        Residuals ``d - polynomial``.
    usable : ndarray of bool (h, w)
        The pixels :func:`line_sums` counts.
    row0, col0 : int
        The block's first pixel in the scene.
    shape : (int, int)
        The scene's rows and columns.

    Returns
    -------
    ndarray (NTERM_SUMS, h), float64
    """
    h, w = usable.shape
    # a term is u^a v^b with v constant along a row: every row sum is a sum of powers of u,
    # one matrix product per quantity instead of a plane per term and product
    upow = line_coordinate(np.arange(col0, col0 + w), shape[1])[:, None] ** np.arange(2 * _UMAX + 1)
    v = line_coordinate(np.arange(row0, row0 + h), shape[0])
    ok = np.asarray(usable, np.float64)
    s_u = ok @ upow
    s_x = np.where(usable, np.asarray(rx, np.float64), 0.0) @ upow[:, : _UMAX + 1]
    s_y = np.where(usable, np.asarray(ry, np.float64), 0.0) @ upow[:, : _UMAX + 1]
    rows = [s_u[:, a] * v**b for a, b in TERMS]
    rows += [s_u[:, TERMS[i][0] + TERMS[j][0]] * v ** (TERMS[i][1] + TERMS[j][1]) for i, j in _PAIRS]
    rows += [s[:, a] * v**b for s in (s_x, s_y) for a, b in TERMS]
    return np.stack(rows)


def term_values(phi: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per pixel, the quantities whose sums :func:`term_sums` gives, in its order.

    Parameters
    ----------
    phi : ndarray (len(TERMS), ...)
        The :data:`TERMS` at the pixels (:func:`terms`).
    x, y : ndarray (...)
        Their residuals.

    Returns
    -------
    ndarray (NTERM_SUMS, ...)
        The terms, the products of two terms (upper triangle), term times ``x``, term times ``y``.
    """
    return np.concatenate([phi, np.stack([phi[i] * phi[j] for i, j in _PAIRS]), phi * x, phi * y])


def smooth_fit(sums: np.ndarray, moments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smooth part along the lines, and the lines' sums with it taken off.

    The residuals of the usable pixels are modelled as ``P(u, v) + t(line)``: ``P`` a
    combination of the :data:`TERMS`, ``t`` each line's own shift. ``P`` is fitted to every
    line's residuals about that line's mean (so the lines' shifts do not enter it), by least
    squares over all lines.

    Parameters
    ----------
    sums : ndarray (10, H)
        :data:`SUMS` of whole lines.
    moments : ndarray (NTERM_SUMS, H)
        :func:`term_sums` of whole lines.

    Returns
    -------
    coef : ndarray (2, len(TERMS))
        ``P``'s coefficients in x and y (zero where the terms are not determined).
    adjusted : ndarray (10, H)
        ``sums`` of the residuals minus ``P``: their means are the lines' shifts, their
        spreads how far each line is from ``P`` plus one shift.
    """
    nt = len(TERMS)
    n = sums[0]
    s_phi = moments[:nt]
    s_pp = moments[nt : nt + len(_PAIRS)]
    s_pr = moments[nt + len(_PAIRS) :].reshape(2, nt, -1)
    safe = np.maximum(n, 1.0)
    gram = np.zeros((nt, nt))
    for m, (i, j) in enumerate(_PAIRS):
        gram[i, j] = gram[j, i] = np.sum(s_pp[m] - s_phi[i] * s_phi[j] / safe)
    coef = np.zeros((2, nt))
    diag = np.diag(gram)
    if np.all(diag > 0):
        scale = np.sqrt(diag)
        if np.linalg.cond(gram / np.outer(scale, scale)) < 1e8:
            for a, r in enumerate((sums[1], sums[2])):
                coef[a] = np.linalg.solve(gram, np.sum(s_pr[a] - s_phi * (r / safe), axis=1))
    adjusted = np.array(sums, dtype=np.float64, copy=True)
    for a in (0, 1):
        c = coef[a]
        quad = np.zeros(n.shape)
        for m, (i, j) in enumerate(_PAIRS):
            quad += (1.0 if i == j else 2.0) * c[i] * c[j] * s_pp[m]
        adjusted[1 + a] = sums[1 + a] - c @ s_phi
        adjusted[3 + a] = np.maximum(sums[3 + a] - 2.0 * (c @ s_pr[a]) + quad, 0.0)
    return coef, adjusted


def smooth_values(coef: np.ndarray, cols: np.ndarray, rows: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``P`` (:func:`smooth_fit`) in x and y at (broadcast) ``cols`` and ``rows``, shape (2, ...)."""
    return np.tensordot(coef, terms(cols, rows, shape), axes=1)


def fit_sums(rx: np.ndarray, ry: np.ndarray, sx: np.ndarray, sy: np.ndarray, matched: np.ndarray, *,
             col0: int = 0, width: int) -> np.ndarray:
    """Per row of a block: :data:`FIT_SUMS` of its matches (those with a sigma).

    Parameters
    ----------
    rx, ry : ndarray (H, W)
        Residuals ``d - polynomial``.
    sx, sy : ndarray (H, W)
        The matches' sigmas.
    matched : ndarray of bool (H, W)
    col0 : int
        Column of the block's first pixel in the scene.
    width : int
        The scene's width (px).

    Returns
    -------
    ndarray (15, H), float64
    """
    ok = matched & np.isfinite(sx) & np.isfinite(sy) & np.isfinite(rx) & np.isfinite(ry)
    upow = line_coordinate(np.arange(ok.shape[-1]) + col0, width)[:, None] ** np.arange(5)
    x = np.where(ok, np.asarray(rx, np.float64), 0.0)
    y = np.where(ok, np.asarray(ry, np.float64), 0.0)
    vx = np.where(ok, np.asarray(sx, np.float64) ** 2, 0.0)
    vy = np.where(ok, np.asarray(sy, np.float64) ** 2, 0.0)
    return np.concatenate([(ok.astype(np.float64) @ upow).T, (x @ upow[:, :3]).T, (y @ upow[:, :3]).T,
                           np.stack([(x * x).sum(axis=-1), (y * y).sum(axis=-1), vx.sum(axis=-1), vy.sum(axis=-1)])])


@dataclass(frozen=True)
class LineFit:
    """Per row, a polynomial of the line coordinate ``u`` (:func:`line_coordinate`) fitted to
    the residuals of the line's matches (:func:`line_fits`).

    Attributes
    ----------
    cx, cy : ndarray (H, 3)
        Coefficients of ``1, u, u^2`` (zero beyond the order) in x and y: the line's shift, slope
        and curvature, each shrunk toward the lines' trend (:func:`shrink_coefficients`).
    tau2_x, tau2_y : ndarray (H,)
        Variance of the residuals about the fit beyond the matches' own noise (px^2): how far
        the line departs from the fit (each row's estimate shrunk toward the rows' trend,
        :func:`row_departures`).
    spread_x, spread_y : ndarray (H,)
        Variance of the residuals about the fit (px^2), over the row's independent matches
        (one per ``correlation`` px, of which the fit takes one per coefficient).
    lev : ndarray (2, H, 5)
        Coefficients of ``1, u, ..., u^4`` of the variance of the fit at ``u`` (px^2), in x and
        y (at most the spread: a fit is never less certain than one match).
    ok : ndarray of bool (H,)
        Rows with a fit (enough matches).
    """

    cx: np.ndarray
    cy: np.ndarray
    tau2_x: np.ndarray
    tau2_y: np.ndarray
    spread_x: np.ndarray
    spread_y: np.ndarray
    lev: np.ndarray
    ok: np.ndarray


#: Columns of :func:`fit_table`: per row, whether it has a fit, then per axis the fit's
#: coefficients, ``tau2``, the spread and the quartic of the fit's variance.
FIT_TABLE = ("ok", "cx0", "cx1", "cx2", "cy0", "cy1", "cy2", "tau2_x", "tau2_y", "spread_x", "spread_y",
             *(f"vx{k}" for k in range(5)), *(f"vy{k}" for k in range(5)))


def fit_table(fits: LineFit) -> np.ndarray:
    """The :class:`LineFit` as one (H, 21) float64 table (columns :data:`FIT_TABLE`)."""
    return np.column_stack([fits.ok.astype(np.float64), fits.cx, fits.cy, fits.tau2_x, fits.tau2_y, fits.spread_x,
                            fits.spread_y, fits.lev[0], fits.lev[1]])


def shrink_block(dx: np.ndarray, dy: np.ndarray, px: np.ndarray, py: np.ndarray, matched: np.ndarray,
                 sx: np.ndarray, sy: np.ndarray, u: np.ndarray, table: np.ndarray,
                 filled: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The matches of a block shrunk toward their lines' fits (see
    :func:`geocoder.pipeline.lines.line_field`), the filled pixels on them.

    A filled pixel (a short gap of its line, :mod:`geocoder.quality.postfilter`) was
    interpolated from the raw matches beside a rejected one, which err most there (0.10-0.15
    px RMSE on issue 14's cases against 0.02-0.05 for the matches): it takes its line's fit,
    with the fit's variance plus the line's departure from it as its sigma (0.02-0.04 px).

    Parameters
    ----------
    dx, dy, px, py : ndarray (h, w)
        The field and the polynomial's displacement.
    matched : ndarray of bool (h, w)
    sx, sy : ndarray (h, w)
        The matches' sigmas.
    u : ndarray (w,)
        The line coordinate of the block's columns (:func:`line_coordinate`).
    table : ndarray (h, 21)
        :func:`fit_table` of the block's rows.
    filled : ndarray of bool (h, w), optional
        The filled pixels.

    Returns
    -------
    dx, dy, sx, sy : ndarray of float32 (h, w)
    """
    h, w = np.shape(matched)
    on_fit = np.zeros((h, w), bool) if filled is None else np.asarray(filled, bool)
    out = np.empty((4, h, w), np.float32)
    _shrink_rows(np.asarray(dx), np.asarray(dy), np.asarray(px), np.asarray(py), np.asarray(matched, bool),
                 np.asarray(sx), np.asarray(sy), np.asarray(u, np.float64), np.asarray(table, np.float64), on_fit, out)
    return out[0], out[1], out[2], out[3]


@numba.njit(nogil=True, cache=True, inline="always")
def _minimum(a, b):  # pragma: no cover - compiled
    """``numpy.minimum`` of two floats: NaN if either is."""
    return a + b if a != a or b != b else min(a, b)


@numba.njit(nogil=True, cache=True, inline="always")
def _maximum(a, b):  # pragma: no cover - compiled
    """``numpy.maximum`` of two floats: NaN if either is."""
    return a + b if a != a or b != b else max(a, b)


@numba.njit(nogil=True, cache=True, inline="always")
def _fit_at(t, r, a, uu):  # pragma: no cover - compiled
    """Row ``r`` of a :data:`FIT_TABLE` table, axis ``a`` (0 x, 1 y), at line coordinate ``uu``:
    the fit's value, the line's departure ``tau2`` and the fit's variance (at most the spread)."""
    fit = t[r, 1 + 3 * a] + t[r, 2 + 3 * a] * uu + t[r, 3 + 3 * a] * uu * uu
    v = 0.0
    for k in range(4, -1, -1):  # the quartic by Horner's rule
        v = v * uu + t[r, 11 + 5 * a + k]
    return fit, t[r, 7 + a], _minimum(v, t[r, 9 + a])


@numba.njit(nogil=True, cache=True)
def _shrink_rows(dx, dy, px, py, matched, sx, sy, u, t, filled, out):  # pragma: no cover - compiled
    """:func:`shrink_block` pixel by pixel into ``out`` (dx, dy, sx, sy)."""
    h, w = matched.shape
    for r in range(h):
        fitted = t[r, 0] > 0
        for a in range(2):
            d_, p_, s_ = (dx, px, sx) if a == 0 else (dy, py, sy)
            for c in range(w):
                d = float(d_[r, c])
                p = float(p_[r, c])
                s = float(s_[r, c])
                fit, tau2, v_fit = _fit_at(t, r, a, u[c])
                if filled[r, c] and fitted:
                    value = p + fit
                    sigma = math.sqrt(v_fit + tau2)
                elif matched[r, c] and fitted and math.isfinite(s) and math.isfinite(d):
                    s2 = s * s
                    keep = tau2 / _maximum(tau2 + s2, 1e-300)
                    value = p + fit + keep * (d - p - fit)
                    # value - truth = keep (the match's error) + (1 - keep) (the fit's error - the line's
                    # departure from its fit). A line departs from its fit beyond the matches' noise by
                    # relief or by the matches' own model error (a 7-row template across a jump of the
                    # turbulence, whose sigma does not know it): the kept share of a match counts the
                    # departure too, and sigma is at most the match's with it
                    sigma = math.sqrt(_minimum(keep * keep * (s2 + tau2) + (1.0 - keep) ** 2 * (v_fit + tau2), s2 + tau2))
                else:
                    value = d
                    sigma = s
                out[a, r, c] = value
                out[2 + a, r, c] = sigma


def departure_table(fits: LineFit | None, shift: np.ndarray, own: np.ndarray, shift_var: np.ndarray, *,
                    rows: int = 16) -> np.ndarray:
    """Per row, what :func:`departures` tests a match against, as a (H, 21) table laid out as
    :data:`FIT_TABLE` (its ``ok`` column the reference's kind: 0 none, 1 the line's fit, 2 the
    smooth part plus the row's shift).

    The reference is the line's fit where it has one, else, where the row has its own shift
    (``own``), the smooth part along the lines plus that shift (``shift``, (H, 2)). The
    departure a line may have from it (the ``tau2`` columns) is the median, over the rows
    within ``rows`` of it that have one, of the lines' ``tau2`` (``shift_var``, (H, 2), for the
    rows without a fit): a median over many lines, so that the matches under test cannot
    widen their own tolerance (four matches off by 1.1 px among a row's 89 widen its spread to
    about 0.23 px, computed from its sums, against 0.06 px on the fitted rows beside it).
    """
    h = own.shape[0]
    table = np.zeros((h, len(FIT_TABLE)))
    dep = np.full((h, 2), np.nan)
    if fits is not None:
        fitted = fits.ok
        table[fitted] = fit_table(fits)[fitted]
        dep[fitted] = np.column_stack([fits.tau2_x, fits.tau2_y])[fitted]
    else:
        fitted = np.zeros(h, bool)
    corrected = own & ~fitted & np.isfinite(shift).all(axis=1)
    table[corrected, 0] = 2.0
    table[corrected, 1], table[corrected, 4] = shift[corrected, 0], shift[corrected, 1]
    dep[corrected] = np.asarray(shift_var)[corrected]
    padded = np.pad(dep, ((rows, rows), (0, 0)), constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * rows + 1, axis=0)
    tested = table[:, 0] > 0
    if tested.any():
        table[tested, 7:9] = np.nanmedian(windows[tested], axis=-1)
    return table


def departures(dx: np.ndarray, dy: np.ndarray, px: np.ndarray, py: np.ndarray, part: np.ndarray,
               matched: np.ndarray, sx: np.ndarray, sy: np.ndarray, u: np.ndarray, table: np.ndarray, *,
               k: float, floor: float) -> np.ndarray:
    """The matches of a block that depart from their line more than their noise allows.

    Along one scan line the displacement is smooth (turbulence moves the whole line), so a
    match whose residual about its line's reference (:func:`departure_table`) exceeds ``k``
    times ``sqrt(sigma^2 + tau2 + var(reference))`` in x or in y, and ``floor`` px,
    contradicts the rest of its line: a template locked onto the wrong detail (issue 14's
    Landsat crop has a run of four matches off by 1.1 px with sigma 0.08, one line off on a
    weak horizontal structure) that the acceptance tests and the post-filter cannot see, since
    each looks like a precise match and agrees with the others of its run.

    Parameters
    ----------
    dx, dy, px, py, matched, sx, sy, u
        As :func:`shrink_block`.
    part : ndarray (2, h, w)
        The smooth part along the lines at the block's pixels (:func:`smooth_values`).
    table : ndarray (h, 21)
        :func:`departure_table` of the block's rows.
    k : float
        Multiple of the residual's standard deviation.
    floor : float
        Smallest departure (px) flagged.

    Returns
    -------
    ndarray of bool (h, w)
    """
    out = np.zeros(np.shape(matched), bool)
    _departures(np.asarray(dx), np.asarray(dy), np.asarray(px), np.asarray(py), np.asarray(part, np.float64),
                np.asarray(matched, bool), np.asarray(sx), np.asarray(sy), np.asarray(u, np.float64),
                np.asarray(table, np.float64), float(k), float(floor), out)
    return out


@numba.njit(nogil=True, cache=True)
def _departures(dx, dy, px, py, part, matched, sx, sy, u, t, k, floor, out):  # pragma: no cover - compiled
    h, w = matched.shape
    for r in range(h):
        kind = t[r, 0]
        if not kind > 0:
            continue
        for a in range(2):
            d_, p_, s_ = (dx, px, sx) if a == 0 else (dy, py, sy)
            for c in range(w):
                if not matched[r, c]:
                    continue
                s = float(s_[r, c])
                ref, tau2, v_ref = _fit_at(t, r, a, u[c])
                if kind > 1.5:  # the row's shift (no fit, no variance) on the smooth part along the lines
                    ref += part[a, r, c]
                    v_ref = 0.0
                res = abs(float(d_[r, c]) - float(p_[r, c]) - ref)
                if res > floor and res * res > k * k * (s * s + tau2 + v_ref):
                    out[r, c] = True


def _trend_design(v: np.ndarray) -> np.ndarray:
    """Regressors of a quadratic trend across the lines at line positions ``v``."""
    return np.stack([np.ones_like(v), v, v * v], axis=1)


def row_departures(excess: np.ndarray, sampling: np.ndarray, v: np.ndarray) -> np.ndarray:
    """How far each line departs from its fit beyond the matches' noise (px^2, at least 0).

    ``excess`` is a row's moment estimate, the residuals' variance about the fit less the
    matches' own; alone it scatters by its sampling variance ``sampling`` about the truth,
    and floored at 0 it is positive by chance on a quarter to half of the rows of a field
    that does not depart at all (issue 14: the matches there kept 4-10 % of their noise and
    their sigma was 1.4-1.7x their error). The rows' estimates are shrunk toward a quadratic trend
    across the lines by how much they scatter beyond their sampling variance (empirical
    Bayes, :func:`geocoder.quality.shrinkage.shrink`), then floored at 0: rows that do depart
    (relief, a local distortion) keep their own, the others take what the scene shows in all.

    Parameters
    ----------
    excess, sampling : ndarray (L,)
        Per line, the moment estimate and its sampling variance.
    v : ndarray (L,)
        The lines' position across the scene (:func:`line_coordinate`).
    """
    x = _trend_design(np.asarray(v, np.float64))
    if len(excess) < 4 * x.shape[1]:  # too few lines to tell a trend from their spread
        return np.maximum(excess, 0.0)
    return np.maximum(shrink(excess, sampling, x)[0], 0.0)


def shrink_coefficients(coef: np.ndarray, cov: np.ndarray, v: np.ndarray, *,
                        line_correlation: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The lines' coefficients (shift, slope, curvature) shrunk toward a smooth trend across the
    lines by how much the lines differ from it beyond the fits' own noise (empirical Bayes, as
    :func:`geocoder.quality.lines.line_corrections` does for the rows' shifts).

    Each coefficient ``k`` is taken to scatter with a variance ``tau2_k`` about a quadratic
    ``m_k(v)`` in the line's position ``v`` across the scene, ``m_k`` fitted by weighted least
    squares and ``tau2_k`` DerSimonian and Laird's moment estimate about it (at least 0;
    :func:`geocoder.quality.shrinkage.random_effects`), taken only where the lines' squares
    about the trend pass a test at :data:`SPREAD_SIGNIFICANCE` standard deviations (the
    lines' correlation counted): without it a spread of pure noise was taken on about half of
    the coefficients of a smooth field, and each line then kept a share of its noise that its
    variance counted as signal (issue 14: the smooth demo's sigma x 1.56 -> 1.30 times its
    error). With ``T = diag(tau2)``, a line's
    covariance ``P`` and ``K = T (T + P)^-1`` the posterior is ``m + K (c - m)`` with covariance
    ``K P + (I - K) M (I - K)^T`` (``M``: the trend's own variance at the line). Coefficients
    that do not vary from line to line beyond their noise come back on the trend, known to the
    precision of all lines together instead of one line's (issue 14: on the simulator's cases
    the matches' RMSE falls by a quarter to a third).

    Roll and pitch move every scan line on its own: on a scanner's field the shifts scatter far
    beyond their noise (``tau2_0`` of 0.1-10 px² against 1e-4 px²), so ``K`` keeps each line's own
    shift to a ten-thousandth of its departure from the trend. Where the global polynomial
    already explains the field (no turbulence), they do not, and the shifts too come back on
    the trend: on issue 14's smooth cases the matches' RMSE 0.018 -> 0.012 and 0.024 -> 0.015 px.

    Parameters
    ----------
    coef : ndarray (L, p)
        The lines' least-squares coefficients (shift first).
    cov : ndarray (L, p, p)
        Their covariances.
    v : ndarray (L,)
        The lines' position across the scene (:func:`line_coordinate` of the row).
    line_correlation : float
        How many neighbouring lines share one line's errors: the trend's variance, computed as
        if the lines were independent, is multiplied by it. Consecutive lines matched with a
        template ``2 ry + 1`` rows high share ``2 ry + 1 - d`` of their rows at distance ``d``,
        so their errors correlate by ``1 - d / (2 ry + 1)`` and a trend over many lines knows
        ``2 ry + 1`` times less than the independent count says (measured on issue 14's smooth
        S2 case, 1,017 lines: the shifts' residuals about the trend correlate by 0.90, 0.75,
        0.58, 0.38, 0.22, 0.09, 0.0 at distances 1-7; ``1 - d / 7`` is 0.86, 0.71, 0.57, 0.43,
        0.29, 0.14, 0).

    Returns
    -------
    coef, cov : ndarray (L, p), (L, p, p)
    """
    n, p = coef.shape
    x = _trend_design(np.asarray(v, np.float64))
    if n < 4 * x.shape[1]:  # too few lines to tell a trend from their spread
        return coef, cov
    diag = np.maximum(np.diagonal(cov, axis1=1, axis2=2), 1e-300)
    t = np.zeros((n, p, p))
    trend, trend_var = coef.copy(), np.zeros((n, p))
    for k in range(p):
        trend[:, k], trend_var[:, k], t[:, k, k] = random_effects(coef[:, k], diag[:, k], x, significance=SPREAD_SIGNIFICANCE,
                                                                  correlation=line_correlation)
    trend_var *= line_correlation
    gain = t @ np.linalg.inv(t + cov)
    rest = np.eye(p) - gain
    shrunk = trend + np.einsum("lij,lj->li", gain, coef - trend)
    # K P = T - K T without its cancellation
    return shrunk, gain @ cov + rest @ (trend_var[:, :, None] * np.swapaxes(rest, 1, 2))


def line_fits(sums: np.ndarray, *, order: int = 2, min_count: int = 102, correlation: int = 51,
              line_correlation: float = 1.0) -> LineFit:
    """Least-squares polynomial of order ``order`` along every row from :data:`FIT_SUMS`.

    After the global polynomial, what is left of a scanner's displacement along one line is
    its turbulence (a shift, a rotation) and the polynomial's own error, both smooth along
    the line; the matches add their noise, pixel by pixel. A low-order fit over the whole
    line averages that noise away where the line follows it; its covariance counts the
    matches once per ``correlation`` pixels (neighbouring matches share most of their
    template). How far the line departs from the fit beyond the matches' noise (``tau2``)
    says how much of each match to keep (:func:`geocoder.pipeline.lines.line_field`):
    relief or a local distortion makes it large and the matches stand.

    Parameters
    ----------
    sums : ndarray (15, H)
        :data:`FIT_SUMS` of whole rows.
    order : int
        0, 1 or 2.
    min_count : int
        Fewest matches a row needs for a fit.
    correlation : int
        Template length along the line (px): neighbouring matches share most of their template.
    line_correlation : float
        Template height (rows): neighbouring lines share most of their matches' rows
        (:func:`shrink_coefficients`).

    Returns
    -------
    LineFit
    """
    s = np.asarray(sums, dtype=np.float64)
    rows = s.shape[1]
    p = order + 1
    n = s[0]
    N = np.empty((rows, p, p))
    for i in range(p):
        for j in range(p):
            N[:, i, j] = s[i + j]
    ok = n >= max(min_count, p + 1)
    # rows whose normal matrix is too ill-conditioned to trust (matches bunched in one spot)
    cond = np.full(rows, np.inf)
    if ok.any():
        cond[ok] = np.linalg.cond(N[ok])
    ok &= cond < 1e8
    out = {k: np.zeros((rows, 3)) for k in ("cx", "cy")}
    var = {k: np.zeros(rows) for k in ("tau2_x", "tau2_y", "spread_x", "spread_y")}
    if not ok.any():
        return LineFit(**out, **var, lev=np.zeros((2, rows, 5)), ok=ok)
    inv = np.linalg.inv(N[ok])
    post = np.zeros((2, int(ok.sum()), p, p))
    lines = line_coordinate(np.flatnonzero(ok), rows)
    for a, (name, r0, rr, v) in enumerate((("x", 5, 11, 13), ("y", 8, 12, 14))):
        rhs = s[r0 : r0 + p, ok].T
        coef = np.einsum("rij,rj->ri", inv, rhs)
        # residual sum of squares of a least-squares fit: sum(r^2) - coef . rhs
        ss = np.maximum(s[rr, ok] - np.einsum("ri,ri->r", coef, rhs), 0.0)
        noise = s[v, ok] / n[ok]
        # how far the matches are shrunk: the residuals' variance counted as if the matches were
        # independent (smaller than the spread below), less their noise; that estimate scatters
        # as the residuals' variance over the row's n / correlation independent ones does
        excess = ss / (n[ok] - p) - noise
        var[f"tau2_{name}"][ok] = row_departures(excess, 2.0 * noise**2 * correlation / n[ok], lines)
        # the fit's own variance: neighbouring matches share their errors over ``correlation``
        # px, so a row holds about n / correlation independent ones and the fit takes p of them:
        # the residuals' variance over the rest (counted over n - p, the fit's sigma came out
        # 1.2-1.4x optimistic, issue 14); with less than one left, the matches' own variance
        dof = n[ok] - p * correlation
        spread = np.where(dof >= correlation, ss / np.maximum(dof, 1.0), noise)
        out[f"c{name}"][ok, :p], post[a] = shrink_coefficients(coef, (spread * correlation)[:, None, None] * inv,
                                                               lines, line_correlation=line_correlation)
        var[f"spread_{name}"][ok] = spread
    # the fit's variance a(u)^T P a(u), a = (1, u, u^2)[:p], as a quartic in u; x and y apart
    lev = np.zeros((2, rows, 5))
    for i in range(p):
        for j in range(p):
            lev[:, ok, i + j] += post[:, :, i, j]
    return LineFit(**out, **var, lev=lev, ok=ok)
