"""Terrain for the simulator: fractal DEMs and a bilinear DEM sampler in world coordinates."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from affine import Affine

from ..geometry import world_to_pixel


def fractal_dem(shape: tuple[int, int], *, seed: int, relief: float = 100.0, beta: float = 3.2) -> np.ndarray:
    """A fractal surface by spectral synthesis (power spectrum ``~ f^-beta``).

    Parameters
    ----------
    shape : (rows, cols)
    seed : int
    relief : float
        Height range (max - min) of the surface, in metres; the minimum is 0.
    beta : float
        Spectral exponent (3 to 3.5 gives natural-looking hills).

    Returns
    -------
    ndarray of float64, shape ``shape``
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2)
    amp[0, 0] = 0.0
    spec = amp * (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape))
    z = np.fft.irfft2(spec, s=shape)
    z -= z.min()
    top = z.max()
    return z * (relief / top) if top > 0 else z


@dataclass(frozen=True)
class Terrain:
    """Heights on a georeferenced grid, sampled bilinearly at world coordinates.

    ``transform`` is the grid's affine (GDAL corner convention); outside the grid the
    nearest edge value is used, so rays never fall off the terrain.
    """

    heights: np.ndarray
    transform: Affine

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        h, w = self.heights.shape
        px, py = world_to_pixel(self.transform, x, y)
        px = np.clip(np.nan_to_num(np.asarray(px, dtype=np.float64), nan=0.0), 0, w - 1)
        py = np.clip(np.nan_to_num(np.asarray(py, dtype=np.float64), nan=0.0), 0, h - 1)
        c0 = np.minimum(np.floor(px).astype(np.int64), w - 2) if w > 1 else np.zeros_like(px, dtype=np.int64)
        r0 = np.minimum(np.floor(py).astype(np.int64), h - 2) if h > 1 else np.zeros_like(py, dtype=np.int64)
        fx, fy = px - c0, py - r0
        z = self.heights
        c1 = np.minimum(c0 + 1, w - 1)
        r1 = np.minimum(r0 + 1, h - 1)
        return (
            z[r0, c0] * (1 - fx) * (1 - fy) + z[r0, c1] * fx * (1 - fy)
            + z[r1, c0] * (1 - fx) * fy + z[r1, c1] * fx * fy
        )

    @classmethod
    def flat(cls, height: float, transform: Affine) -> Terrain:
        return cls(np.full((2, 2), float(height)), transform)
