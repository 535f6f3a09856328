"""Automatic coarse alignment on a pyramid level, with no user-supplied overlap estimate.

If both scenes are georeferenced the prediction comes from their transforms (and CRSs);
otherwise Fourier-Mellin (log-polar phase correlation) finds rotation, scale and shift. In
both cases a phase correlation of the base overview against the distorted overview warped
into base geometry then corrects the translation (a georeference is often off by a few
pixels, seed 003 sec. 3). Works on small in-memory overviews; the caller makes them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import MatchingError
from ..kernels.phasecorr import estimate_similarity, phase_correlation
from ..kernels.polynomial import PolyMap
from ..kernels.resample import sample

#: smallest normalised phase-correlation peak taken as a real match
MIN_PEAK = 0.03


@dataclass(frozen=True)
class CoarseAlignment:
    """Affine prediction base pixel -> distorted pixel (full-resolution frames).

    ``method`` says where it came from (``georeference``, ``fourier-mellin``, with
    ``+shift`` when the phase correlation corrected it), ``factor`` is the pyramid level
    (overview pixel = factor x factor pixels) and ``peak`` the final correlation peak.
    """

    matrix: np.ndarray
    method: str
    factor: int
    peak: float

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


def refine_translation(base: np.ndarray, dist: np.ndarray, matrix: np.ndarray) -> tuple[np.ndarray, float]:
    """Correct the translation of ``matrix`` (base -> dist) by phase correlation."""
    warped = warp_into(dist, matrix, base.shape)
    valid = np.isfinite(warped) & np.isfinite(base)
    if valid.mean() < 0.05:
        return _h(matrix), 0.0
    shift = phase_correlation(base, warped)
    if not np.isfinite(shift.dx):
        return _h(matrix), 0.0
    t = np.array([[1.0, 0.0, shift.dx], [0.0, 1.0, shift.dy], [0.0, 0.0, 1.0]])
    return _h(matrix) @ t, float(shift.peak)


def align_overviews(
    base: np.ndarray,
    dist: np.ndarray,
    factor: int,
    *,
    prior: np.ndarray | None = None,
    min_peak: float = MIN_PEAK,
) -> CoarseAlignment:
    """Coarse affine between two overviews, returned in full-resolution pixel frames.

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
        If no rotation/scale/shift gives a correlation peak above ``min_peak``.
    """
    o = _overview_frame(factor)
    o_inv = np.linalg.inv(o)
    if prior is not None:
        start = o_inv @ _h(prior) @ o
        method = "georeference"
    else:
        sim = estimate_similarity(base, dist)
        if not np.all(np.isfinite(sim.matrix)) or sim.peak < min_peak:
            raise MatchingError(
                f"no overlap found between the images (Fourier-Mellin peak {sim.peak:.3f} < {min_peak})"
            )
        start = _h(sim.matrix)
        method = "fourier-mellin"
    refined, peak = refine_translation(base, dist, start)
    if peak >= min_peak:
        # a second pass removes what the first shift estimate left (windowing bias)
        again, peak2 = refine_translation(base, dist, refined)
        if peak2 >= peak:
            refined, peak = again, peak2
        method += "+shift"
        start = refined
    elif prior is None:
        raise MatchingError(f"no overlap found between the images (phase-correlation peak {peak:.3f})")
    full = o @ start @ o_inv
    return CoarseAlignment(matrix=full[:2], method=method, factor=factor, peak=float(peak))
