"""Composition of two displacement fields (registration chains, seed 003 sec. 10).

A field ``d_AB`` on the grid of image A gives, for every pixel ``p`` of A, the position
``q = p + d_AB(p)`` of the same ground point in image B (``d = p_distorted - p_base`` of
a registration with base A and distorted B). A field ``d_BC`` on B's grid does the same
from B into C. Their composition is the field of A into C::

    d_AC(p) = d_AB(p) + d_BC(p + d_AB(p))

with ``d_BC`` interpolated bilinearly between B's pixels. Pure numpy: the caller passes
the window of the second field that the positions fall in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..status import Status

#: Status codes from the best to the worst: a composed pixel takes the worse of its two.
STATUS_ORDER = (Status.MATCHED, Status.FILLED, Status.ESTIMATED, Status.MODEL, Status.NO_TEXTURE, Status.BLUNDER,
                Status.OUTSIDE)

_RANK = np.zeros(256, dtype=np.uint8)
_RANK[:] = len(STATUS_ORDER) - 1  # unknown codes count as outside
for _i, _s in enumerate(STATUS_ORDER):
    _RANK[int(_s)] = _i
_CODE = np.array([int(s) for s in STATUS_ORDER], dtype=np.uint8)


def worse_status(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The worse of two status arrays (uint8 codes of :class:`geocoder.Status`), by :data:`STATUS_ORDER`.

    Parameters
    ----------
    a, b : numpy.ndarray
        Status codes, broadcast together.

    Returns
    -------
    numpy.ndarray
        uint8 codes.
    """
    return _CODE[np.maximum(_RANK[np.asarray(a, dtype=np.uint8)], _RANK[np.asarray(b, dtype=np.uint8)])]


@dataclass(frozen=True)
class FieldBlock:
    """A block of a displacement field on its image's pixel grid.

    Attributes
    ----------
    dx, dy : numpy.ndarray, shape (h, w)
        ``x_next - x``, ``y_next - y`` in pixels; NaN where there is none.
    sigma_x, sigma_y : numpy.ndarray or None
        Standard deviations of ``dx`` and ``dy`` (px); None: zero.
    status : numpy.ndarray or None
        uint8 :class:`geocoder.Status` codes; None: all ``MATCHED`` where ``dx`` is finite.
    correlation : numpy.ndarray or None
        Correlation coefficient of the matches; None: not carried.
    row0, col0 : int
        Position of the block's first pixel on its image's grid.
    """

    dx: np.ndarray
    dy: np.ndarray
    sigma_x: np.ndarray | None = None
    sigma_y: np.ndarray | None = None
    status: np.ndarray | None = None
    correlation: np.ndarray | None = None
    row0: int = 0
    col0: int = 0


@dataclass(frozen=True)
class Composition:
    """The composed field ``d_AC`` on the first field's block, and its propagated covariance.

    Attributes
    ----------
    dx, dy : numpy.ndarray
        ``d_AC`` (float64, px); NaN where the chain breaks.
    var_x, var_y, cov_xy : numpy.ndarray
        First-order covariance of ``d_AC``: ``J C_AB J^T + C_BC`` (px^2).
    status : numpy.ndarray
        uint8: the worse of the two fields' status; ``OUTSIDE`` where the chain breaks.
    correlation : numpy.ndarray or None
        The smaller of the two correlations, when both fields carry one.
    """

    dx: np.ndarray
    dy: np.ndarray
    var_x: np.ndarray
    var_y: np.ndarray
    cov_xy: np.ndarray
    status: np.ndarray
    correlation: np.ndarray | None

    @property
    def sigma_x(self) -> np.ndarray:
        """Standard deviation of ``dx`` (px)."""
        return np.sqrt(self.var_x)

    @property
    def sigma_y(self) -> np.ndarray:
        """Standard deviation of ``dy`` (px)."""
        return np.sqrt(self.var_y)


def _or_zero(a: np.ndarray | None, like: np.ndarray) -> np.ndarray:
    return np.zeros(like.shape) if a is None else np.asarray(a, dtype=np.float64)


