"""Per-line estimates of the displacement where nothing was matched (issue 14).

A scanner's turbulence moves a whole scan line at once (seed 003 secs. 9-10): after the
global polynomial, what is left of the displacement is nearly the same for every pixel of a
line. So a pixel that could not be matched (no texture, a rejected blunder) but whose line
holds matches is better placed by the polynomial plus its line's mean residual than by the
polynomial alone, which cannot know the line's shift.

* :func:`line_sums` sums, per row of a block, the residuals ``d - polynomial`` of the
  usable pixels (matched or filled) and their squares; blocks of one row band add up.
* :func:`line_corrections` turns the sums of whole rows into a correction per row: the
  mean residual of a row with at least ``min_count`` usable pixels; for a row without,
  the linear interpolation between the nearest rows above and below that have one, if
  at most ``max_gap`` rows lie between them; the ``end_rows`` rows before the first and
  after the last row with data take that row's (the rows its templates covered); nothing
  farther. Its sigma is the spread of the row's residuals about
  their mean (how far a single shift per line is from the matches), for an interpolated
  row the larger of its two neighbours' plus half the step between their corrections.
* :func:`term_sums` and :func:`smooth_fit`: what the global polynomial leaves is not one
  shift per line only; it also errs smoothly along the lines (most at the scene's edges).
  A polynomial ``P`` of the line coordinate (:data:`TERMS`) is fitted to every line's
  residuals about that line's mean, by least squares over all lines, and taken off the
  lines' sums before :func:`line_corrections`: an unmatched pixel then takes the polynomial
  plus ``P`` plus its line's shift, anywhere along the line
  (:func:`geocoder.pipeline.lines.line_field`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

#: Quantities :func:`line_sums` returns per row, in this order: added over the blocks of a row
#: band, except ``first`` (the smallest column of a usable pixel; +inf without) and ``last``
#: (the largest; -inf without), reduced by min and max (:func:`combine_sums`).
SUMS = ("count", "sum_x", "sum_y", "sum_xx", "sum_yy", "sigma_count", "sum_sxx", "sum_syy", "first", "last")


@dataclass(frozen=True)
class LineOptions:
    """Options of the per-line estimates.

    Attributes
    ----------
    enabled : bool
        Give unmatched pixels of the overlap the per-line estimate (False: the polynomial).
    min_count : int
        Fewest usable (matched or filled) pixels a row needs for its own correction.
    max_gap : int
        Most consecutive rows without their own correction interpolated across.
    end_rows : int
        Rows before the first and after the last row with a correction of its own that take
        its correction (the template's half-height: the rows its matches saw); 0: none.
    max_hole : int
        Longest run of unmatched pixels along a line (px) that takes the interpolation of the
        residuals at its two ends instead of the line's estimate (0: never).
    edge : int
        Usable pixels (at most) averaged at each end of a hole for its residual there.
    smooth : int
        Window (px, odd) along the line of the sigma-weighted smoothing of the matches
        (:func:`smooth_matches`; 0: none, the default). Opt-in: with 129 the matched pixels'
        RMSE fell 0.065 -> 0.052 px (aerial 512^2), 0.104 -> 0.071 (S2 1024^2), 0.067 ->
        0.043 (the demo), but a window mean also carries the lattice's small path
        dependence to its neighbours: 0.0102 px between tilings 256 and 1024 on one pixel of
        the S2 test pair, over the tests' 0.01 bound (issue 14's notes).
    fit_order : int
        Order (0-2) of the polynomial along each line, fitted to the residuals of all of the
        line's matches, that every match is shrunk toward by how much the line departs from
        it beyond the matches' noise (:func:`line_fits`); -1: none.
    """

    enabled: bool = True
    min_count: int = 32
    max_gap: int = 8
    end_rows: int = 3
    max_hole: int = 128
    edge: int = 32
    smooth: int = 0
    fit_order: int = 2

    def validate(self) -> None:
        """Raise ValueError if an option is out of range."""
        if int(self.min_count) != self.min_count or self.min_count < 1:
            raise ValueError(f"min_count must be an integer >= 1, got {self.min_count!r}")
        if int(self.max_gap) != self.max_gap or self.max_gap < 0:
            raise ValueError(f"max_gap must be an integer >= 0, got {self.max_gap!r}")
        if int(self.end_rows) != self.end_rows or self.end_rows < 0:
            raise ValueError(f"end_rows must be an integer >= 0, got {self.end_rows!r}")
        if int(self.max_hole) != self.max_hole or self.max_hole < 0:
            raise ValueError(f"max_hole must be an integer >= 0, got {self.max_hole!r}")
        if int(self.edge) != self.edge or self.edge < 1:
            raise ValueError(f"edge must be an integer >= 1, got {self.edge!r}")
        if int(self.smooth) != self.smooth or self.smooth < 0 or (self.smooth and self.smooth % 2 == 0):
            raise ValueError(f"smooth must be 0 or an odd integer, got {self.smooth!r}")
        if self.fit_order not in (-1, 0, 1, 2):
            raise ValueError(f"fit_order must be -1, 0, 1 or 2, got {self.fit_order!r}")


def line_sums(dx: np.ndarray, dy: np.ndarray, px: np.ndarray, py: np.ndarray, usable: np.ndarray,
              sigma_x: np.ndarray, sigma_y: np.ndarray, col0: int = 0) -> np.ndarray:
    """Per row of a block: :data:`SUMS` of its usable pixels (residuals ``d - p``, their squares,
    the squared sigmas of the matches, and the columns of the first and last usable pixel).

    Parameters
    ----------
    dx, dy : ndarray (H, W)
        Displacement of the dense field.
    px, py : ndarray (H, W)
        Displacement of the global polynomial.
    usable : ndarray of bool (H, W)
        Pixels whose ``dx, dy`` rest on matches (matched or filled).
    sigma_x, sigma_y : ndarray (H, W)
        Standard deviations of the matches (NaN where none, e.g. filled pixels).
    col0 : int
        Column of the block's first pixel in the scene.

    Returns
    -------
    ndarray (10, H), float64
        The rows of :data:`SUMS`.
    """
    ex = np.where(usable, np.asarray(dx, np.float64) - px, 0.0)
    ey = np.where(usable, np.asarray(dy, np.float64) - py, 0.0)
    has_sigma = usable & np.isfinite(sigma_x) & np.isfinite(sigma_y)
    vx = np.where(has_sigma, np.asarray(sigma_x, np.float64) ** 2, 0.0)
    vy = np.where(has_sigma, np.asarray(sigma_y, np.float64) ** 2, 0.0)
    cols = np.arange(usable.shape[-1], dtype=np.float64) + col0
    first = np.where(usable, cols, np.inf).min(axis=-1)
    last = np.where(usable, cols, -np.inf).max(axis=-1)
    return np.stack([usable.sum(axis=-1).astype(np.float64), ex.sum(axis=-1), ey.sum(axis=-1),
                     (ex * ex).sum(axis=-1), (ey * ey).sum(axis=-1), has_sigma.sum(axis=-1).astype(np.float64),
                     vx.sum(axis=-1), vy.sum(axis=-1), first, last])


def combine_sums(parts: np.ndarray) -> np.ndarray:
    """:data:`SUMS` of whole rows from those of the blocks along them (last axis).

    Parameters
    ----------
    parts : ndarray (10, H, B)
        :func:`line_sums` of the ``B`` blocks of every row band.

    Returns
    -------
    ndarray (10, H)
    """
    out = parts.sum(axis=-1)
    out[8], out[9] = parts[8].min(axis=-1), parts[9].max(axis=-1)
    return out


@dataclass(frozen=True)
class LineCorrection:
    """Correction per row (:func:`line_corrections`); NaN where a row has none.

    Attributes
    ----------
    cx, cy : ndarray (H,)
        Correction of x and y (px) added to the polynomial's displacement.
    sx, sy : ndarray (H,)
        Standard deviation of a pixel's estimate in x and y (px).
    own : ndarray of bool (H,)
        The row's correction rests on its own matches (False: interpolated, or none).
    first, last : ndarray (H,)
        The span of a row's usable pixels (of an interpolated row, the overlap of its two
        neighbours' spans).
    smooth : ndarray (2, len(TERMS)) or None
        The smooth part along the lines (:func:`smooth_fit`) that ``cx, cy`` are the
        lines' shifts beyond; None: none.
    """

    cx: np.ndarray
    cy: np.ndarray
    sx: np.ndarray
    sy: np.ndarray
    own: np.ndarray
    first: np.ndarray
    last: np.ndarray
    smooth: np.ndarray | None = None


def line_corrections(sums: np.ndarray, *, min_count: int = 32, max_gap: int = 8, end_rows: int = 0,
                     correlation: int | None = None) -> LineCorrection:
    """A correction per row from the sums of whole rows (:func:`line_sums` added over the row).

    Parameters
    ----------
    sums : ndarray (5, H)
        :data:`SUMS` of every row, over the row's full width.
    min_count : int
        Fewest usable pixels a row needs for its own correction.
    max_gap : int
        Most consecutive rows without their own correction that are interpolated across.
    end_rows : int
        Rows before the first and after the last row with its own correction that take that
        row's correction (0: none), its sigma grown by the step to the next row inside per row.
    correlation : int, optional
        Length (px) along a line over which the matches' errors are correlated (a template's
        length). With it, each row's mean is shrunk toward the mean of all rows by how little
        the rows' means differ beyond their own uncertainty (:func:`shrink_rows`), so rows
        that share no shift (a push-broom scene) do not pass their noise on as stripes.

    Returns
    -------
    LineCorrection
    """
    n, sx_, sy_, sxx, syy, ns, svx, svy, first, last = np.asarray(sums, dtype=np.float64)
    rows = n.size
    own = n >= max(min_count, 1)
    safe = np.where(own, n, 1.0)
    cx, cy = sx_ / safe, sy_ / safe
    # The spread of the residuals about the line's mean is the matches' own noise plus how
    # far the line is from one shift; only the latter reaches an estimate, so the matches'
    # mean variance comes off (plus the uncertainty of the mean: the standard error, or with
    # ``correlation`` that of the shrunk mean).
    noise_x, noise_y = svx / np.maximum(ns, 1.0), svy / np.maximum(ns, 1.0)
    spread_x, spread_y = (sxx / safe - cx * cx).clip(0.0), (syy / safe - cy * cy).clip(0.0)
    err_x, err_y = spread_x / safe, spread_y / safe
    if correlation is not None and own.sum() > 2:
        effective = np.maximum(safe / max(correlation, 1), 1.0)
        cx, err_x = shrink_rows(cx, spread_x / effective, own)
        cy, err_y = shrink_rows(cy, spread_y / effective, own)
    vx = np.maximum(spread_x - noise_x, 0.0) + err_x
    vy = np.maximum(spread_y - noise_y, 0.0) + err_y
    out = {k: np.full(rows, np.nan) for k in ("cx", "cy", "sx", "sy", "first", "last")}
    if not own.any():
        return LineCorrection(**out, own=own)
    idx = np.arange(rows)
    out["cx"][own], out["cy"][own] = cx[own], cy[own]
    out["sx"][own], out["sy"][own] = np.sqrt(vx[own]), np.sqrt(vy[own])
    out["first"][own], out["last"][own] = first[own], last[own]
    # the nearest rows with their own correction above and below every row
    above = np.maximum.accumulate(np.where(own, idx, -1))
    below = np.minimum.accumulate(np.where(own, idx, rows)[::-1])[::-1]
    gap = (~own) & (above >= 0) & (below < rows) & (below - above - 1 <= max_gap)
    if gap.any():
        a, b = above[gap], below[gap]
        t = (idx[gap] - a) / (b - a)
        for c, v, name in ((cx, vx, "x"), (cy, vy, "y")):
            out[f"c{name}"][gap] = (1.0 - t) * c[a] + t * c[b]
            out[f"s{name}"][gap] = np.sqrt(np.maximum(v[a], v[b])) + 0.5 * np.abs(c[b] - c[a])
        out["first"][gap], out["last"][gap] = np.maximum(first[a], first[b]), np.minimum(last[a], last[b])
    # the rows before the first and after the last row with its own correction, up to end_rows:
    # that row's correction, its sigma grown by the step to the next row per row of distance
    owned = np.flatnonzero(own)
    for edge_row, inner, rows_out in ((owned[0], owned[1] if owned.size > 1 else owned[0],
                                       idx[max(owned[0] - end_rows, 0): owned[0]]),
                                      (owned[-1], owned[-2] if owned.size > 1 else owned[-1],
                                       idx[owned[-1] + 1: owned[-1] + 1 + end_rows])):
        if rows_out.size == 0:
            continue
        d = np.abs(rows_out - edge_row)
        span = max(abs(int(inner) - int(edge_row)), 1)
        for c, v, name in ((cx, vx, "x"), (cy, vy, "y")):
            out[f"c{name}"][rows_out] = c[edge_row]
            out[f"s{name}"][rows_out] = np.sqrt(v[edge_row]) + d * np.abs(c[edge_row] - c[inner]) / span
        out["first"][rows_out], out["last"][rows_out] = first[edge_row], last[edge_row]
    return LineCorrection(**out, own=own)


def shrink_rows(mean: np.ndarray, var: np.ndarray, own: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows' means shrunk toward their common mean by how much they differ beyond their noise.

    Empirical Bayes: with ``tau2`` the variance of the rows' true shifts (the variance of the
    means about their precision-weighted mean, less their mean variance ``var``), a row's mean
    moves ``tau2 / (tau2 + var)`` of the way from the common mean to its own. Rows that share a
    turbulence keep theirs; rows of a scene without one fall back to the common mean.

    Parameters
    ----------
    mean, var : ndarray (H,)
        Each row's mean residual and that mean's variance.
    own : ndarray of bool (H,)
        Rows with a mean of their own (the others are returned as they are).

    Returns
    -------
    mean, var : ndarray (H,)
        The shrunk means and their posterior variance ``k var``.
    """
    m, v = mean[own], np.maximum(var[own], 1e-12)
    w = 1.0 / v
    centre = float(np.sum(w * m) / np.sum(w))
    tau2 = max(float(np.mean((m - centre) ** 2) - np.mean(v)), 0.0)
    keep = tau2 / (tau2 + v)
    out_mean, out_var = mean.copy(), var.copy()
    out_mean[own] = centre + keep * (m - centre)
    out_var[own] = keep * v
    return out_mean, out_var


