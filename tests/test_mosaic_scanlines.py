"""Per-scan-line estimates of a block scene's field (geocoder.mosaic.scanlines), against a known field."""

from __future__ import annotations

import numpy as np

from geocoder.mosaic.scanlines import combine_line_sums, line_estimates, line_table, scene_line_sums
from geocoder.status import Status

SHAPE = (150, 220)  # scene rows, columns
ANGLE = np.deg2rad(2.5)


def _case(seed: int = 0):
    """A scene rotated on a reference grid; the model misses a smooth bend and every row's shift."""
    rng = np.random.default_rng(seed)
    ry, rx = np.mgrid[-10:170, -20:250].astype(np.float64)
    c, s = np.cos(ANGLE), np.sin(ANGLE)
    # the model: reference pixel -> scene pixel (a rotation about (100, 70))
    mx = 100 + c * (rx - 100) + s * (ry - 70)
    my = 70 - s * (rx - 100) + c * (ry - 70)
    row = np.rint(my).astype(int)
    u = (mx - (SHAPE[1] - 1) / 2) / (SHAPE[1] / 2)
    v = (my - (SHAPE[0] - 1) / 2) / (SHAPE[0] / 2)
    lines = np.arange(-20, SHAPE[0] + 20)[None, :]
    phase = rng.uniform(0, 2 * np.pi, (2, 2, 1))
    shift = 0.9 * np.sin(2 * np.pi * lines / 37 + phase[:, 0]) + 0.4 * np.sin(2 * np.pi * lines / 23 + phase[:, 1])  # roll, pitch
    bend_x = 0.8 * u**2 - 0.5 * u * v + 0.3 * u
    bend_y = -0.6 * u**2 + 0.4 * u * v
    at = np.clip(row, -20, SHAPE[0] + 19) + 20
    tx = mx + bend_x + shift[0][at]
    ty = my + bend_y + shift[1][at]
    # matches: both ends of every row (the neighbours' overlaps) and whole rows in the lower half
    inside = (mx > -0.5) & (mx < SHAPE[1] - 0.5) & (my > -0.5) & (my < SHAPE[0] - 0.5)
    matched = inside & ((mx < 50) | (mx > 180) | (my > 90))
    matched &= ~((my > 40) & (my < 46))  # a few rows without any match: interpolated across
    noise = rng.normal(0.0, 0.03, (2, *rx.shape))
    status = np.where(matched, Status.MATCHED, np.where(inside, Status.NO_TEXTURE, Status.OUTSIDE)).astype(np.uint8)
    dx = np.where(matched, tx - rx + noise[0], np.nan)
    dy = np.where(matched, ty - ry + noise[1], np.nan)
    return dict(dx=dx, dy=dy, status=status, pdx=mx - rx, pdy=my - ry, truth=(tx - rx, ty - ry), inside=inside,
                row0=-10, col0=-20)


def _table(case, bands: int = 3):
    """The scene's table from ``bands`` row bands, as the graph adds them up."""
    edges = np.linspace(0, case["dx"].shape[0], bands + 1).astype(int)
    parts = [scene_line_sums(*(case[k][a:b] for k in ("dx", "dy", "status", "pdx", "pdy")),
                             row0=case["row0"] + a, col0=case["col0"], shape=SHAPE) for a, b in zip(edges[:-1], edges[1:])]
    return line_table(combine_line_sums(np.stack(parts, axis=-1)), min_count=16, max_gap=8, end_rows=8)


def test_rows_shift_and_smooth_bend_are_recovered_where_nothing_matched():
    case = _case()
    out = line_estimates(*(case[k] for k in ("dx", "dy", "status", "pdx", "pdy")), _table(case),
                         row0=case["row0"], col0=case["col0"], shape=SHAPE)
    dx, dy, status = out
    est = status == Status.ESTIMATED
    holes = case["inside"] & (case["status"] == Status.NO_TEXTURE)
    # every unmatched pixel of the scene is estimated, nothing outside it, no match touched
    assert est.sum() == holes.sum() and not (est & ~holes).any()
    matched = case["status"] == Status.MATCHED
    np.testing.assert_array_equal(dx[matched], case["dx"][matched].astype(np.float32))
    ex, ey = dx[est] - case["truth"][0][est], dy[est] - case["truth"][1][est]
    rmse = float(np.sqrt(np.mean(ex**2 + ey**2)))
    assert rmse < 0.05, rmse
    # the model alone misses each row's shift and the bend by about a pixel
    mx, my = case["pdx"][est] - case["truth"][0][est], case["pdy"][est] - case["truth"][1][est]
    assert np.sqrt(np.mean(mx**2 + my**2)) > 0.7


def test_the_row_bands_add_up_to_the_whole():
    case = _case(1)
    np.testing.assert_allclose(_table(case, bands=1), _table(case, bands=5), rtol=1e-9, atol=1e-9)


def test_rows_far_from_any_match_are_left_alone():
    case = _case(2)
    far = case["pdy"] + np.arange(case["row0"], case["row0"] + case["dx"].shape[0])[:, None] < 60
    for k in ("dx", "dy"):
        case[k] = np.where(far, np.nan, case[k])
    case["status"] = np.where(far & (case["status"] == Status.MATCHED), Status.NO_TEXTURE, case["status"]).astype(np.uint8)
    dx, _, status = line_estimates(*(case[k] for k in ("dx", "dy", "status", "pdx", "pdy")), _table(case),
                                   row0=case["row0"], col0=case["col0"], shape=SHAPE)
    row = np.rint(case["pdy"] + np.arange(case["row0"], case["row0"] + case["dx"].shape[0])[:, None])
    # the first rows with matches pass theirs to at most 8 rows before them (a template's half-height)
    assert not (status[row < 60 - 8 - 1] == Status.ESTIMATED).any()
    assert (status[(row >= 60) & case["inside"]] == Status.ESTIMATED).any()
