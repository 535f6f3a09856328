"""Forward-mode automatic differentiation on numpy arrays ("jets"), vectorised over points.

A :class:`Jet` carries a value array of shape ``S`` and its derivatives with respect to ``k``
seed directions, an array of shape ``S + (k,)``.  Arithmetic, ``sin``, ``cos``, ``sqrt`` and
``arctan2`` propagate the derivatives by the chain rule with numpy broadcasting (a frame-level
scalar of shape ``()`` combines with per-point arrays of shape ``(m,)``), so a model written
once with jets yields its value and its exact (to rounding) Jacobian in one pass, with no
per-point Python.  Plain floats and arrays act as constants.

Used by :mod:`geocoder.adjust.linescanner_jacobian`; pure numpy.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["Jet", "arctan2", "constant", "cos", "cross", "dot", "seed", "sin", "sqrt", "stack", "unit"]


class Jet:
    """A value and its derivatives along ``k`` directions.

    Parameters
    ----------
    v : array_like
        Value, shape ``S``.
    d : array_like
        Derivatives, shape ``S + (k,)`` (or broadcastable to it).
    """

    __slots__ = ("d", "v")
    __array_ufunc__ = None  # ndarray <op> Jet defers to the Jet's reflected operator

    def __init__(self, v: ArrayLike, d: ArrayLike) -> None:
        self.v = np.asarray(v, dtype=np.float64)
        self.d = np.asarray(d, dtype=np.float64)

    def __repr__(self) -> str:
        return f"Jet(shape={self.v.shape}, k={self.d.shape[-1]})"

    # ----------------------------------------------------------------- shape
    def comp(self, i: int) -> Jet:
        """Component ``i`` of the last value axis (e.g. ``x`` of an array of 3-vectors)."""
        return Jet(self.v[..., i], self.d[..., i, :])

    def expand(self) -> Jet:
        """A trailing value axis of length 1 (a per-point scalar that scales 3-vectors)."""
        return Jet(self.v[..., None], self.d[..., None, :])

    def sum_last(self) -> Jet:
        """Sum over the last value axis."""
        return Jet(self.v.sum(axis=-1), self.d.sum(axis=-2))

    # ------------------------------------------------------------ arithmetic
    def __neg__(self) -> Jet:
        return Jet(-self.v, -self.d)

    def __add__(self, o: Jet | ArrayLike) -> Jet:
        if isinstance(o, Jet):
            return Jet(self.v + o.v, self.d + o.d)
        o = np.asarray(o, dtype=np.float64)
        return Jet(self.v + o, np.broadcast_to(self.d, np.broadcast_shapes(self.v.shape, o.shape) + self.d.shape[-1:]))

    __radd__ = __add__

    def __sub__(self, o: Jet | ArrayLike) -> Jet:
        return self + (-o)

    def __rsub__(self, o: ArrayLike) -> Jet:
        return (-self) + o

    def __mul__(self, o: Jet | ArrayLike) -> Jet:
        if isinstance(o, Jet):
            return Jet(self.v * o.v, self.d * o.v[..., None] + self.v[..., None] * o.d)
        o = np.asarray(o, dtype=np.float64)
        return Jet(self.v * o, self.d * o[..., None])

    __rmul__ = __mul__

    def __truediv__(self, o: Jet | ArrayLike) -> Jet:
        if isinstance(o, Jet):
            q = self.v / o.v
            return Jet(q, (self.d - q[..., None] * o.d) / o.v[..., None])
        o = np.asarray(o, dtype=np.float64)
        return Jet(self.v / o, self.d / o[..., None])

    def __rtruediv__(self, o: ArrayLike) -> Jet:
        o = np.asarray(o, dtype=np.float64)
        q = o / self.v
        return Jet(q, -(q / self.v)[..., None] * self.d)


# ------------------------------------------------------------------ constructors
def constant(v: ArrayLike, k: int) -> Jet:
    """A jet with zero derivatives.

    Parameters
    ----------
    v : array_like
        Value.
    k : int
        Number of directions.

    Returns
    -------
    Jet
    """
    v = np.asarray(v, dtype=np.float64)
    return Jet(v, np.zeros(v.shape + (k,)))


def seed(v: ArrayLike, k: int, index: int, scale: float = 1.0) -> Jet:
    """An independent variable: derivative ``scale`` along direction ``index``, zero elsewhere.

    Parameters
    ----------
    v : array_like
        Value (any shape; every element gets the same direction).
    k : int
        Number of directions.
    index : int
        Its direction.
    scale : float
        The derivative (e.g. -1 for a variable entering with a sign flip).

    Returns
    -------
    Jet
    """
    j = constant(v, k)
    j.d[..., index] = scale
    return j


# -------------------------------------------------------------------- functions
def sin(x: Jet) -> Jet:
    """``sin`` of a jet."""
    return Jet(np.sin(x.v), np.cos(x.v)[..., None] * x.d)


def cos(x: Jet) -> Jet:
    """``cos`` of a jet."""
    return Jet(np.cos(x.v), -np.sin(x.v)[..., None] * x.d)


def sqrt(x: Jet) -> Jet:
    """``sqrt`` of a jet (derivative infinite at 0)."""
    r = np.sqrt(x.v)
    return Jet(r, x.d / (2.0 * r)[..., None])


def arctan2(y: Jet, x: Jet) -> Jet:
    """``arctan2(y, x)`` of two jets: derivative ``(x dy - y dx) / (x^2 + y^2)``."""
    r2 = x.v * x.v + y.v * y.v
    return Jet(np.arctan2(y.v, x.v), (x.v[..., None] * y.d - y.v[..., None] * x.d) / r2[..., None])


def stack(parts: Sequence[Jet]) -> Jet:
    """Stack jets of equal value shape along a new last value axis."""
    shape = np.broadcast_shapes(*(p.v.shape for p in parts))
    k = parts[0].d.shape[-1]
    v = np.stack([np.broadcast_to(p.v, shape) for p in parts], axis=-1)
    d = np.stack([np.broadcast_to(p.d, shape + (k,)) for p in parts], axis=-2)
    return Jet(v, d)


def dot(a: Jet, b: Jet) -> Jet:
    """Dot product of arrays of 3-vectors (last value axis)."""
    return (a * b).sum_last()


def cross(a: Jet, b: Jet) -> Jet:
    """Cross product of arrays of 3-vectors (last value axis)."""
    a0, a1, a2 = a.comp(0), a.comp(1), a.comp(2)
    b0, b1, b2 = b.comp(0), b.comp(1), b.comp(2)
    return stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def unit(a: Jet) -> Jet:
    """``a / |a|`` for arrays of 3-vectors."""
    return a / sqrt(dot(a, a)).expand()
