"""A block of overlapping scenes over an orthoimage, each with a known pixel -> ortho mapping.

Every scene sees the ortho through ``T_k`` (scene pixel -> ortho pixel): a rotation and scale
about its centre, a quadratic term (up to a few pixels at the edges), and its own gain, offset
and noise. The scenes form a ``rows x cols`` grid with the given overlap. Truth for the mosaic:
the output pixel ``p`` taken from scene ``k`` is right where ``T_k(model_k(p)) = p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels.resample import sample


@dataclass(frozen=True)
class BlockScene:
    """One scene of a synthetic block: where it lies on the ortho and how it is distorted."""

    row0: float
    col0: float
    size: int
    angle_deg: float
    scale: float
    quadratic_px: float
    gain: float
    offset: float
    turbulence_px: float = 0.0
    turbulence_seed: int = 0

    def to_ortho(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T``: scene pixel -> ortho pixel (pixel centres at integers)."""
        half = self.size / 2
        u, v = np.asarray(x, dtype=np.float64) - half, np.asarray(y, dtype=np.float64) - half
        a = np.deg2rad(self.angle_deg)
        q = self.quadratic_px / half**2
        ox = self.col0 + half + self.scale * (np.cos(a) * u - np.sin(a) * v) + q * u * v
        oy = self.row0 + half + self.scale * (np.sin(a) * u + np.cos(a) * v) + q * u * u
        if self.turbulence_px:
            tx, ty = self.turbulence(np.asarray(y, dtype=np.float64))
            ox, oy = ox + tx, oy + ty
        return ox, oy

    def turbulence(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scan-line turbulence (ortho px) of scene row ``y``: an airborne line scanner's roll
        and pitch, shared by the whole line and changing over tens of lines (three sinusoids
        per axis of periods 15-80 lines and random phases, peak ``turbulence_px``)."""
        rng = np.random.default_rng(self.turbulence_seed)
        periods = rng.uniform(15.0, 80.0, (2, 3))
        phases = rng.uniform(0.0, 2 * np.pi, (2, 3))
        weights = rng.uniform(0.5, 1.0, (2, 3))
        weights *= self.turbulence_px / weights.sum(axis=1, keepdims=True)
        t = [sum(w * np.sin(2 * np.pi * y / p + f) for w, p, f in zip(weights[k], periods[k], phases[k])) for k in (0, 1)]
        return t[0], t[1]


def block_layout(rows: int, cols: int, *, size: int, overlap: tuple[float, float] = (0.2, 0.6),
                 origin: tuple[float, float] = (0.0, 0.0), seed: int = 0) -> list[BlockScene]:
    """A ``rows x cols`` grid of scenes of ``size`` px, seeded distortions.

    ``overlap`` is the (along-track, across-track) overlap as fractions: consecutive scenes of a
    strip (a row) overlap by the first, neighbouring strips by the second (sidelap).
    """
    rng = np.random.default_rng(seed)
    scenes = []
    for r in range(rows):
        for c in range(cols):
            scenes.append(BlockScene(
                row0=origin[0] + r * size * (1.0 - overlap[1]), col0=origin[1] + c * size * (1.0 - overlap[0]), size=size,
                angle_deg=float(rng.uniform(-3, 3)), scale=float(rng.uniform(0.97, 1.03)),
                quadratic_px=float(rng.uniform(-2.5, 2.5)), gain=float(rng.uniform(0.8, 1.25)),
                offset=float(rng.uniform(-10, 10)),
            ))
    return scenes


def render(ortho: np.ndarray, scene: BlockScene, *, noise: float = 0.01, seed: int = 0) -> np.ndarray:
    """The scene's image: the ortho through ``T`` (cubic), gain, offset, noise (fraction of the ortho's std)."""
    ys, xs = np.mgrid[0 : scene.size, 0 : scene.size].astype(np.float64)
    img = sample(np.asarray(ortho, dtype=np.float64), *scene.to_ortho(xs, ys), method="cubic")
    rng = np.random.default_rng(seed)
    return (scene.gain * img + scene.offset + rng.normal(0.0, noise * float(np.nanstd(ortho)), img.shape)).astype(np.float32)
