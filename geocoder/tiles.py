"""Tile grid: the core window of every tile, its halo, and block origins after an overlap."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np


@dataclass(frozen=True)
class Tile:
    """One tile of a grid: indices and the half-open core window in global pixels."""

    iy: int
    ix: int
    row0: int
    row1: int
    col0: int
    col1: int

    @property
    def key(self) -> str:
        return f"{self.iy}-{self.ix}"

    def window(self, halo: int = 0) -> tuple[int, int, int, int]:
        """Core window grown by ``halo`` on every side (not clipped)."""
        return self.row0 - halo, self.row1 + halo, self.col0 - halo, self.col1 + halo

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Mask of points whose nearest pixel lies in the core."""
        xi, yi = np.rint(x), np.rint(y)
        return (yi >= self.row0) & (yi < self.row1) & (xi >= self.col0) & (xi < self.col1)


def chunk_sizes(n: int, tile: int, *, min_last: int = 1) -> tuple[int, ...]:
    """Chunk sizes along one axis; a last chunk smaller than ``min_last`` joins its neighbour."""
    sizes = [tile] * (n // tile) + ([n % tile] if n % tile else [])
    if len(sizes) > 1 and sizes[-1] < min_last:
        sizes[-2] += sizes.pop()
    return tuple(sizes) if sizes else (n,)


@dataclass(frozen=True)
class TileGrid:
    """Regular tiling of an ``(height, width)`` image by chunks (see :func:`chunk_sizes`)."""

    height: int
    width: int
    rows: tuple[int, ...]
    cols: tuple[int, ...]

    @classmethod
    def regular(cls, height: int, width: int, tile: int, *, min_last: int = 1) -> TileGrid:
        return cls(height, width, chunk_sizes(height, tile, min_last=min_last), chunk_sizes(width, tile, min_last=min_last))

    @classmethod
    def from_chunks(cls, chunks: tuple[tuple[int, ...], tuple[int, ...]]) -> TileGrid:
        return cls(sum(chunks[0]), sum(chunks[1]), tuple(chunks[0]), tuple(chunks[1]))

    @property
    def chunks(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        return self.rows, self.cols

    def __iter__(self) -> Iterator[Tile]:
        r_edges = np.r_[0, np.cumsum(self.rows)]
        c_edges = np.r_[0, np.cumsum(self.cols)]
        for iy in range(len(self.rows)):
            for ix in range(len(self.cols)):
                yield Tile(iy, ix, int(r_edges[iy]), int(r_edges[iy + 1]), int(c_edges[ix]), int(c_edges[ix + 1]))

    def __len__(self) -> int:
        return len(self.rows) * len(self.cols)

    def overlapped_origin(self, iy: int, ix: int, depth: int) -> tuple[int, int, tuple[int, int, int, int]]:
        """Where block (iy, ix) of ``dask.array.overlap(..., depth, boundary='none')`` starts.

        Returns the global (row, col) of the block's first pixel and the block-local core
        window (row0, row1, col0, col1).
        """
        r0 = int(sum(self.rows[:iy]))
        c0 = int(sum(self.cols[:ix]))
        top = depth if iy > 0 else 0
        left = depth if ix > 0 else 0
        return r0 - top, c0 - left, (top, top + self.rows[iy], left, left + self.cols[ix])
