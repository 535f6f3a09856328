"""The tie-point table: columns of equal length, concatenated across tiles."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np


@dataclass(frozen=True)
class TiePoints:
    """Point pairs between a base and a distorted image (global pixel coordinates).

    Attributes
    ----------
    base_x, base_y : base interest point (pixel centres).
    dist_x, dist_y : its conjugate in the distorted image, refined to sub-pixel.
    weight : a-priori weight of the pair (eq 29), relative.
    rho : correlation coefficient after refinement.
    sigma_x, sigma_y : standard deviation of ``dist_x, dist_y`` from least-squares matching.
    residual_x, residual_y : residual against the global polynomial (NaN until fitted).
    inlier : whether the global robust fit kept the pair.
    """

    base_x: np.ndarray
    base_y: np.ndarray
    dist_x: np.ndarray
    dist_y: np.ndarray
    weight: np.ndarray
    rho: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    residual_x: np.ndarray
    residual_y: np.ndarray
    inlier: np.ndarray

    @classmethod
    def empty(cls) -> TiePoints:
        return cls(**{f.name: np.empty(0, dtype=bool if f.name == "inlier" else np.float64) for f in fields(cls)})

    @classmethod
    def build(cls, **columns) -> TiePoints:
        n = len(columns["base_x"])
        columns.setdefault("residual_x", np.full(n, np.nan))
        columns.setdefault("residual_y", np.full(n, np.nan))
        columns.setdefault("inlier", np.ones(n, dtype=bool))
        return cls(**{k: np.asarray(v) for k, v in columns.items()})

    def __len__(self) -> int:
        return int(self.base_x.size)

    def select(self, mask: np.ndarray) -> TiePoints:
        return TiePoints(**{f.name: getattr(self, f.name)[mask] for f in fields(self)})

    def with_fit(self, residuals: np.ndarray, inlier: np.ndarray) -> TiePoints:
        return replace(self, residual_x=residuals[:, 0], residual_y=residuals[:, 1], inlier=np.asarray(inlier, dtype=bool))

    @staticmethod
    def concatenate(parts: list[TiePoints]) -> TiePoints:
        parts = [p for p in parts if len(p)]
        if not parts:
            return TiePoints.empty()
        joined = TiePoints(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(TiePoints)})
        order = np.lexsort((joined.base_x, joined.base_y))
        return joined.select(order)

    def columns(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}