#: Quantities :func:`fit_sums` returns per row, all added over the blocks of a row band: the
#: moments ``sum(u^k)`` of the line coordinate of the matches, ``sum(r u^k)`` of their residuals
#: in x and y, the residuals' squares and the matches' variances.
FIT_SUMS = ("u0", "u1", "u2", "u3", "u4", "xu0", "xu1", "xu2", "yu0", "yu1", "yu2", "xx", "yy", "vx", "vy")


def line_coordinate(cols: np.ndarray, width: int) -> np.ndarray:
    """Column -> ``u`` in [-1, 1] across the scene's width (the fits' coordinate along a line)."""
    half = max(0.5 * (width - 1), 1.0)
    return (np.asarray(cols, np.float64) - 0.5 * (width - 1)) / half


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
        Coefficients of ``1, u, u^2`` (zero beyond the order) in x and y.
    tau2_x, tau2_y : ndarray (H,)
        Variance of the residuals about the fit beyond the matches' own noise (px^2): how far
        the line departs from the fit.
    spread_x, spread_y : ndarray (H,)
        Variance of the residuals about the fit (px^2).
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
                 sx: np.ndarray, sy: np.ndarray, u: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, ...]:
    """The matches of a block shrunk toward their lines' fits (see
    :func:`geocoder.pipeline.lines.shrink_to_lines`).

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

    Returns
    -------
    dx, dy, sx, sy : ndarray of float32 (h, w)
    """
    t = np.asarray(table, np.float64)
    uu = np.asarray(u, np.float64)[None, :]
    powers = [np.ones_like(uu), uu, uu * uu, uu**3, uu**4]
    out = []
    for a, (d, p, sig) in enumerate(((dx, px, sx), (dy, py, sy))):
        d64, s64 = np.asarray(d, np.float64), np.asarray(sig, np.float64)
        c = t[:, 1 + 3 * a : 4 + 3 * a]
        fit = c[:, :1] + c[:, 1:2] * uu + c[:, 2:3] * uu * uu
        s2 = s64 * s64
        tau2 = t[:, 7 + a : 8 + a]
        keep = tau2 / np.maximum(tau2 + s2, 1e-300)
        quartic = sum(t[:, 11 + 5 * a + k : 12 + 5 * a + k] * powers[k] for k in range(5))
        v_fit = np.minimum(quartic, t[:, 9 + a : 10 + a])
        value = p + fit + keep * (d64 - p - fit)
        sigma = np.sqrt(keep * s2 + (1.0 - keep) ** 2 * v_fit)
        sel = matched & (t[:, :1] > 0) & np.isfinite(s64) & np.isfinite(d64)
        out += [np.where(sel, value, d64).astype(np.float32), np.where(sel, sigma, s64).astype(np.float32)]
    return out[0], out[2], out[1], out[3]