def _status(block: FieldBlock) -> np.ndarray:
    if block.status is not None:
        return np.asarray(block.status, dtype=np.uint8)
    return np.where(np.isfinite(block.dx) & np.isfinite(block.dy), np.uint8(Status.MATCHED), np.uint8(Status.OUTSIDE))


def compose_fields(first: FieldBlock, second: FieldBlock) -> Composition:
    """Compose ``first`` (A -> B) with ``second`` (B -> C) into A -> C on ``first``'s block.

    Every pixel ``p`` of the first block goes to ``q = p + d_AB(p)`` on B's grid; the second
    field is interpolated bilinearly there, ``d_AC(p) = d_AB(p) + d_BC(q)``. ``second`` must
    hold every B pixel the positions need (plus one on each side); a position outside it,
    or next to a pixel of it without a displacement, breaks the chain (NaN, ``OUTSIDE``).

    Parameters
    ----------
    first : FieldBlock
        The A -> B field on a block of A (``row0``, ``col0``: its place on A's grid).
    second : FieldBlock
        A window of the B -> C field (``row0``, ``col0``: its place on B's grid).

    Returns
    -------
    Composition
        The A -> C field with its covariance, status and correlation.

    Notes
    -----
    The covariance is propagated to first order (seed 003 sec. 10 couples the two
    "distortion descriptions"; the errors of the two registrations are independent)::

        C_AC = J C_AB J^T + C_BC(q),   J = I + d(d_BC)/dq

    ``J`` is the Jacobian of the B -> C mapping, the gradient of the bilinear interpolant of
    ``d_BC`` in the cell of ``q``; ``C_AB = diag(sigma_x^2, sigma_y^2)`` of the first field
    and ``C_BC`` the bilinear interpolation of the second's variances. The status of the
    second field at ``q`` is the worst of the (up to four) pixels with a non-zero weight.
    """
    h, w = first.dx.shape
    ys, xs = np.mgrid[first.row0 : first.row0 + h, first.col0 : first.col0 + w].astype(np.float64)
    dx1 = np.asarray(first.dx, dtype=np.float64)
    dy1 = np.asarray(first.dy, dtype=np.float64)
    # position on the second field's window
    qx = xs + dx1 - second.col0
    qy = ys + dy1 - second.row0
    h2, w2 = second.dx.shape
    inside = np.isfinite(qx) & np.isfinite(qy) & (qx >= 0) & (qx <= w2 - 1) & (qy >= 0) & (qy <= h2 - 1)
    qx = np.where(inside, qx, 0.0)
    qy = np.where(inside, qy, 0.0)
    j0 = np.clip(np.floor(qx).astype(np.intp), 0, max(w2 - 2, 0))
    i0 = np.clip(np.floor(qy).astype(np.intp), 0, max(h2 - 2, 0))
    fx, fy = qx - j0, qy - i0
    j1, i1 = np.minimum(j0 + 1, w2 - 1), np.minimum(i0 + 1, h2 - 1)
    corners = ((i0, j0, (1 - fx) * (1 - fy)), (i0, j1, fx * (1 - fy)), (i1, j0, (1 - fx) * fy), (i1, j1, fx * fy))

    dx2 = np.asarray(second.dx, dtype=np.float64)
    dy2 = np.asarray(second.dy, dtype=np.float64)
    var2x = _or_zero(second.sigma_x, dx2) ** 2
    var2y = _or_zero(second.sigma_y, dx2) ** 2
    rank2 = _RANK[_status(second)]
    corr2 = None if second.correlation is None else np.asarray(second.correlation, dtype=np.float64)
    broken = ~inside
    rank = np.zeros((h, w), dtype=np.uint8)
    vals = {k: np.zeros((h, w)) for k in ("dx", "dy", "vx", "vy", "corr")}
    corner_dx, corner_dy = [], []
    for i, j, wt in corners:
        use = wt > 0
        cdx, cdy = dx2[i, j], dy2[i, j]
        broken |= use & ~(np.isfinite(cdx) & np.isfinite(cdy))
        rank = np.where(use, np.maximum(rank, rank2[i, j]), rank)
        cdx, cdy = np.where(use, cdx, 0.0), np.where(use, cdy, 0.0)
        corner_dx.append(cdx)
        corner_dy.append(cdy)
        vals["dx"] += wt * cdx
        vals["dy"] += wt * cdy
        vals["vx"] += wt * np.where(use, var2x[i, j], 0.0)
        vals["vy"] += wt * np.where(use, var2y[i, j], 0.0)
        if corr2 is not None:
            vals["corr"] += wt * np.where(use, corr2[i, j], 0.0)
    # gradient of the bilinear interpolant in the cell: the Jacobian of B -> C minus I
    (a00, a01, a10, a11), (b00, b01, b10, b11) = corner_dx, corner_dy
    gxx = (1 - fy) * (a01 - a00) + fy * (a11 - a10)
    gxy = (1 - fx) * (a10 - a00) + fx * (a11 - a01)
    gyx = (1 - fy) * (b01 - b00) + fy * (b11 - b10)
    gyy = (1 - fx) * (b10 - b00) + fx * (b11 - b01)
    j00, j01, j10, j11 = 1 + gxx, gxy, gyx, 1 + gyy
    v1x = _or_zero(first.sigma_x, dx1) ** 2
    v1y = _or_zero(first.sigma_y, dx1) ** 2
    var_x = j00**2 * v1x + j01**2 * v1y + vals["vx"]
    var_y = j10**2 * v1x + j11**2 * v1y + vals["vy"]
    cov_xy = j00 * j10 * v1x + j01 * j11 * v1y

    rank = np.maximum(rank, _RANK[_status(first)])
    broken |= rank == _RANK[int(Status.OUTSIDE)]
    status = np.where(broken, np.uint8(Status.OUTSIDE), _CODE[rank]).astype(np.uint8)
    nan = np.float64(np.nan)
    correlation = None
    if corr2 is not None and first.correlation is not None:
        correlation = np.where(broken, nan, np.fmin(np.asarray(first.correlation, dtype=np.float64), vals["corr"]))
    return Composition(
        dx=np.where(broken, nan, dx1 + vals["dx"]),
        dy=np.where(broken, nan, dy1 + vals["dy"]),
        var_x=np.where(broken, nan, var_x),
        var_y=np.where(broken, nan, var_y),
        cov_xy=np.where(broken, nan, cov_xy),
        status=status,
        correlation=correlation,
    )


