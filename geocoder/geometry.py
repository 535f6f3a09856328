"""Pixel <-> world coordinates: the one place where the half-pixel offset is applied.

Pixel coordinates follow the conventions (x = column, y = row, pixel centres at integers);
GDAL/rasterio affine transforms address pixel corners.
"""

from __future__ import annotations

import numpy as np
from affine import Affine


def pixel_to_world(transform: Affine, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World coordinates of pixel-centre coordinates ``(x=col, y=row)``.

    GDAL transforms address pixel corners; the centre of pixel (r, c) is at (c + 0.5, r + 0.5)
    in that frame. This function and :func:`world_to_pixel` are the only places that offset.
    """
    x = np.asarray(x, dtype=np.float64) + 0.5
    y = np.asarray(y, dtype=np.float64) + 0.5
    t = transform
    return t.a * x + t.b * y + t.c, t.d * x + t.e * y + t.f


def world_to_pixel(transform: Affine, wx: np.ndarray, wy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates ``(x=col, y=row)`` of world coordinates (inverse of the above)."""
    inv = ~transform
    wx = np.asarray(wx, dtype=np.float64)
    wy = np.asarray(wy, dtype=np.float64)
    return inv.a * wx + inv.b * wy + inv.c - 0.5, inv.d * wx + inv.e * wy + inv.f - 0.5
