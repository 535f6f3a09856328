"""What the block adjustment needs from a sensor model, and the one numeric Jacobian.

A sensor model maps ground coordinates (ECEF metres for the satellite models, map coordinates
for the mosaic's :class:`~geocoder.adjust.models.MapPolynomial`; shape ``(m, 3)``) to image
coordinates ``(x = column, y = row)`` (shape ``(m, 2)``; pixel centres at integers, see
``CONVENTIONS.md``) through a parameter vector.  :class:`SensorModel` is the protocol the
solver (:func:`geocoder.adjust.solver.adjust`) consumes; the models of
:mod:`geocoder.adjust.models` also offer ``initial_params()``, ``param_steps`` and
``ground_step``.

:func:`central_difference` is the central-difference Jacobian every model without analytic
derivatives uses (vectorised over the points, looping only over the differentiated
components); :func:`numeric_jacobians` applies it to a whole model.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["SensorModel", "as_ground", "as_params", "central_difference", "numeric_jacobians"]


@runtime_checkable
class SensorModel(Protocol):
    """What the block-adjustment solver needs from a sensor model (one instance per frame, or shared).

    Attributes
    ----------
    n_params : int
        Length of the parameter vector of one frame.
    """

    n_params: int

    def project(self, params: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Image coordinates of ground points.

        Parameters
        ----------
        params : ndarray, shape (n_params,)
            The frame's parameters.
        ground : ndarray, shape (m, 3)
            Ground coordinates (ECEF metres for the satellite models).

        Returns
        -------
        ndarray, shape (m, 2)
            ``(x = col, y = row)``.
        """
        ...

    def jacobians(self, params: np.ndarray, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of :meth:`project` with respect to the parameters and the ground points.

        Parameters
        ----------
        params : ndarray, shape (n_params,)
            The frame's parameters.
        ground : ndarray, shape (m, 3)
            Ground coordinates.

        Returns
        -------
        J_params : ndarray, shape (m, 2, n_params)
            ``d image / d params``.
        J_ground : ndarray, shape (m, 2, 3)
            ``d image / d ground``.
        """
        ...


def as_ground(ground: ArrayLike) -> np.ndarray:
    """Ground coordinates as a float64 ``(m, 3)`` array.

    Parameters
    ----------
    ground : array_like
        Ground coordinates.

    Returns
    -------
    ndarray, shape (m, 3)

    Raises
    ------
    ValueError
        If the shape is not ``(m, 3)``.
    """
    g = np.asarray(ground, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != 3:
        raise ValueError(f"ground must have shape (m, 3), got {g.shape}")
    return g


def as_params(params: ArrayLike, n: int) -> np.ndarray:
    """A parameter vector as a float64 ``(n,)`` array.

    Parameters
    ----------
    params : array_like
        Parameter vector.
    n : int
        Expected length.

    Returns
    -------
    ndarray, shape (n,)

    Raises
    ------
    ValueError
        If the shape is not ``(n,)``.
    """
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (n,):
        raise ValueError(f"params must have shape ({n},), got {p.shape}")
    return p


def central_difference(f: Callable[[np.ndarray], np.ndarray], x0: ArrayLike, steps: ArrayLike) -> np.ndarray:
    """Central-difference Jacobian of ``f`` with respect to the last axis of ``x0``.

    Parameters
    ----------
    f : callable
        ``f(x) -> (m, d)`` (``d = 2`` for image coordinates); ``x`` has the shape of ``x0``.
    x0 : array_like, shape ``(..., k)``
        Either a shared parameter vector ``(k,)`` or per-point variables ``(m, k)`` (e.g.
        ground coordinates): component ``j`` is perturbed in all points at once, which is
        valid because the points are independent.
    steps : array_like, shape ``(k,)``
        Half-step per component.

    Returns
    -------
    ndarray, shape ``(m, d, k)``
        ``(f(x0 + h_j e_j) - f(x0 - h_j e_j)) / (2 h_j)`` for each ``j``.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    steps = np.broadcast_to(np.asarray(steps, dtype=np.float64), (x0.shape[-1],))
    if steps.size == 0:
        return np.asarray(f(x0), dtype=np.float64)[..., None][..., :0]
    cols = []
    for j, h in enumerate(steps):
        xp = x0.copy()
        xm = x0.copy()
        xp[..., j] += h
        xm[..., j] -= h
        cols.append((f(xp) - f(xm)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def numeric_jacobians(
    model: SensorModel,
    params: np.ndarray,
    ground: np.ndarray,
    *,
    step_params: np.ndarray | float | None = None,
    step_ground: np.ndarray | float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference Jacobians of ``model.project``, vectorised over the points.

    Parameters
    ----------
    model : SensorModel
        Only ``project`` is used, so a model may implement ``jacobians`` with this function.
    params : ndarray, shape (n,)
        Parameters at which to differentiate.
    ground : ndarray, shape (m, 3)
        Ground points.
    step_params : float or ndarray, shape (n,), optional
        Half-steps for the parameters; default ``1e-6 * max(1, |params|)``.
    step_ground : float or ndarray, shape (3,), optional
        Half-steps for the ground coordinates (ground units), default 1.0.

    Returns
    -------
    jp : ndarray, shape (m, 2, n)
        Derivatives with respect to the parameters.
    jg : ndarray, shape (m, 2, 3)
        Derivatives with respect to the ground coordinates.
    """
    params = np.asarray(params, dtype=np.float64)
    ground = np.asarray(ground, dtype=np.float64)
    if step_params is None:
        hp = 1e-6 * np.maximum(1.0, np.abs(params))
    else:
        hp = np.broadcast_to(np.asarray(step_params, dtype=np.float64), (params.size,))
    jp = central_difference(lambda p: model.project(p, ground), params, hp)
    jg = central_difference(lambda g: model.project(params, g), ground, step_ground)
    return jp, jg
