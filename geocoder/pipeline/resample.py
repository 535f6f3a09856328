"""Displacement fields on the base grid, and the single resampling of the distorted image.

One task per output tile: the tile's displacement says which window of the ORIGINAL
distorted image it needs; the task reads exactly that window from the Zarr store and
samples every band once at ``p + d(p)``.
"""

from __future__ import annotations

import dask.array as da
import numpy as np

from ..kernels.polynomial import PolyMap
from ..scene import WindowReader
from ..status import Status


def _poly_block(block_info=None, *, mapping: PolyMap, component: int):
    loc = block_info[None]["array-location"]
    (r0, r1), (c0, c1) = loc
    ys, xs = np.mgrid[r0:r1, c0:c1].astype(np.float64)
    out = mapping(xs, ys)[component]
    return (out - (xs if component == 0 else ys)).astype(np.float32)


def polynomial_displacement(mapping: PolyMap, chunks: tuple[tuple[int, ...], tuple[int, ...]]) -> tuple[da.Array, da.Array]:
    """Lazy ``dx, dy`` (float32, on the base grid) of a polynomial base -> distorted mapping."""
    dx = da.map_blocks(_poly_block, chunks=chunks, dtype=np.float32, mapping=mapping, component=0, name=f"dx-poly-{da.core.tokenize(mapping.coef)}")
    dy = da.map_blocks(_poly_block, chunks=chunks, dtype=np.float32, mapping=mapping, component=1, name=f"dy-poly-{da.core.tokenize(mapping.coef)}")
    return dx, dy


def _resample_block(dx, dy, block_info=None, *, reader: WindowReader, method: str):
    (r0, r1), (c0, c1) = block_info[0]["array-location"]
    ys, xs = np.mgrid[r0:r1, c0:c1].astype(np.float64)
    return reader.sample(xs + dx, ys + dy, method=method)


def resample(reader: WindowReader, dx: da.Array, dy: da.Array, *, method: str = "bilinear") -> da.Array:
    """Registered bands ``(band, y, x)`` on the base grid, float32, NaN outside the overlap.

    Parameters
    ----------
    reader : WindowReader
        The ORIGINAL distorted scene in Zarr.
    dx, dy : dask.array.Array, shape (H, W)
        Displacement ``p_distorted - p_base`` on the base grid (chunks = output tiles).
    method : {"nearest", "bilinear", "cubic", "lanczos"}
    """
    nbands = reader.shape[0]
    return da.map_blocks(
        _resample_block, dx, dy,
        new_axis=0, chunks=((nbands,), *dx.chunks), dtype=np.float32,
        reader=reader, method=method,
    )


def model_status(registered: da.Array) -> da.Array:
    """Status of a polynomial-only registration: MODEL inside the overlap, else OUTSIDE."""
    inside = ~da.isnan(registered).all(axis=0)
    return da.where(inside, np.uint8(Status.MODEL), np.uint8(Status.OUTSIDE)).astype(np.uint8)
