"""Displacement fields on the base grid, and the single resampling of the distorted image.

One task per output tile: the tile's displacement says which window of the ORIGINAL
distorted image it needs; the task reads exactly that window from the Zarr store and
samples every band once at ``p + d(p)``.
"""

from __future__ import annotations

import dask.array as da
import numpy as np

from ..kernels.polynomial import PolyMap, exponents
from ..scene import WindowReader
from ..status import Status


def poly_grid(mapping: PolyMap, rows: tuple[int, int], cols: tuple[int, int], component: int) -> np.ndarray:
    """One component of ``mapping(x, y) - (x, y)`` on the pixel grid ``rows x cols``, float64.

    The monomials ``u^i v^j`` of a grid are outer products of a column and a row vector,
    so the map is summed as ``sum_i (sum_j c_ij v^j) u^i``: ``order + 1`` passes over the
    block instead of a design matrix of all monomials of every pixel. Equal to
    ``mapping(xs, ys)[component] - (xs, ys)[component]`` up to float64 rounding (1e-12 px).
    """
    (r0, r1), (c0, c1) = rows, cols
    x = np.arange(c0, c1, dtype=np.float64)
    y = np.arange(r0, r1, dtype=np.float64)
    u = (x - mapping.centre[0]) / mapping.scale
    v = (y - mapping.centre[1]) / mapping.scale
    coef = mapping.coef[:, component]
    terms = exponents(mapping.order)
    out = np.zeros((y.size, x.size))
    for i in range(mapping.order + 1):
        a = np.zeros(y.size)  # coefficient of u^i, per row
        for k, (ei, ej) in enumerate(terms):
            if ei == i:
                a += coef[k] * v**ej
        out += a[:, None] * (u**i)[None, :]
    out -= x[None, :] if component == 0 else y[:, None]
    return out


def _poly_block(block_info=None, *, mapping: PolyMap, component: int):
    (r0, r1), (c0, c1) = block_info[None]["array-location"]
    return poly_grid(mapping, (r0, r1), (c0, c1), component).astype(np.float32)


def polynomial_displacement(mapping: PolyMap, chunks: tuple[tuple[int, ...], tuple[int, ...]]) -> tuple[da.Array, da.Array]:
    """Lazy ``dx, dy`` (float32, on the base grid) of a polynomial base -> distorted mapping."""
    # the whole map (coefficients, order, centre, scale) and the chunks name the layers
    token = da.core.tokenize(mapping.to_dict(), chunks)
    dx = da.map_blocks(_poly_block, chunks=chunks, dtype=np.float32, mapping=mapping, component=0, name=f"dx-poly-{token}")
    dy = da.map_blocks(_poly_block, chunks=chunks, dtype=np.float32, mapping=mapping, component=1, name=f"dy-poly-{token}")
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


def _status_block(block: np.ndarray) -> np.ndarray:
    inside = ~np.isnan(block).all(axis=0)
    return np.where(inside, np.uint8(Status.MODEL), np.uint8(Status.OUTSIDE)).astype(np.uint8)


def model_status(registered: da.Array) -> da.Array:
    """Status of a polynomial-only registration: MODEL inside the overlap, else OUTSIDE.

    One task per tile (``isnan``, ``all``, ``~`` and ``where`` as separate array
    operations made four).
    """
    return da.map_blocks(_status_block, registered, drop_axis=0, dtype=np.uint8,
                         chunks=registered.chunks[1:])
