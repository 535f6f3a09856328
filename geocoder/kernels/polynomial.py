"""2-D polynomial mappings between pixel frames (seed 000 eqs 12-13, seed 003 sec. 7).

A :class:`PolyMap` maps base pixel coordinates to distorted pixel coordinates. Monomials are
taken in normalised coordinates ``u = (x - cx) / s``, ``v = (y - cy) / s`` so that the
normal equations stay well conditioned for images of any size.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .robust import RobustFit, robust_fit


def exponents(order: int) -> list[tuple[int, int]]:
    """Monomial exponents ``(i, j)`` of ``u**i * v**j`` with ``i + j <= order``, by degree."""
    if not 1 <= order <= 3:
        raise ValueError(f"polynomial order must be 1, 2 or 3, got {order}")
    return [(d - j, j) for d in range(order + 1) for j in range(d + 1)]


def design(u: np.ndarray, v: np.ndarray, order: int) -> np.ndarray:
    """Design matrix, shape (n, m), of the monomials of :func:`exponents`."""
    u = np.asarray(u, dtype=np.float64).ravel()
    v = np.asarray(v, dtype=np.float64).ravel()
    return np.stack([u**i * v**j for i, j in exponents(order)], axis=1)


@dataclass(frozen=True)
class PolyMap:
    """Polynomial ``(x, y) -> (x', y')`` of order 1 (affine), 2 (quadratic) or 3.

    Attributes
    ----------
    coef : ndarray, shape (m, 2)
        Coefficients of the monomials for x' and y'.
    order : int
    centre : (cx, cy)
    scale : float
    """

    coef: np.ndarray
    order: int
    centre: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0
    fit_info: RobustFit | None = field(default=None, compare=False, repr=False)

    def _uv(self, x, y):
        return (
            (np.asarray(x, dtype=np.float64) - self.centre[0]) / self.scale,
            (np.asarray(y, dtype=np.float64) - self.centre[1]) / self.scale,
        )

    def __call__(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map points; returns arrays of the shape of ``x``."""
        x = np.asarray(x, dtype=np.float64)
        u, v = self._uv(x, y)
        out = design(u, v, self.order) @ self.coef
        return out[:, 0].reshape(x.shape), out[:, 1].reshape(x.shape)

    def jacobian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Derivatives ``d(x', y') / d(x, y)``, shape (*x.shape, 2, 2)."""
        x = np.asarray(x, dtype=np.float64)
        u, v = self._uv(x, y)
        u, v = u.ravel(), v.ravel()
        du = np.zeros((u.size, len(self.coef)))
        dv = np.zeros_like(du)
        for k, (i, j) in enumerate(exponents(self.order)):
            if i:
                du[:, k] = i * u ** (i - 1) * v**j
            if j:
                dv[:, k] = j * u**i * v ** (j - 1)
        jac = np.stack([du @ self.coef, dv @ self.coef], axis=-1) / self.scale
        return jac.reshape(*x.shape, 2, 2)

    @classmethod
    def from_affine(cls, matrix: np.ndarray) -> PolyMap:
        """Order-1 map from a 2x3 matrix ``[[a, b, c], [d, e, f]]`` (x' = a x + b y + c)."""
        m = np.asarray(matrix, dtype=np.float64)
        coef = np.array([[m[0, 2], m[1, 2]], [m[0, 0], m[1, 0]], [m[0, 1], m[1, 1]]])
        return cls(coef=coef, order=1)

    def to_order(self, order: int) -> PolyMap:
        """The same mapping expressed with monomials up to a higher ``order``."""
        if order < self.order:
            raise ValueError("cannot lower the order of a polynomial map exactly")
        new = np.zeros((len(exponents(order)), 2))
        index = {e: k for k, e in enumerate(exponents(order))}
        for k, e in enumerate(exponents(self.order)):
            new[index[e]] = self.coef[k]
        return PolyMap(new, order, self.centre, self.scale)

    def recentred(self, centre: tuple[float, float], scale: float) -> PolyMap:
        """The same mapping with other normalisation constants (refit on a grid; exact)."""
        g = np.linspace(-1.0, 1.0, self.order + 3)
        gu, gv = np.meshgrid(g, g)
        x = gu.ravel() * scale + centre[0]
        y = gv.ravel() * scale + centre[1]
        xp, yp = self(x, y)
        coef = np.linalg.lstsq(design(gu, gv, self.order), np.stack([xp, yp], 1), rcond=None)[0]
        return PolyMap(coef, self.order, centre, scale)

    def to_dict(self) -> dict:
        """JSON-able description (for store attributes)."""
        return {
            "order": self.order,
            "centre": list(self.centre),
            "scale": self.scale,
            "coef_x": self.coef[:, 0].tolist(),
            "coef_y": self.coef[:, 1].tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> PolyMap:
        coef = np.stack([np.asarray(d["coef_x"]), np.asarray(d["coef_y"])], axis=1)
        return cls(coef, int(d["order"]), tuple(d["centre"]), float(d["scale"]))


def fit_polymap(
    x: np.ndarray,
    y: np.ndarray,
    xp: np.ndarray,
    yp: np.ndarray,
    *,
    order: int = 2,
    weights: np.ndarray | None = None,
    robust: bool = True,
    **robust_options,
) -> PolyMap:
    """Fit ``(x, y) -> (xp, yp)``, robustly (eq 20b then 22b) unless ``robust=False``.

    The fit's :class:`~geocoder.kernels.robust.RobustFit` is kept in ``fit_info`` (weights
    0 mark rejected points, residuals in the target frame).
    """
    x, y, xp, yp = (np.asarray(a, dtype=np.float64).ravel() for a in (x, y, xp, yp))
    centre = (float((x.min() + x.max()) / 2), float((y.min() + y.max()) / 2))
    scale = float(max(x.max() - x.min(), y.max() - y.min(), 1.0) / 2)
    basis = design((x - centre[0]) / scale, (y - centre[1]) / scale, order)
    obs = np.stack([xp, yp], axis=1)
    if robust:
        info = robust_fit(basis, obs, weights, **robust_options)
    else:
        w = np.ones(x.size) if weights is None else np.asarray(weights, dtype=np.float64)
        sw = np.sqrt(w)[:, None]
        coef = np.linalg.lstsq(basis * sw, obs * sw, rcond=None)[0]
        res = obs - basis @ coef
        dof = max(2 * x.size - 2 * basis.shape[1], 1)
        info = RobustFit(coef, w, res, float(np.sqrt((w[:, None] * res**2).sum() / dof)), 1, True, "direct")
    return PolyMap(info.coef, order, centre, scale, info)
