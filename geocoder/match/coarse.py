"""Automatic coarse alignment on a pyramid level, with no user-supplied overlap estimate.

If both scenes are georeferenced the prediction comes from their transforms (and CRSs);
otherwise Fourier-Mellin (log-polar phase correlation) finds rotation, scale and shift. In
both cases a phase correlation of the base overview against the distorted overview warped
into base geometry then corrects the translation (a georeference is often off by a few
pixels, seed 003 sec. 3). Works on small in-memory overviews; the caller makes them.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from ..errors import MatchingError
from ..kernels.phasecorr import estimate_similarity, phase_correlation
from ..kernels.polynomial import PolyMap
from ..kernels.resample import sample
from ..kernels.robust import StopReason

#: smallest normalised phase-correlation peak taken as a real match
MIN_PEAK = 0.03
#: a plain shift's phase-correlation peak from which no rotation or scale is looked for
#: (Fourier-Mellin): the overviews then differ by little more than a shift
DECISIVE_PEAK = 0.5


class Hypothesis(StrEnum):
    """Where a coarse alignment starts from."""

    GEOREFERENCE = "georeference"
    FOURIER_MELLIN = "fourier-mellin"
    TRANSLATION = "translation"
    #: both images already placed by matching (a mosaic's tie pair): the prior, taken as it is
    PLACEMENT = "placement"


@dataclass(frozen=True)
class CoarseAlignment:
    """Affine prediction base pixel -> distorted pixel (full-resolution frames).

    ``start`` says where it came from, ``shifted`` whether the phase correlation corrected
    its translation, ``affine`` whether local phase correlations refined it to a full affine
    (see :attr:`method`); ``factor`` is the pyramid level (overview pixel = factor x factor
    pixels) and ``peak`` the final correlation peak.
    """

    matrix: np.ndarray
    start: Hypothesis
    shifted: bool
    affine: bool
    factor: int
    peak: float

    @property
    def method(self) -> str:
        """The start with ``+shift`` and ``+affine`` for the refinements made (as reported)."""
        return str(self.start) + ("+shift" if self.shifted else "") + ("+affine" if self.affine else "")

    @property
    def mapping(self) -> PolyMap:
        return PolyMap.from_affine(self.matrix)


def _h(m: np.ndarray) -> np.ndarray:
    return np.vstack([np.asarray(m, dtype=np.float64)[:2], [0.0, 0.0, 1.0]])


def _overview_frame(factor: int) -> np.ndarray:
    """Overview pixel -> full-resolution pixel (pixel centres), 3x3."""
    c = (factor - 1) / 2.0
    return np.array([[factor, 0.0, c], [0.0, factor, c], [0.0, 0.0, 1.0]])


def warp_into(dist: np.ndarray, matrix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``dist`` resampled on a grid of ``shape`` through the 2x3 (or 3x3) ``matrix``."""
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    m = _h(matrix)
    return sample(dist, m[0, 0] * xs + m[0, 1] * ys + m[0, 2], m[1, 0] * xs + m[1, 1] * ys + m[1, 2], method="bilinear")


def overlap_correlation(a: np.ndarray, b: np.ndarray, dx: float, dy: float, *, min_fraction: float = 0.02) -> float:
    """Correlation coefficient of ``a(x, y)`` and ``b(x + dx, y + dy)`` (shift rounded) over their overlap.

    NaN if fewer than ``min_fraction`` of the pixels (and 256) are valid in both.
    """
    h, w = a.shape
    ix, iy = int(round(dx)), int(round(dy))
    ya, yb = slice(max(0, -iy), min(h, h - iy)), slice(max(0, iy), min(h, h + iy))
    xa, xb = slice(max(0, -ix), min(w, w - ix)), slice(max(0, ix), min(w, w + ix))
    pa, pb = a[ya, xa], b[yb, xb]
    ok = np.isfinite(pa) & np.isfinite(pb)
    if ok.sum() < max(256, min_fraction * a.size):
        return float("nan")
    u, v = pa[ok] - pa[ok].mean(), pb[ok] - pb[ok].mean()
    denom = np.sqrt((u * u).sum() * (v * v).sum())
    return float((u * v).sum() / denom) if denom > 0 else float("nan")


