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
* :mod:`geocoder.quality.line_fits`: what the global polynomial leaves is not one shift per
  line only; it also errs smoothly along the lines, and the smooth part fitted over all
  lines is taken off the lines' sums before :func:`line_corrections`; every line's own fit
  shrinks its matches. :func:`hole_estimates` and :func:`smooth_matches` (below) work along
  a line within a tile's reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .shrinkage import shrink

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
    max_departure, departure_floor : float
        A match further from its line than ``max_departure`` times its residual's standard
        deviation, and than ``departure_floor`` px, is flagged ``BLUNDER`` and estimated like
        an unmatched pixel (:func:`~geocoder.quality.line_fits.departures`: against the line's
        fit, or on a line without one its shift plus the smooth part along the lines); 0: never.
        On the nine cases of ``bench_dense_cases.py`` (5 against 0) the matched RMSE the same or
        0.001 px lower, coverage the same or 0.1 point lower; on issue 14's Landsat crop a run of
        four matches 1.1 px off, the only unflagged error above 1 px, is flagged.
    """

    enabled: bool = True
    min_count: int = 32
    max_gap: int = 8
    end_rows: int = 3
    max_hole: int = 128
    edge: int = 32
    smooth: int = 0
    fit_order: int = 2
    max_departure: float = 5.0
    departure_floor: float = 0.3

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
        if not self.max_departure >= 0 or not self.departure_floor >= 0:
            raise ValueError(f"max_departure and departure_floor must be >= 0, got {self.max_departure!r}, "
                             f"{self.departure_floor!r}")


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
        the rows' means differ beyond their own uncertainty
        (:func:`geocoder.quality.shrinkage.shrink`), so rows
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
        common = np.ones((int(own.sum()), 1))  # toward the rows' common mean
        for c, spread, err in ((cx, spread_x, err_x), (cy, spread_y, err_y)):
            c[own], err[own] = shrink(c[own], np.maximum(spread[own] / effective[own], 1e-12), common)
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


@numba.njit(nogil=True, cache=True)
def estimate_unmatched(dx, dy, px, py, sx, sy, holes, rows, part, target, out, status, estimated):  # pragma: no cover - compiled
    """Every ``target`` pixel of a corrected row estimated, pixel by pixel (the rules are
    :func:`geocoder.pipeline.lines._estimates`'); the others copied.

    Parameters
    ----------
    dx, dy, px, py, sx, sy : float (h, w)
        The field, the polynomial's displacement and the matches' sigmas.
    holes : float (5, h, w)
        :func:`hole_estimates` at every pixel: ``cx, cy, nx, ny, ok``.
    rows : float64 (h, 6)
        The rows' ``first, last, cx, cy, sx, sy`` (:func:`line_corrections`).
    part : float (2, h, w)
        The smooth part along the lines.
    target : bool (h, w)
        The pixels to estimate.
    out : float32 (4, h, w)
        Gets ``dx, dy, sigma_x, sigma_y``.
    status : uint8 (h, w)
        Set to ``estimated`` where a pixel was.
    """
    h, w = target.shape
    for r in range(h):
        line_ok = math.isfinite(rows[r, 2]) and math.isfinite(rows[r, 3])
        spread_ok = math.isfinite(rows[r, 4]) and math.isfinite(rows[r, 5])
        for c in range(w):
            if not target[r, c]:
                out[0, r, c] = dx[r, c]
                out[1, r, c] = dy[r, c]
                out[2, r, c] = sx[r, c]
                out[3, r, c] = sy[r, c]
                continue
            # a hole needs its ends' noise or its line's spread for a sigma
            known = (math.isfinite(holes[2, r, c]) and math.isfinite(holes[3, r, c])) or spread_ok
            by_hole = holes[4, r, c] > 0 and known
            by_line = not by_hole and line_ok
            if by_hole or by_line:
                status[r, c] = estimated
            for k in range(2):
                d = dx[r, c] if k == 0 else dy[r, c]
                p = px[r, c] if k == 0 else py[r, c]
                s = sx[r, c] if k == 0 else sy[r, c]
                corr, sig = rows[r, 2 + k], rows[r, 4 + k]
                line = (corr if corr == corr else 0.0) + part[k, r, c]
                spread = sig * sig if sig == sig else math.inf  # how far the line is from its estimate
                noise = holes[2 + k, r, c]
                # how much of the ends' departure from the line's estimate to keep: all of it where the
                # line is far from it, none where the ends differ from it by their noise only
                keep = 1.0
                if math.isfinite(spread):
                    den = spread + noise  # NaN where the ends' noise is not known: keep NaN, sigma the spread
                    keep = spread / (den if not den < 1e-12 else 1e-12)
                if by_hole:
                    out[k, r, c] = p + (line + keep * (holes[k, r, c] - line))
                    # the posterior variance of the shrunk departure, keep * noise (= (1 - keep) * spread);
                    # with nothing known of the ends' noise (keep = 0), the line's spread
                    out[2 + k, r, c] = math.sqrt(keep * noise if keep > 0 else spread)
                elif by_line:
                    out[k, r, c] = p + line
                    out[2 + k, r, c] = sig
                else:
                    out[k, r, c] = d
                    out[2 + k, r, c] = s