def field_window(first: FieldBlock, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """The window ``(row0, row1, col0, col1)`` of the second field that :func:`compose_fields` needs.

    Parameters
    ----------
    first : FieldBlock
        The A -> B block.
    shape : tuple of int
        ``(H, W)`` of B's grid.

    Returns
    -------
    tuple of int or None
        Half-open bounds clipped to B's grid, holding every bilinear neighbour of the
        positions ``p + d_AB(p)``; None when no position lands on B's grid.
    """
    h, w = first.dx.shape
    ys, xs = np.mgrid[first.row0 : first.row0 + h, first.col0 : first.col0 + w].astype(np.float64)
    qx = xs + np.asarray(first.dx, dtype=np.float64)
    qy = ys + np.asarray(first.dy, dtype=np.float64)
    H, W = shape
    ok = np.isfinite(qx) & np.isfinite(qy) & (qx >= 0) & (qx <= W - 1) & (qy >= 0) & (qy <= H - 1)
    if not ok.any():
        return None
    r0 = max(int(np.floor(qy[ok].min())) - 1, 0)
    r1 = min(int(np.floor(qy[ok].max())) + 3, H)
    c0 = max(int(np.floor(qx[ok].min())) - 1, 0)
    c1 = min(int(np.floor(qx[ok].max())) + 3, W)
    return r0, r1, c0, c1