def unwrap_shift(a: np.ndarray, b: np.ndarray, dx: float, dy: float) -> tuple[float, float]:
    """The shift among the circular aliases of ``(dx, dy)`` (one image size either way) that correlates best.

    Phase correlation is circular: a shift of 300 px on a 512 px overview reads as -212 px.
    """
    h, w = a.shape
    cand_x = [c for c in (dx, dx - w, dx + w) if abs(c) < w]
    cand_y = [c for c in (dy, dy - h, dy + h) if abs(c) < h]
    scored = [(overlap_correlation(a, b, cx, cy), cx, cy) for cx in cand_x for cy in cand_y]
    scored = [s for s in scored if np.isfinite(s[0])]
    if not scored:
        return dx, dy
    _, bx, by = max(scored)
    return bx, by


def refine_translation(base: np.ndarray, dist: np.ndarray, matrix: np.ndarray, *, local: bool = False) -> tuple[np.ndarray, float]:
    """Correct the translation of ``matrix`` (base -> dist) by phase correlation.

    ``local``: ``matrix`` already places the distorted image (a georeference, an earlier
    refinement). Where its footprint covers less than half of ``base`` (a small scene on a
    large reference), the correlation also runs on the footprint's bounding box grown by a
    quarter of its size on every side, where the rest of the base adds no false peaks (shifts
    up to about that quarter are found there); the higher of the two peaks wins, so a
    georeference hundreds of pixels off is still corrected by the whole base.
    """
    warped = warp_into(dist, matrix, base.shape)
    valid = np.isfinite(warped) & np.isfinite(base)
    rows, cols = np.nonzero(valid.any(axis=1))[0], np.nonzero(valid.any(axis=0))[0]
    windows = []
    if valid.mean() >= 0.05:
        windows.append((base, warped))
    if local and rows.size >= 8 and cols.size >= 8 and (rows[-1] + 1 - rows[0]) * (cols[-1] + 1 - cols[0]) < 0.5 * base.size:
        grow_r, grow_c = (rows[-1] - rows[0]) // 4 + 4, (cols[-1] - cols[0]) // 4 + 4
        r0, r1 = max(rows[0] - grow_r, 0), min(rows[-1] + 1 + grow_r, base.shape[0])
        c0, c1 = max(cols[0] - grow_c, 0), min(cols[-1] + 1 + grow_c, base.shape[1])
        windows.append((base[r0:r1, c0:c1], warped[r0:r1, c0:c1]))
    best = (0.0, 0.0, 0.0)
    for a, b in windows:
        shift = phase_correlation(a, b)
        if np.isfinite(shift.dx) and shift.peak > best[0]:
            best = (float(shift.peak), *unwrap_shift(a, b, shift.dx, shift.dy))
    peak, dx, dy = best
    if peak <= 0.0:
        return _h(matrix), 0.0
    t = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
    return _h(matrix) @ t, peak