def line_fits(sums: np.ndarray, *, order: int = 2, min_count: int = 102, correlation: int = 51) -> LineFit:
    """Least-squares polynomial of order ``order`` along every row from :data:`FIT_SUMS`.

    After the global polynomial, what is left of a scanner's displacement along one line is
    its turbulence (a shift, a rotation) and the polynomial's own error, both smooth along
    the line; the matches add their noise, pixel by pixel. A low-order fit over the whole
    line averages that noise away where the line follows it; its covariance counts the
    matches once per ``correlation`` pixels (neighbouring matches share most of their
    template). How far the line departs from the fit beyond the matches' noise (``tau2``)
    says how much of each match to keep (:func:`geocoder.pipeline.lines.shrink_to_lines`):
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
    for a, (name, r0, rr, v) in enumerate((("x", 5, 11, 13), ("y", 8, 12, 14))):
        rhs = s[r0 : r0 + p, ok].T
        coef = np.einsum("rij,rj->ri", inv, rhs)
        # residual sum of squares of a least-squares fit: sum(r^2) - coef . rhs
        ss = np.maximum(s[rr, ok] - np.einsum("ri,ri->r", coef, rhs), 0.0)
        spread = ss / (n[ok] - p)
        noise = s[v, ok] / n[ok]
        out[f"c{name}"][ok, :p] = coef
        post[a] = (spread * correlation)[:, None, None] * inv
        var[f"spread_{name}"][ok] = spread
        var[f"tau2_{name}"][ok] = np.maximum(spread - noise, 0.0)
    # the fit's variance a(u)^T P a(u), a = (1, u, u^2)[:p], as a quartic in u; x and y apart
    lev = np.zeros((2, rows, 5))
    for i in range(p):
        for j in range(p):
            lev[:, ok, i + j] += post[:, :, i, j]
    return LineFit(**out, **var, lev=lev, ok=ok)


@numba.njit(nogil=True, cache=True)
def _holes(rx, ry, vx, vy, usable, target, max_hole, edge, ox, oy, onx, ony, ok):  # pragma: no cover - compiled
    h, w = usable.shape
    ends = np.empty((2, 4))
    for r in range(h):
        c = 0
        while c < w:
            if not target[r, c]:
                c += 1
                continue
            a = c  # a run of targets [a, b)
            while c < w and target[r, c]:
                c += 1
            b = c
            if a == 0 or b == w or not usable[r, a - 1] or not usable[r, b] or b - a > max_hole:
                continue
            for side in range(2):
                n = 0
                nv = 0
                ends[side, :] = 0.0
                j = a - 1 if side == 0 else b
                while 0 <= j < w and usable[r, j] and n < edge:
                    ends[side, 0] += rx[r, j]
                    ends[side, 1] += ry[r, j]
                    n += 1
                    if vx[r, j] == vx[r, j] and vy[r, j] == vy[r, j]:  # filled pixels carry no sigma
                        ends[side, 2] += vx[r, j]
                        ends[side, 3] += vy[r, j]
                        nv += 1
                    j += -1 if side == 0 else 1
                ends[side, 0:2] /= n
                if nv > 0:
                    ends[side, 2:4] /= nv
                else:
                    ends[side, 2:4] = np.inf  # nothing known of the ends' noise: the line's mean
            span = float(b - a + 1)
            for j in range(a, b):
                t = (j - a + 1) / span
                ox[r, j] = (1.0 - t) * ends[0, 0] + t * ends[1, 0]
                oy[r, j] = (1.0 - t) * ends[0, 1] + t * ends[1, 1]
                onx[r, j] = (1.0 - t) * ends[0, 2] + t * ends[1, 2]
                ony[r, j] = (1.0 - t) * ends[0, 3] + t * ends[1, 3]
                ok[r, j] = True


def hole_estimates(rx: np.ndarray, ry: np.ndarray, vx: np.ndarray, vy: np.ndarray, usable: np.ndarray,
                   target: np.ndarray, *, max_hole: int, edge: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals interpolated along each line across holes bounded by usable pixels on both sides.

    A run of ``target`` pixels (unmatched pixels of the overlap) with a usable pixel right
    before and right after it on the same row, at most ``max_hole`` long, takes the linear
    interpolation between the mean residuals of the (at most ``edge``) usable pixels at
    either end, and the same interpolation of their variances: the residual after the
    polynomial may change along a line, and the ends of a hole see that change. Nothing is
    extrapolated: a run that reaches the block's edge or a pixel of another kind is left alone.

    Parameters
    ----------
    rx, ry : ndarray (H, W)
        Residuals ``d - polynomial`` (read where ``usable``).
    vx, vy : ndarray (H, W)
        Variances (sigma^2) of the usable pixels.
    usable : ndarray of bool (H, W)
        Matched or filled pixels.
    target : ndarray of bool (H, W)
        Pixels to estimate (disjoint from ``usable``).
    max_hole, edge : int
        See :class:`LineOptions`.

    Returns
    -------
    cx, cy, nx, ny : ndarray of float64 (H, W)
        Interpolated residual and the interpolated variance of the ends' matches (NaN where
        not estimated).
    ok : ndarray of bool (H, W)
        Estimated pixels.
    """
    shape = usable.shape
    out = [np.full(shape, np.nan) for _ in range(4)]
    ok = np.zeros(shape, dtype=np.bool_)
    if max_hole > 0:
        _holes(*(np.asarray(a, np.float64) for a in (rx, ry, vx, vy)), np.asarray(usable, np.bool_),
               np.asarray(target, np.bool_), int(max_hole), int(edge), *out, ok)
    return (*out, ok)


