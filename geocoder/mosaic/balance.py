"""The radiometric balance of a block from the scenes' grey values at its control and tie points
(one small window read per tile of points; the least squares in :mod:`geocoder.mosaic.radiometry`)."""

from __future__ import annotations

import numpy as np
from affine import Affine

from ..geometry import world_to_pixel
from ..scene import WindowReader
from .radiometry import seam_step, solve_balance


def sample_points(reader: WindowReader, x: np.ndarray, y: np.ndarray, tile: int, *, radius: int = 3) -> np.ndarray:
    """Mean values ``(band, n)`` of a scene over ``(2 radius + 1)^2`` px around scattered points.

    A window mean, not the value at the point: tie points sit on corners, where the two
    scenes' different resampling blur changes single values but hardly a window's mean. One
    small window is read per tile of points.
    """
    off = np.arange(-radius, radius + 1, dtype=np.float64)
    ox, oy = np.meshgrid(off, off)
    out = np.full((reader.shape[0], x.size), np.nan, dtype=np.float32)
    ok = np.isfinite(x) & np.isfinite(y)
    key = np.where(ok, (np.floor(y / tile) * 1e6 + np.floor(x / tile)), -1)
    for k in np.unique(key[ok]):
        sel = key == k
        v = reader.sample(x[sel, None, None] + ox, y[sel, None, None] + oy, method="bilinear")
        with np.errstate(invalid="ignore"):
            out[:, sel] = np.mean(v, axis=(-2, -1))  # NaN if the window leaves the scene
    return out


def balance_block(readers: list, ref_reader: WindowReader | None, transform: Affine, tile: int, control: list, ties: list,
             nbands: int):
    """Gain and offset per scene and band (``(K, B, 2)``) and the seam step before and after
    (without a reference, ``ref_reader`` None and no ``control``: the scenes among themselves)."""
    ref_bands = nbands if ref_reader is None else ref_reader.shape[0]
    cvals = []
    for m in control:
        rx, ry = world_to_pixel(transform, m.a[:, 0], m.a[:, 1])
        cvals.append((m.j, sample_points(readers[m.j], m.b[:, 0], m.b[:, 1], tile), sample_points(ref_reader, rx, ry, tile)))
    tvals = [(t.i, t.j, sample_points(readers[t.i], t.a[:, 0], t.a[:, 1], tile),
              sample_points(readers[t.j], t.b[:, 0], t.b[:, 1], tile)) for t in ties]
    gains = np.zeros((len(readers), nbands, 2))
    before, after = [], []
    for b in range(nbands):
        rb = b if b < ref_bands else 0
        c = [(k, v[b], r[rb]) for k, v, r in cvals] if ref_bands == nbands else []  # else: scenes among themselves
        t = [(i, j, vi[b], vj[b]) for i, j, vi, vj in tvals]
        gains[:, b] = solve_balance(len(readers), c, t)
        before.append(seam_step(t))
        after.append(seam_step(t, gains[:, b]))
    return gains, [float(np.sqrt(np.nanmean(np.square(before)))), float(np.sqrt(np.nanmean(np.square(after))))]


__all__ = ["balance_block", "sample_points"]