def refine_affine(base: np.ndarray, dist: np.ndarray, matrix: np.ndarray, *, grid: int = 3, min_peak: float = MIN_PEAK) -> np.ndarray:
    """Correct ``matrix`` (base -> dist, 3x3) to a full affine from local phase correlations.

    The distorted overview is warped into base geometry; ``grid`` x ``grid`` half-size
    windows are phase-correlated against the base; their shifts (weighted by the peak)
    give a robust affine correction. This is seed 000's second matching stage (patches at
    reduced resolution to take out affine distortion), which a similarity cannot model.
    """
    from ..kernels.polynomial import fit_polymap

    h, w = base.shape
    wh, ww = max(h // 2, 16), max(w // 2, 16)
    if h < 32 or w < 32:
        return _h(matrix)
    warped = warp_into(dist, matrix, base.shape)
    cx, cy, sx, sy, peaks = [], [], [], [], []
    for r0 in np.linspace(0, h - wh, grid).astype(int):
        for c0 in np.linspace(0, w - ww, grid).astype(int):
            a = base[r0 : r0 + wh, c0 : c0 + ww]
            b = warped[r0 : r0 + wh, c0 : c0 + ww]
            if np.isfinite(b).mean() < 0.5 or np.isfinite(a).mean() < 0.5:
                continue
            shift = phase_correlation(a, b)
            if np.isfinite(shift.dx) and shift.peak >= min_peak:
                cx.append(c0 + (ww - 1) / 2)
                cy.append(r0 + (wh - 1) / 2)
                sx.append(shift.dx)
                sy.append(shift.dy)
                peaks.append(shift.peak)
    if len(cx) < 4:
        return _h(matrix)
    cx, cy = np.asarray(cx), np.asarray(cy)
    corr = fit_polymap(cx, cy, cx + np.asarray(sx), cy + np.asarray(sy), order=1, weights=np.asarray(peaks), min_points=4)
    if corr.fit_info.reason == StopReason.TOO_FEW:
        return _h(matrix)
    # correction as a 3x3 matrix in base coordinates: p -> corr(p)
    ex, ey = corr(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    c = np.array([[ex[1] - ex[0], ex[2] - ex[0], ex[0]], [ey[1] - ey[0], ey[2] - ey[0], ey[0]], [0.0, 0.0, 1.0]])
    return _h(matrix) @ c


def align_overviews(
    base: np.ndarray,
    dist: np.ndarray,
    factor: int,
    *,
    prior: np.ndarray | None = None,
    min_peak: float = MIN_PEAK,
) -> CoarseAlignment:
    """Coarse affine between two overviews, returned in full-resolution pixel frames.

    Hypotheses: the georeference ``prior`` if given, else the identity and, unless its
    translation already correlates with a peak of :data:`DECISIVE_PEAK`, the Fourier-Mellin
    similarity. Each gets its translation corrected by phase correlation, the one with the
    highest peak wins, and local phase correlations then refine it to a full affine.

    Parameters
    ----------
    base, dist : ndarray, 2-D
        Overviews (block means over ``factor`` x ``factor`` pixels), NaN = nodata.
    factor : int
        Pyramid factor of both overviews.
    prior : ndarray (2x3), optional
        Full-resolution prediction from the georeference.

    Raises
    ------
    MatchingError
        If no hypothesis gives a correlation peak above ``min_peak``.
    """
    o = _overview_frame(factor)
    o_inv = np.linalg.inv(o)

    def shifted_start(name: Hypothesis, start: np.ndarray) -> tuple:
        refined, peak = refine_translation(base, dist, start, local=name == Hypothesis.GEOREFERENCE)
        shifted = peak >= min_peak
        if shifted:
            again, peak2 = refine_translation(base, dist, refined, local=True)
            if peak2 >= peak:
                refined, peak = again, peak2
        else:
            refined = start
        return name, shifted, refined, peak

    if prior is not None:
        best = shifted_start(Hypothesis.GEOREFERENCE, o_inv @ _h(prior) @ o)
    else:
        # a plain shift first: where it correlates decisively, rotation and scale are small
        # enough for the affine refinement below, and Fourier-Mellin (three quarters of the
        # alignment's time) is not needed
        best = shifted_start(Hypothesis.TRANSLATION, np.eye(3))
        if best[3] < DECISIVE_PEAK:
            sim = estimate_similarity(base, dist)
            if np.all(np.isfinite(sim.matrix)):
                other = shifted_start(Hypothesis.FOURIER_MELLIN, _h(sim.matrix))
                if other[3] >= best[3]:
                    best = other
    name, shifted, matrix, peak = best
    if peak < min_peak and prior is None:
        raise MatchingError(f"no overlap found between the images (best correlation peak {peak:.3f} < {min_peak})")
    affine = peak >= min_peak
    if affine:
        for _ in range(2):
            matrix = refine_affine(base, dist, matrix, min_peak=min_peak)
        _, peak_after = refine_translation(base, dist, matrix, local=True)
        peak = max(peak, peak_after)
    full = o @ matrix @ o_inv
    return CoarseAlignment(matrix=full[:2], start=name, shifted=shifted, affine=affine, factor=factor, peak=float(peak))
