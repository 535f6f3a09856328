"""The window algebra of :mod:`geocoder.tiles` (``Window``) and the tiles' windows."""

from __future__ import annotations

import numpy as np

from geocoder.tiles import PointsByRow, TileGrid, Window


def test_window_grow_clip_slices():
    w = Window(10, 20, 30, 50)
    assert w.shape == (10, 20) and not w.empty
    assert w.grow(3) == Window(7, 23, 27, 53)
    assert w.grow(0, 5) == (10, 20, 25, 55)  # a tuple: unpacks and compares as one
    assert w.grow(15).clip(30, 60) == Window(0, 30, 15, 60)
    r0, r1, c0, c1 = w.grow(15).clip(30, 60)
    assert (r0, r1, c0, c1) == (0, 30, 15, 60)
    a = np.arange(100 * 100).reshape(100, 100)
    assert np.array_equal(a[w.slices()], a[10:20, 30:50])
    assert np.array_equal(a[5:, 8:][w.slices((5, 8))], a[10:20, 30:50])
    outside = Window(40, 50, 0, 10).clip(30, 60)
    assert outside.empty and outside.shape == (0, 10)


def test_window_around_points_is_the_whole_pixels_that_hold_them():
    rows, cols = np.array([2.2, 7.9, 5.0]), np.array([-1.5, 3.0, 0.25])
    assert Window.around(rows, cols) == Window(2, 9, -2, 4)
    assert Window.around(rows, cols, margin=1.0) == Window(1, 10, -3, 5)


def test_tile_windows_cover_the_grid_once():
    grid = TileGrid.regular(300, 500, 128)
    cover = np.zeros((300, 500), dtype=int)
    for tile in grid:
        cover[tile.window().slices()] += 1
        assert tile.window(8).clip(300, 500) == Window(max(tile.row0 - 8, 0), min(tile.row1 + 8, 300),
                                                      max(tile.col0 - 8, 0), min(tile.col1 + 8, 500))
    assert (cover == 1).all()


def test_route_and_windows_equal_the_per_tile_masks():
    """TileGrid.route and PointsByRow.in_window select what Tile.contains and a window's mask
    select, in the same order: points on tile edges, on the scene's edges, outside it and NaN."""
    rng = np.random.default_rng(5)
    grid = TileGrid.regular(300, 250, 64, min_last=20)
    x = np.r_[rng.uniform(-20, 270, 2000), [0.0, -0.5, -0.51, 63.5, 64.49, 249.49, 249.5, np.nan, 10.0]]
    y = np.r_[rng.uniform(-20, 320, 2000), [0.0, 0.0, 0.0, 10.0, 64.0, 299.0, 299.49, 5.0, np.nan]]
    routed = grid.route(x, y)
    for tile in grid:
        want = np.flatnonzero(tile.contains(x, y))
        assert np.array_equal(routed.get(tile.key, np.empty(0, int)), want), tile
    assert sum(len(i) for i in routed.values()) == sum(tile.contains(x, y).sum() for tile in grid)
    rows = PointsByRow(x, y)
    for window in (Window(0, 64, 0, 64), Window(-30, 10, 200, 400), Window(63, 65, 60, 70), Window(5, 5, 0, 9),
                   Window(299, 400, -1, 250)):
        r0, r1, c0, c1 = window
        want = np.flatnonzero((y >= r0) & (y < r1) & (x >= c0) & (x < c1))
        assert np.array_equal(rows.in_window(window), want), window
