"""Control and check points through the adjusted models: which points are withheld as check points,
and the residuals of the check points and of every point of the ``control`` CSV."""

from __future__ import annotations

from dataclasses import replace

import numpy as np


def given_residuals(given, models: list, index: dict, checks: list, heights=None) -> list[list]:
    """Every point of the ``control`` CSV: ``[id, scene, residual px, role]``, the residual its
    scene pixel leaves against its map position through the adjusted model (None for a scene
    out of the block), role ``"control"`` or ``"check"`` (withheld from the adjustment)."""
    withheld = {(m.j, float(x), float(y)) for m in checks if m.ground_sigma is not None for x, y in m.b}
    out = []
    for i in range(len(given)):
        k = int(given.scene[i])
        col, row = (float(v) for v in given.pixel[i])
        role = "check" if (k, col, row) in withheld else "control"
        if k not in index:
            out.append([given.ids[i], k, None, role])
            continue
        residual = pixel_residuals(models[index[k]], given.world[i : i + 1], given.pixel[i : i + 1], heights)[0]
        out.append([given.ids[i], k, round(float(residual), 4), role])
    return out


def pixel_residuals(model: tuple, world: np.ndarray, pixel: np.ndarray, heights=None) -> np.ndarray:
    """Distance (scene px) between measured ``pixel`` (n, 2) and where the adjusted ``model``
    (``(model, params)``) puts the map points ``world`` (n, 2), at the DEM's heights (0 without)."""
    e, n = world[:, 0], world[:, 1]
    h = np.zeros(e.size) if heights is None else np.asarray(heights(e, n), dtype=np.float64)
    xy = model[0].project(model[1], np.column_stack([e, n, h]))
    return np.hypot(*(xy - pixel).T)


def withhold(control: list, share: float) -> tuple[list, list]:
    """``control`` split into the points the adjustment uses and every n-th withheld as a check
    (``n = round(1 / share)``; none for ``share = 0``)."""
    if not share:
        return control, []
    n = max(round(1.0 / share), 2)
    used, checks = [], []
    for m in control:
        keep = np.arange(len(m)) % n != n - 1
        for part, sel in ((used, keep), (checks, ~keep)):
            part.append(replace(m, a=m.a[sel], b=m.b[sel], sigma=m.sigma[sel],
                                ground_sigma=None if m.ground_sigma is None else m.ground_sigma[sel]))
    return used, checks


def check_residuals(checks: list, models: list, index: dict, nscenes: int, heights=None) -> tuple[list, list]:
    """Check points per scene and the RMS of their residuals (scene pixels) through the adjusted models."""
    count = [0] * nscenes
    rmse = [float("nan")] * nscenes
    for m in checks:
        if m.j not in index or len(m) == 0:
            continue
        count[m.j] = len(m)
        rmse[m.j] = float(np.sqrt(np.mean(pixel_residuals(models[index[m.j]], m.a, m.b, heights) ** 2)))
    return count, rmse


__all__ = ["check_residuals", "given_residuals", "pixel_residuals", "withhold"]
