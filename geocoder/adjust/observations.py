"""Observations of a block adjustment: ground points, image measurements and their weights.

* :class:`GroundPoints` -- ground points with an id, a role (``"control"``, ``"check"`` or
  ``"tie"``), the a-priori coordinates, the true ones (equal to the a-priori ones for points
  read from files; the simulator keeps its unperturbed truth there) and the a-priori standard
  deviations.  Coordinates are WGS84 ECEF metres for satellite frames and the local ground
  frame (``X`` east, ``Y`` north, ``Z`` up) for airborne frames.
* :class:`ImageObservations` -- one image measurement of one ground point (``point`` holds the
  ground point *id*) in one frame (``frame`` is the index into the list of frames), with its
  2 x 2 weight matrix in ``(x, y) = (col, row)`` order.  ``kind`` is ``"point"`` or ``"edge"``;
  edge points carry the edge direction ``theta`` (radians from the image ``x`` axis towards
  ``y``; unit direction ``(cos theta, sin theta)`` in ``(x, y)``).
* :func:`point_weight` and :func:`edge_weight` -- the weight matrices of a point and of an edge
  point (Paderes, Mikhail & Foerstner (1984), sec. 3, eqs. 6-7).

The simulator (:mod:`geocoder.simulate.points`) makes these with known truth; the file readers
(:mod:`geocoder.adjust.io`) make them from CSV.  Pure numpy; no file I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "KINDS",
    "ROLES",
    "GroundPoints",
    "ImageObservations",
    "edge_weight",
    "point_weight",
]

#: Roles of ground points.
ROLES = ("control", "check", "tie")
#: Kinds of image observations.
KINDS = ("point", "edge")


def _f64(a: ArrayLike) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class GroundPoints:
    """Ground points: a-priori (perturbed) and true coordinates.

    Attributes
    ----------
    id : ndarray of int64, shape (n,)
        Unique point ids (referenced by :attr:`ImageObservations.point`).
    X, Y, Z : ndarray, shape (n,)
        A-priori coordinates (the truth plus the simulated perturbation);
        ECEF metres for satellite frames, the local frame for airborne ones.
    role : ndarray of str, shape (n,)
        ``"control"``, ``"check"`` or ``"tie"``.
    true_X, true_Y, true_Z : ndarray, shape (n,)
        The unperturbed truth.
    sigma : ndarray, shape (n, 3)
        A-priori standard deviations per axis (m); ``inf`` = unconstrained.
    """

    id: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    Z: np.ndarray
    role: np.ndarray
    true_X: np.ndarray
    true_Y: np.ndarray
    true_Z: np.ndarray
    sigma: np.ndarray

    def __post_init__(self) -> None:
        ids = np.asarray(self.id, dtype=np.int64).reshape(-1)
        n = ids.size
        set_ = lambda k, v: object.__setattr__(self, k, v)
        set_("id", ids)
        for k in ("X", "Y", "Z", "true_X", "true_Y", "true_Z"):
            a = _f64(getattr(self, k)).reshape(-1)
            if a.size != n:
                raise ValueError(f"{k} has {a.size} values, expected {n}")
            set_(k, a)
        role = np.asarray(self.role, dtype=str).reshape(-1)
        if role.size != n or not np.all(np.isin(role, ROLES)):
            raise ValueError(f"role must be {n} values out of {ROLES}")
        set_("role", role)
        sig = np.broadcast_to(_f64(self.sigma), (n, 3)).copy()
        set_("sigma", sig)
        if np.unique(ids).size != n:
            raise ValueError("point ids must be unique")

    def __len__(self) -> int:
        return int(self.id.size)

    @property
    def xyz(self) -> np.ndarray:
        """A-priori coordinates, shape ``(n, 3)``."""
        return np.stack([self.X, self.Y, self.Z], axis=-1)

    @property
    def true_xyz(self) -> np.ndarray:
        """True coordinates, shape ``(n, 3)``."""
        return np.stack([self.true_X, self.true_Y, self.true_Z], axis=-1)

    def subset(self, mask: ArrayLike) -> GroundPoints:
        """The points selected by a boolean mask or an index array."""
        m = np.asarray(mask)
        return GroundPoints(**{f.name: getattr(self, f.name)[m] for f in dataclasses.fields(self)})

    @classmethod
    def concatenate(cls, parts: Sequence[GroundPoints]) -> GroundPoints:
        """Join point sets (ids must stay unique).

        Parameters
        ----------
        parts : sequence of GroundPoints

        Returns
        -------
        GroundPoints
        """
        return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(cls)})


@dataclass(frozen=True, eq=False)
class ImageObservations:
    """Image measurements of ground points.

    Attributes
    ----------
    frame : ndarray of int64, shape (m,)
        Index of the frame (position in the list of scanners).
    point : ndarray of int64, shape (m,)
        Id of the observed ground point (:attr:`GroundPoints.id`).
    row, col : ndarray, shape (m,)
        Measured (perturbed) image coordinates (``y``, ``x``).
    true_row, true_col : ndarray, shape (m,)
        Error-free image coordinates.
    weight : ndarray, shape (m, 2, 2)
        Weight matrix (inverse covariance, px^-2) in ``(x, y) = (col, row)`` order.
    kind : ndarray of str, shape (m,)
        ``"point"`` or ``"edge"``.
    theta : ndarray, shape (m,)
        Edge direction (radians from the ``x`` axis towards ``y``); NaN for points.
    """

    frame: np.ndarray
    point: np.ndarray
    row: np.ndarray
    col: np.ndarray
    true_row: np.ndarray
    true_col: np.ndarray
    weight: np.ndarray
    kind: np.ndarray
    theta: np.ndarray

    def __post_init__(self) -> None:
        frame = np.asarray(self.frame, dtype=np.int64).reshape(-1)
        m = frame.size
        set_ = lambda k, v: object.__setattr__(self, k, v)
        set_("frame", frame)
        set_("point", np.asarray(self.point, dtype=np.int64).reshape(-1))
        for k in ("row", "col", "true_row", "true_col", "theta"):
            set_(k, _f64(getattr(self, k)).reshape(-1))
        set_("kind", np.asarray(self.kind, dtype=str).reshape(-1))
        set_("weight", np.broadcast_to(_f64(self.weight), (m, 2, 2)).copy())
        for k in ("point", "row", "col", "true_row", "true_col", "kind", "theta"):
            if getattr(self, k).size != m:
                raise ValueError(f"{k} has {getattr(self, k).size} values, expected {m}")
        if not np.all(np.isin(self.kind, KINDS)):
            raise ValueError(f"kind must be out of {KINDS}")

    def __len__(self) -> int:
        return int(self.frame.size)

    def subset(self, mask: ArrayLike) -> ImageObservations:
        """The observations selected by a boolean mask or an index array."""
        m = np.asarray(mask)
        return ImageObservations(**{f.name: getattr(self, f.name)[m] for f in dataclasses.fields(self)})

    @classmethod
    def concatenate(cls, parts: Sequence[ImageObservations]) -> ImageObservations:
        """Join observation sets.

        Parameters
        ----------
        parts : sequence of ImageObservations

        Returns
        -------
        ImageObservations
        """
        return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(cls)})



# --------------------------------------------------------------------------- #
# Weights
# --------------------------------------------------------------------------- #
def point_weight(sigma: float) -> np.ndarray:
    """Weight matrix of a point measured with ``sigma`` px per axis.

    Parameters
    ----------
    sigma : float
        Standard deviation (px), > 0.

    Returns
    -------
    ndarray, shape (2, 2)
        ``I / sigma^2``.
    """
    if not sigma > 0:
        raise ValueError("sigma must be > 0")
    return np.eye(2) / float(sigma) ** 2


def edge_weight(theta: ArrayLike, *, sigma_p: float = 0.5, kappa: float = 50.0) -> np.ndarray:
    """Weight matrix of an edge point (seed eqs. 6-7), built directly.

    ``W = R(theta) diag(1 / (kappa sigma_p)^2, 1 / sigma_p^2) R(theta)^T``
    with ``R(theta) = [[cos, -sin], [sin, cos]]`` in ``(x, y)`` order: the
    first rotated axis ``(cos theta, sin theta)`` runs along the edge (weak,
    standard deviation ``kappa * sigma_p``), the second across it (strong,
    ``sigma_p``).  This is the inverse of eq. (7)'s covariance, and stays
    finite (positive semi-definite) as ``kappa -> inf``.

    Parameters
    ----------
    theta : array_like
        Edge direction (radians from the image ``x`` axis towards ``y``).
    sigma_p : float
        Standard deviation across the edge (px).
    kappa : float
        ``sigma_l / sigma_p``; ``inf`` gives zero weight along the edge.

    Returns
    -------
    ndarray, shape ``theta.shape + (2, 2)``
    """
    if not sigma_p > 0 or not kappa > 0:
        raise ValueError("sigma_p and kappa must be > 0")
    th = _f64(theta)
    c, s = np.cos(th), np.sin(th)
    w_l = 1.0 / (kappa * sigma_p) ** 2  # 0 for kappa = inf
    w_p = 1.0 / sigma_p**2
    W = np.empty(th.shape + (2, 2))
    W[..., 0, 0] = w_l * c * c + w_p * s * s
    W[..., 1, 1] = w_l * s * s + w_p * c * c
    W[..., 0, 1] = W[..., 1, 0] = (w_l - w_p) * c * s
    return W
