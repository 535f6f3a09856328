"""Per-pixel status codes of a registration (the ``status`` array of the output store)."""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Status(IntEnum):
    """What the displacement of a base pixel rests on.

    Attributes
    ----------
    OUTSIDE : int
        0: no distorted data at ``p + d(p)`` (outside the overlap or nodata).
    MATCHED : int
        1: dense least-squares match.
    FILLED : int
        2: a short gap of a scan line between matches (a rejected match, no texture), filled
        by interpolation along the line (:mod:`geocoder.quality.postfilter`); in a dense
        field with line fits, then set on its line's fit
        (:func:`geocoder.quality.line_fits.shrink_block`).
    BLUNDER : int
        3: match rejected as a blunder by the post-filter.
    NO_TEXTURE : int
        4: not matched: too little texture.
    MODEL : int
        5: displacement from the global polynomial only (a mosaic's ``status``: the position
        from the source scene's adjusted model, :mod:`geocoder.mosaic.layers`).
    ESTIMATED : int
        6: not matched (no texture or a rejected blunder); the global polynomial plus the
        smooth part along the scan lines and the shift of its scan line, both from the
        line's and all lines' matches (:mod:`geocoder.quality.lines`; in a mosaic, along the
        scene's rows, :mod:`geocoder.mosaic.scanlines`).
    """

    OUTSIDE = 0
    MATCHED = 1
    FILLED = 2
    BLUNDER = 3
    NO_TEXTURE = 4
    MODEL = 5
    ESTIMATED = 6


def legend() -> dict[str, int]:
    """Code table stored with the output as JSON (``status`` attribute ``status_legend``).

    The same table is in the CF attributes ``flag_values`` / ``flag_meanings``
    (:func:`geocoder.conventions.status_attrs`).
    """
    return {s.name.lower(): int(s) for s in Status}


def positioned(status: np.ndarray) -> np.ndarray:
    """Where a dense field gives the position (``MATCHED``, ``FILLED`` or ``ESTIMATED``), elementwise."""
    status = np.asarray(status)
    return (status == Status.MATCHED) | (status == Status.FILLED) | (status == Status.ESTIMATED)