def smooth_matches(rx: np.ndarray, ry: np.ndarray, sx: np.ndarray, sy: np.ndarray, matched: np.ndarray, *,
                   window: int, correlation: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sigma-weighted smoothing of the matches' residuals along each line (a Wiener shrinkage).

    Around every matched pixel, over ``window`` pixels of its line, the matches' mean residual
    ``m``, and their spread beyond their own noise ``v = max(var(r) - mean(sigma^2), 0)``; the
    residual becomes ``m + k (r - m)`` with ``k = v / (v + sigma^2)``. Where the residual
    after the polynomial is one shift along the window (the turbulence of a line, or nothing
    at all on a field the polynomial explains), ``k`` is small and the pixel takes the
    window's mean, whose noise is that of many matches; where it changes (relief, a local
    distortion), ``k`` nears one and the match stands. Its sigma is the posterior one,
    ``k sigma^2 + (1 - k)^2 mean(sigma^2) / n_eff``, with ``n_eff`` the matches in the window
    over ``correlation`` (neighbouring matches share most of their template).

    Parameters
    ----------
    rx, ry : ndarray (H, W)
        Residuals ``d - polynomial`` (read where ``matched``).
    sx, sy : ndarray (H, W)
        The matches' sigmas.
    matched : ndarray of bool (H, W)
    window : int
        Odd window along the line (px).
    correlation : int
        Template length along the line (px).

    Returns
    -------
    rx, ry, sx, sy : ndarray of float64 (H, W)
        Smoothed residuals and sigmas at the matched pixels (the inputs elsewhere).
    """
    from scipy.ndimage import uniform_filter1d

    def box(a: np.ndarray) -> np.ndarray:
        return uniform_filter1d(a, window, axis=1, mode="constant") * window

    m = np.asarray(matched, dtype=bool)
    count = box(m.astype(np.float64))
    n = np.maximum(count, 1.0)
    n_eff = np.maximum(count / max(correlation, 1), 1.0)
    out = []
    for r0, s0 in ((rx, sx), (ry, sy)):
        r = np.where(m, np.asarray(r0, np.float64), 0.0)
        s2 = np.where(m, np.asarray(s0, np.float64) ** 2, 0.0)
        mean = box(r) / n
        noise = box(s2) / n
        spread = np.maximum(box(r * r) / n - mean * mean - noise, 0.0)
        k = spread / np.maximum(spread + s2, 1e-300)
        value = mean + k * (r - mean)
        sigma = np.sqrt(k * s2 + (1.0 - k) ** 2 * noise / n_eff)
        ok = m & (count > 0.5)
        out.append((np.where(ok, value, r0), np.where(ok, sigma, s0)))
    (vx, sgx), (vy, sgy) = out
    return vx, vy, sgx, sgy
