"""Per-line estimates (geocoder.quality.lines): corrections from row sums, against hand-made rows."""

import numpy as np
import pytest

from geocoder.quality.lines import LineOptions, combine_sums, line_corrections, line_sums


def _rows(shifts, usable, noise=0.0, sigma=0.05, seed=0):
    """A 2-row-per-shift field: residual = the row's shift (+ noise) where usable."""
    rng = np.random.default_rng(seed)
    h, w = usable.shape
    px = np.zeros((h, w))
    dx = px + np.asarray(shifts)[:, None] + noise * rng.standard_normal((h, w))
    dy = px - np.asarray(shifts)[:, None]
    s = np.full((h, w), sigma)
    return dx, dy, px, px, usable, s, s


def test_rows_with_matches_get_their_mean_and_gaps_are_interpolated_never_extrapolated():
    h, w = 30, 100
    shifts = np.linspace(-1.0, 2.0, h)
    usable = np.zeros((h, w), bool)
    usable[:, 20:80] = True
    usable[[0, 1]] = False            # before the first row with data: nothing
    usable[10:13] = False             # 3 rows: interpolated (max_gap 8)
    usable[15:25] = False             # 10 rows: too long a gap
    usable[29] = False                # after the last: nothing
    sums = line_sums(*_rows(shifts, usable))
    c = line_corrections(sums, min_count=32, max_gap=8)
    own = usable.any(axis=1)
    np.testing.assert_allclose(c.cx[own], shifts[own])
    np.testing.assert_allclose(c.cy[own], -shifts[own])
    np.testing.assert_allclose(c.cx[10:13], shifts[10:13])  # linear in the row here, so exact
    assert np.isnan(c.cx[[0, 1, *range(15, 25), 29]]).all()
    assert (c.first[own] == 20).all() and (c.last[own] == 79).all()
    assert c.own.sum() == own.sum() and not c.own[10:13].any()


def test_blocks_along_a_row_add_up_to_the_whole_row():
    h, w = 6, 90
    usable = np.random.default_rng(1).random((h, w)) < 0.7
    args = _rows(np.arange(h, dtype=float), usable, noise=0.1)
    whole = line_sums(*args)
    parts = np.stack([line_sums(*(a[:, c0:c0 + 30] for a in args), col0=c0) for c0 in (0, 30, 60)], axis=-1)
    np.testing.assert_allclose(combine_sums(parts), whole)


def test_sigma_is_the_spread_beyond_the_matches_own_noise():
    h, w = 4, 2000
    usable = np.ones((h, w), bool)
    # residual noise 0.1 px that the matches' sigma (0.1) fully explains: the line is one shift
    c = line_corrections(line_sums(*_rows(np.zeros(h), usable, noise=0.1, sigma=0.1)), min_count=32)
    assert (c.sx < 0.04).all()  # against 0.1 if the noise were not taken off
    # the same noise with matches claiming 0.02 px: the rest (~0.098 px) is the line's own spread
    c = line_corrections(line_sums(*_rows(np.zeros(h), usable, noise=0.1, sigma=0.02)), min_count=32)
    np.testing.assert_allclose(c.sx, 0.098, atol=0.01)


def test_options_are_checked():
    with pytest.raises(ValueError, match="min_count"):
        LineOptions(min_count=0).validate()
    with pytest.raises(ValueError, match="max_gap"):
        LineOptions(max_gap=-1).validate()
