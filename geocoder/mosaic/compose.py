"""Blending several resampled scenes into one output tile: seams nearest each scene's centre, feathered.

Pure numpy: no dask, no I/O. Every scene covering a pixel gets a score, its normalised
Chebyshev distance from the scene's centre (0 at the centre, 1 at its edge); the seam between
two scenes is where their scores are equal, so each pixel comes from the scene that sees it
closest to its centre (least lens/scan-angle distortion and relief displacement). Across a
seam the scenes are blended linearly over ``feather`` score units.
"""

from __future__ import annotations

import numpy as np

#: ``source`` value of a pixel that no scene covers.
NO_SOURCE = np.uint16(65535)


def centre_score(x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Normalised Chebyshev distance of scene pixels ``(x, y)`` from the scene's centre.

    0 at the centre, 1 on the outermost pixel centres, > 1 outside, NaN where not finite.
    """
    h, w = shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    return np.maximum(np.abs(x - cx) / max(cx, 0.5), np.abs(y - cy) / max(cy, 0.5))


def blend(values: np.ndarray, scores: np.ndarray, *, feather: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feathered composite of ``K`` co-registered scene samples.

    Parameters
    ----------
    values : ndarray, shape (K, B, h, w)
        Every scene resampled onto the output tile (NaN where it has no data).
    scores : ndarray, shape (K, h, w)
        :func:`centre_score` of every output pixel in every scene (NaN where not covered).
    feather : float
        Width of the blend across a seam, in score units (``2 * pixels / scene size``).

    Returns
    -------
    mosaic : ndarray, shape (B, h, w), float32
        Weighted mean of the covering scenes (NaN where none covers).
    source : ndarray, shape (h, w), uint16
        Index of the scene with the lowest score (:data:`NO_SOURCE` where none).
    weight : ndarray, shape (K, h, w), float32
        Normalised blending weights.
    """
    k = values.shape[0]
    covered = np.isfinite(scores) & np.all(np.isfinite(values), axis=1)
    s = np.where(covered, scores, np.inf)
    best = s.min(axis=0) if k else np.full(scores.shape[1:], np.inf)
    with np.errstate(invalid="ignore"):  # inf - inf where no scene covers a pixel
        raw = np.where(covered, np.clip(1.0 - (s - best) / max(feather, 1e-9), 0.0, 1.0), 0.0)
    total = raw.sum(axis=0)
    weight = np.divide(raw, total, out=np.zeros_like(raw), where=total > 0)
    mosaic = np.einsum("khw,kbhw->bhw", weight, np.where(covered[:, None], values, 0.0))
    mosaic[:, total == 0] = np.nan
    source = np.where(np.isfinite(best), np.argmin(s, axis=0), NO_SOURCE).astype(np.uint16) if k else \
        np.full(scores.shape[1:], NO_SOURCE, dtype=np.uint16)
    return mosaic.astype(np.float32), source, weight.astype(np.float32)
