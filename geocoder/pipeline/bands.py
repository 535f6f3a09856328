"""The bands the dense matching uses at once (seed 003 sec. 11), and the windows its tasks match on."""

from __future__ import annotations

from dataclasses import dataclass

import dask
import numpy as np

__all__ = ["Bands", "band_windows"]


@dataclass(frozen=True)
class Bands:
    """The bands the dense matching uses at once, and each band's grey-value scale.

    A window's bands are taken as ``(value - location) / noise`` with the location and noise
    of the whole band (:func:`geocoder.kernels.alsc_bands.band_scales`), the same in every
    tile, so the bands weigh by their noise and the result does not depend on the tiling.

    Attributes
    ----------
    index : tuple of int
        0-based bands, the same in both scenes.
    base_scales, dist_scales : ndarray (n, 2)
        Location and noise of each band of the base and of the distorted scene.
    """

    index: tuple[int, ...]
    base_scales: np.ndarray
    dist_scales: np.ndarray

    @classmethod
    def of(cls, base, dist, bands: tuple[int, ...]) -> Bands:
        """The 1-based ``bands`` of two scenes (``(band, y, x)`` DataArrays), scaled from the
        central 1024 x 1024 pixels of each (or all of a smaller scene)."""
        from ..kernels.alsc_bands import band_scales

        index = tuple(int(b) - 1 for b in bands)

        def centre(scene):
            h, w = scene.sizes["y"], scene.sizes["x"]
            r0, c0 = max((h - 1024) // 2, 0), max((w - 1024) // 2, 0)
            return scene.data[list(index), r0 : r0 + 1024, c0 : c0 + 1024]

        crops = dask.compute(centre(base), centre(dist))  # one graph for both scenes
        return cls(index, band_scales(np.asarray(crops[0])), band_scales(np.asarray(crops[1])))

    def pick(self, window: np.ndarray, scales: np.ndarray) -> np.ndarray:
        """The bands of a ``(band, y, x)`` window, scaled, float32 ``(n, y, x)``."""
        w = np.asarray(window)[list(self.index)]
        return ((w - scales[:, 0, None, None]) / scales[:, 1, None, None]).astype(np.float32)


def band_windows(base: np.ndarray, dist: np.ndarray, band: int, dist_band: int,
             bands: Bands | None) -> tuple[np.ndarray, np.ndarray]:
    """The matched band of a base and a distorted window (2-D), or with ``bands`` all of them (3-D)."""
    if bands is None:
        return base[band], dist[dist_band]
    return bands.pick(base, bands.base_scales), bands.pick(dist, bands.dist_scales)

