"""Tile grid: the core window of every tile, its halo, and block origins after an overlap."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, NamedTuple

import numpy as np


class Window(NamedTuple):
    """A half-open window of pixels, ``row0, row1, col0, col1`` (a tuple: it unpacks as one).

    The one place where windows are grown, clipped and turned into slices, so that the stages
    do not each write ``max(a - halo, 0), min(b + halo, n)`` by hand.
    """

    row0: int
    row1: int
    col0: int
    col1: int

    @property
    def shape(self) -> tuple[int, int]:
        """Rows and columns (negative sizes read as 0)."""
        return max(self.row1 - self.row0, 0), max(self.col1 - self.col0, 0)

    @property
    def empty(self) -> bool:
        """Whether the window holds no pixel."""
        return self.row1 <= self.row0 or self.col1 <= self.col0

    def grow(self, rows: int, cols: int | None = None) -> Window:
        """The window grown by ``rows`` above and below and ``cols`` (default ``rows``) left and right."""
        cols = rows if cols is None else cols
        return Window(self.row0 - rows, self.row1 + rows, self.col0 - cols, self.col1 + cols)

    def clip(self, height: int, width: int) -> Window:
        """The part inside ``[0, height) x [0, width)`` (possibly empty)."""
        return Window(max(self.row0, 0), min(self.row1, height), max(self.col0, 0), min(self.col1, width))

    def slices(self, origin: tuple[int, int] = (0, 0)) -> tuple[slice, slice]:
        """Row and column slices of the window in an array whose first pixel is ``origin`` (row, col)."""
        return slice(self.row0 - origin[0], self.row1 - origin[0]), slice(self.col0 - origin[1], self.col1 - origin[1])

    @classmethod
    def around(cls, rows: np.ndarray, cols: np.ndarray, margin: float = 0.0) -> Window:
        """The window of whole pixels that holds every ``(row, col)`` point, grown by ``margin``
        (e.g. a tile's outline mapped through a prediction into another image)."""
        return cls(int(math.floor(float(np.min(rows)) - margin)), int(math.ceil(float(np.max(rows)) + margin)) + 1,
                   int(math.floor(float(np.min(cols)) - margin)), int(math.ceil(float(np.max(cols)) + margin)) + 1)


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

    def window(self, halo: int = 0) -> Window:
        """Core window grown by ``halo`` on every side (not clipped)."""
        return Window(self.row0, self.row1, self.col0, self.col1).grow(halo)

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

    def route(self, x: np.ndarray, y: np.ndarray) -> dict[str, np.ndarray]:
        """The points whose nearest pixel lies in each tile's core (:meth:`Tile.contains`), in
        one pass over the points instead of one per tile.

        Returns
        -------
        dict
            Tile key -> indices of its points, ascending (tiles without points left out).
        """
        xi, yi = np.rint(np.asarray(x, np.float64)), np.rint(np.asarray(y, np.float64))
        nrows, ncols = len(self.rows), len(self.cols)
        iy = np.searchsorted(np.r_[0, np.cumsum(self.rows)], yi, side="right") - 1
        ix = np.searchsorted(np.r_[0, np.cumsum(self.cols)], xi, side="right") - 1
        # NaN, and every point past the last edge, lands on index nrows (ncols): outside
        flat = np.where((iy >= 0) & (iy < nrows) & (ix >= 0) & (ix < ncols), iy * ncols + ix, -1)
        order = np.argsort(flat, kind="stable")  # the outside first, then tile by tile, each ascending
        ends = np.cumsum(np.bincount(flat + 1, minlength=nrows * ncols + 1))
        return {t.key: order[ends[k]:ends[k + 1]] for k, t in enumerate(self) if ends[k + 1] > ends[k]}

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


class PointsByRow:
    """Points sorted by row once, for the points inside many windows (:meth:`in_window`)."""

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        self.x = np.asarray(x)
        self.order = np.argsort(np.asarray(y), kind="stable")
        self.rows = np.asarray(y)[self.order]

    def in_window(self, window: Window) -> np.ndarray:
        """Indices (ascending) of the points with ``row0 <= y < row1`` and ``col0 <= x < col1``:
        those of that mask, from the rows in the window only."""
        r0, r1, c0, c1 = window
        a, b = np.searchsorted(self.rows, [r0, r1], side="left")
        candidates = self.order[a:b]
        x = self.x[candidates]
        return np.sort(candidates[(x >= c0) & (x < c1)])
