"""Ground control points measured by hand: a CSV file -> control observations of the block.

The file has a header line and one point per line. Required columns:

``scene``
    The scene the point was measured in: its 0-based index in the list of scenes, or its
    file name (the last part of its path, e.g. ``scene3.tif``).
``col``, ``row``
    The point's pixel position in that scene, pixel centres at integers (the centre of the
    top-left pixel is ``col = 0, row = 0``; :mod:`geocoder.geometry`).
``x``, ``y``
    Its map coordinates in the reference's CRS (easting, northing).

Optional columns: ``sigma``, the standard deviation of ``x`` and ``y`` (map units; default
:data:`DEFAULT_SIGMA_PX` reference pixels), and ``id``, a name reported with the point. Other
columns are ignored. Every point becomes a control point of the block adjustment exactly as a
reference match does (:class:`~geocoder.mosaic.block.Matches` with ``i = -1``): a ground point
of known map position with the prior covariance ``sigma^2 I``, observed in its scene with the
pixel precision :data:`PIXEL_SIGMA`.
"""

from __future__ import annotations

import csv
import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .block import Matches

__all__ = ["ControlPoints", "DEFAULT_SIGMA_PX", "PIXEL_SIGMA", "read_control"]

#: Default standard deviation of a point's map coordinates, in pixels of the reference.
DEFAULT_SIGMA_PX = 0.5
#: Standard deviation (scene pixels) of a point's position measured by hand in its scene.
PIXEL_SIGMA = 0.3
REQUIRED = ("scene", "col", "row", "x", "y")


@dataclass(frozen=True)
class ControlPoints:
    """The points of a control CSV, one row per point.

    Attributes
    ----------
    path : str
        The file.
    scene : ndarray of int, shape (n,)
        0-based scene index of every point.
    pixel : ndarray, shape (n, 2)
        ``col, row`` in its scene.
    world : ndarray, shape (n, 2)
        ``x, y`` map coordinates (the reference's CRS).
    sigma : ndarray, shape (n,)
        Standard deviation of ``x`` and ``y`` (map units).
    ids : list of str
        The ``id`` column, or the line numbers.
    digest : str
        SHA-256 of the file's bytes (the job key).
    """

    path: str
    scene: np.ndarray
    pixel: np.ndarray
    world: np.ndarray
    sigma: np.ndarray
    ids: list[str]
    digest: str

    def __len__(self) -> int:
        return int(self.scene.size)

    def matches(self, scenes: int) -> list[Matches]:
        """One :class:`~geocoder.mosaic.block.Matches` of control points per scene that has points.

        Parameters
        ----------
        scenes : int
            Number of scenes.

        Returns
        -------
        list of Matches
            ``i = -1``, ``a`` the map coordinates, ``b`` the scene pixels, ``sigma`` the
            pixel precision :data:`PIXEL_SIGMA`, ``ground_sigma`` the map coordinates'.
        """
        out = []
        for k in range(scenes):
            sel = self.scene == k
            if sel.any():
                out.append(Matches(-1, k, self.world[sel], self.pixel[sel], np.full((int(sel.sum()), 2), PIXEL_SIGMA),
                                   ground_sigma=self.sigma[sel]))
        return out


def _scene_index(value: str, names: list[str]) -> int | None:
    """A ``scene`` cell as a 0-based index: a number, or a scene's file name."""
    try:
        k = int(value)
    except ValueError:
        hits = [n for n, name in enumerate(names) if name == value]
        return hits[0] if len(hits) == 1 else None
    return k if 0 <= k < len(names) else None


def _number(path: str, line: int, column: str, value: str) -> float:
    try:
        v = float(value)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise InputError(path, f"line {line}, column {column!r}: {value!r} is not a finite number")
    return v


def read_control(path: str | os.PathLike, scenes: list, shapes: list[tuple[int, int]], *,
                 default_sigma: float) -> ControlPoints:
    """Read and check a control CSV (the format is this module's docstring).

    Parameters
    ----------
    path : str or PathLike
        The CSV file.
    scenes : list of str or PathLike
        The scenes, in the block's order (their file names may name them in ``scene``).
    shapes : list of (rows, cols)
        Their sizes: a point must lie inside its scene (within half a pixel of the outermost
        pixel centres).
    default_sigma : float
        ``sigma`` of the points that give none (map units).

    Returns
    -------
    ControlPoints

    Raises
    ------
    InputError
        Naming the file, and the line and column: a missing column, a value that is not a
        finite number or not a positive ``sigma``, a scene that does not exist, a point
        outside its scene, or no points at all.
    """
    path = os.fspath(path)
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read the control points: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(path, "is not a UTF-8 text (CSV) file") from None
    reader = csv.DictReader(text.splitlines())
    header = [h.strip() for h in (reader.fieldnames or [])]
    reader.fieldnames = header
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise InputError(path, f"line 1: missing column(s) {', '.join(missing)} (the header must name "
                               f"{', '.join(REQUIRED)}; optional sigma, id), found {', '.join(header) or 'none'}")
    names = [Path(os.fspath(s)).name for s in scenes]
    rows = []
    for rec in reader:
        line = reader.line_num
        if not any((v or "").strip() for v in rec.values() if isinstance(v, str)):
            continue  # a blank line
        cell = {c: (rec.get(c) or "").strip() for c in header}
        k = _scene_index(cell["scene"], names)
        if k is None:
            raise InputError(path, f"line {line}, column 'scene': {cell['scene']!r} is not a scene (0..{len(names) - 1} "
                                   f"or one of the scenes' unique file names)")
        col, row, x, y = (_number(path, line, c, cell[c]) for c in ("col", "row", "x", "y"))
        h, w = shapes[k]
        if not (-0.5 <= col <= w - 0.5 and -0.5 <= row <= h - 0.5):
            raise InputError(path, f"line {line}, columns 'col', 'row': ({col:g}, {row:g}) is outside scene {k} "
                                   f"({names[k]}: {w} x {h} px, pixel centres 0..{w - 1}, 0..{h - 1})")
        sigma = _number(path, line, "sigma", cell["sigma"]) if cell.get("sigma") else default_sigma
        if sigma <= 0:
            raise InputError(path, f"line {line}, column 'sigma': {sigma:g} is not positive")
        rows.append((k, col, row, x, y, sigma, cell.get("id") or str(line)))
    if not rows:
        raise InputError(path, "has no control points (a header line and one point per line)")
    k, col, row, x, y, sigma, ids = zip(*rows)
    return ControlPoints(path=path, scene=np.array(k, dtype=np.int64), pixel=np.column_stack([col, row]).astype(np.float64),
                         world=np.column_stack([x, y]).astype(np.float64), sigma=np.array(sigma, dtype=np.float64),
                         ids=list(ids), digest=hashlib.sha256(raw).hexdigest())
