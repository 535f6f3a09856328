"""Tests of geocoder.quality.postfilter (scan-line blunder removal and hole filling)."""

from __future__ import annotations

import numpy as np
import pytest

from geocoder.quality.postfilter import PostFilterOptions, halo, postfilter
from geocoder.quality.postfilter_reference import postfilter_reference
from geocoder.status import Status

OUT, OK, FILLED, BLUNDER, NOTEX, MODEL = (np.uint8(s) for s in (Status.OUTSIDE, Status.MATCHED, Status.FILLED, Status.BLUNDER, Status.NO_TEXTURE, Status.MODEL))


def _smooth(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free field: linear along the rows, smooth across them."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return 3.0 + 0.01 * x + 1.5 * np.sin(y / 20.0), -1.0 + 0.004 * x + 0.8 * np.cos(y / 13.0)


def _quadratic(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free field, quadratic in x along every row."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return (
        2.0 + 0.03 * x - 2e-4 * (x - 150.0) ** 2 + 0.5 * np.sin(y / 7.0),
        -1.0 - 0.01 * x + 1e-4 * (x - 100.0) ** 2 + 0.3 * np.cos(y / 5.0),
    )


def _noisy(tx: np.ndarray, ty: np.ndarray, sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (
        (tx + rng.normal(0.0, sigma, tx.shape)).astype(np.float32),
        (ty + rng.normal(0.0, sigma, ty.shape)).astype(np.float32),
    )


def _inject_blunders(dx, dy, status, fraction: float, seed: int, *, gap: int = 0) -> np.ndarray:
    """Runs of 1-3 px with one offset of 2-10 px each, covering about ``fraction`` of the pixels.

    With ``gap > 0`` the runs are isolated: at least ``gap`` good pixels between two runs
    and between a run and a row end.  (A running median breaks down when half of its
    window is bad, e.g. two 3 px runs 1 px apart, or a run at a row end where the window
    is one-sided; without ``gap`` such clusters occur.)
    """
    rng = np.random.default_rng(seed)
    ny, nx = status.shape
    bad = np.zeros(status.shape, dtype=bool)
    if gap > 0:
        period = 2.0 / fraction  # mean run length is 2
        runs = []
        for r in range(ny):  # one iteration per run
            c = gap + int(rng.integers(0, period))
            while True:
                n = int(rng.integers(1, 4))
                if c + n + gap > nx:
                    break
                runs.append((r, c, n))
                c += n + gap + int(rng.geometric(1.0 / (period - 2 - gap)))
        rows, starts, lengths = np.array(runs).T
    else:
        n_runs = int(fraction * status.size / 2.0)
        rows, starts, lengths = rng.integers(0, ny, n_runs), rng.integers(0, nx, n_runs), rng.integers(1, 4, n_runs)
    size = rng.uniform(2.0, 10.0, rows.size)
    angle = rng.uniform(0.0, 2.0 * np.pi, rows.size)
    for r, c, n, s, a in zip(rows, starts, lengths, size, angle):  # one iteration per run
        cols = slice(c, min(c + n, nx))
        dx[r, cols] += np.float32(s * np.cos(a))
        dy[r, cols] += np.float32(s * np.sin(a))
        bad[r, cols] = True
    return bad


def _tiled(dx, dy, status, options, *, width: int = 64, depth: int | None = None, pad_outside: bool = False):
    """Post-filter column tiles of ``width`` with ``depth`` extra columns each side, cropped back.

    At the image border the tile is either cut (dask ``boundary="none"``) or padded with
    ``OUTSIDE`` pixels.
    """
    depth = halo(options) if depth is None else depth
    nx = status.shape[1]
    out = (np.empty_like(dx), np.empty_like(dy), np.empty_like(status))
    for c0 in range(0, nx, width):
        c1 = min(c0 + width, nx)
        a, b = max(c0 - depth, 0), min(c1 + depth, nx)
        tx, ty, ts = dx[:, a:b], dy[:, a:b], status[:, a:b]
        left, right = c0 - a, b - c1
        if pad_outside:
            pl, pr = depth - left, depth - right
            tx = np.pad(tx, ((0, 0), (pl, pr)), constant_values=np.nan)
            ty = np.pad(ty, ((0, 0), (pl, pr)), constant_values=np.nan)
            ts = np.pad(ts, ((0, 0), (pl, pr)), constant_values=OUT)
            left, right = depth, depth
        res = postfilter(tx, ty, ts, options=options)
        for o, r in zip(out, res):
            o[:, c0:c1] = r[:, left : r.shape[1] - right]
    return out


def _assert_same(a, b) -> None:
    np.testing.assert_array_equal(a[2], b[2])
    assert np.array_equal(a[0], b[0], equal_nan=True)
    assert np.array_equal(a[1], b[1], equal_nan=True)


def _mixed_field(shape, seed: int):
    """Noisy smooth field with blunders, holes of every length, OUTSIDE and MODEL runs."""
    rng = np.random.default_rng(seed)
    dx, dy = _noisy(*_smooth(shape), 0.05, seed)
    status = np.full(shape, OK)
    _inject_blunders(dx, dy, status, 0.03, seed + 1)
    for code, n_runs, max_len in ((NOTEX, 0.012, 45), (OUT, 0.002, 8), (MODEL, 0.002, 8)):
        k = int(n_runs * status.size)
        rows, starts, lengths = rng.integers(0, shape[0], k), rng.integers(0, shape[1], k), rng.integers(1, max_len, k)
        for r, c, n in zip(rows, starts, lengths):
            status[r, c : c + n] = code
    unmatched = status != OK
    dx[unmatched & (status != MODEL)] = np.nan
    dy[unmatched & (status != MODEL)] = np.nan
    return dx, dy, status


# --------------------------------------------------------------------------


def test_smooth_field_is_left_alone():
    tx, ty = _smooth((128, 512))
    dx, dy = _noisy(tx, ty, 0.02, seed=0)
    status = np.full(dx.shape, OK)
    copies = dx.copy(), dy.copy(), status.copy()
    ox, oy, os_ = postfilter(dx, dy, status)
    assert ox.dtype == np.float32 and oy.dtype == np.float32 and os_.dtype == np.uint8
    assert (os_ == OK).all()
    np.testing.assert_array_equal(ox, dx)
    np.testing.assert_array_equal(oy, dy)
    assert ox is not dx and oy is not dy and os_ is not status
    for before, after in zip(copies, (dx, dy, status)):
        np.testing.assert_array_equal(before, after)  # inputs unchanged


def test_blunders_are_found_and_filled():
    shape = (256, 512)
    tx, ty = _smooth(shape)
    dx, dy = _noisy(tx, ty, 0.02, seed=1)
    status = np.full(shape, OK)
    bad = _inject_blunders(dx, dy, status, 0.02, seed=2, gap=4)
    assert 0.015 < bad.mean() < 0.025
    ox, oy, os_ = postfilter(dx, dy, status)

    assert np.isin(os_[bad], (BLUNDER, FILLED)).all()  # every blunder found
    inner = np.zeros(shape, dtype=bool)
    inner[:, 12:-12] = True  # 2 * support px from the row ends: room for the fill's support
    assert (os_[bad & inner] == FILLED).all()  # ... and filled
    false_pos = (os_[~bad] != OK).mean()
    assert false_pos < 0.001
    kept = os_ == OK
    np.testing.assert_array_equal(ox[kept], dx[kept])  # bit for bit
    np.testing.assert_array_equal(oy[kept], dy[kept])
    filled = os_ == FILLED
    assert np.abs(ox[filled] - tx[filled]).max() < 0.1
    assert np.abs(oy[filled] - ty[filled]).max() < 0.1
    blunder = os_ == BLUNDER
    assert np.isnan(ox[blunder]).all() and np.isnan(oy[blunder]).all()


def test_a_removed_blunder_can_unmask_another():
    # A run 1, 1, 10 on a flat row: the 10 px blunder inflates the MAD around the two
    # 1 px ones, so pass 1 removes only it; pass 2 then finds the other two.
    dx = np.zeros((1, 40), np.float32)
    dy = np.zeros((1, 40), np.float32)
    dx[0, 17:20] = 1.0, 1.0, 10.0
    status = np.full(dx.shape, OK)
    one = postfilter(dx, dy, status, options=PostFilterOptions(window=5, passes=1, max_gap=0))[2][0]
    two = postfilter(dx, dy, status, options=PostFilterOptions(window=5, passes=2, max_gap=0))[2][0]
    assert np.nonzero(one == BLUNDER)[0].tolist() == [19]
    assert np.nonzero(two == BLUNDER)[0].tolist() == [17, 18, 19]
    assert (np.delete(two, [17, 18, 19]) == OK).all()
    filled = postfilter(dx, dy, status, options=PostFilterOptions(window=5))
    assert (filled[2][0, 17:20] == FILLED).all()
    np.testing.assert_allclose(filled[0][0, 17:20], 0.0, atol=1e-6)


def test_holes_are_filled_only_when_short_and_supported():
    ny, nx = 64, 300
    tx, ty = _quadratic((ny, nx))
    dx, dy = _noisy(tx, ty, 0.02, seed=3)
    status = np.full((ny, nx), OK)
    fill = {"5": slice(30, 35), "20": slice(60, 80), "max_gap": slice(240, 264)}
    keep = {"start": slice(0, 4), "40": slice(110, 150), "by_outside": slice(185, 190),
            "by_model": slice(210, 214), "end": slice(296, 300)}  # fmt: skip
    for s in (*fill.values(), *keep.values()):
        status[:, s] = NOTEX
    status[:, 180:185] = OUT
    status[:, 214:218] = MODEL
    nan = (status == NOTEX) | (status == OUT)
    dx[nan], dy[nan] = np.nan, np.nan
    ox, oy, os_ = postfilter(dx, dy, status)

    assert ((os_ == OK) | (status != OK)).all()  # no blunders in this field
    for name, s in fill.items():
        assert (os_[:, s] == FILLED).all(), name
        assert np.abs(ox[:, s] - tx[:, s]).max() < 0.1, name
        assert np.abs(oy[:, s] - ty[:, s]).max() < 0.1, name
    for name, s in keep.items():
        assert (os_[:, s] == NOTEX).all(), name
        assert np.isnan(ox[:, s]).all() and np.isnan(oy[:, s]).all(), name
    np.testing.assert_array_equal(os_[:, 180:185], OUT)
    np.testing.assert_array_equal(os_[:, 214:218], MODEL)
    np.testing.assert_array_equal(ox[:, 214:218], dx[:, 214:218])


def test_max_gap_is_inclusive():
    opts = PostFilterOptions(max_gap=10)
    tx, ty = _quadratic((2, 80))
    dx, dy = tx.astype(np.float32), ty.astype(np.float32)
    status = np.full(dx.shape, OK)
    status[0, 30:40] = NOTEX  # 10 px: filled
    status[1, 30:41] = NOTEX  # 11 px: kept
    res = postfilter(dx, dy, status, options=opts)[2]
    assert (res[0, 30:40] == FILLED).all() and (res[1, 30:41] == NOTEX).all()


def test_support_collection():
    opts = PostFilterOptions(support=3, max_gap=5, passes=0)  # support must lie within 6 px
    tx, ty = _quadratic((5, 40))
    dx, dy = tx.astype(np.float32), ty.astype(np.float32)
    status = np.full(dx.shape, OK)
    status[:, 20:23] = NOTEX
    status[1, 16:18] = NOTEX  # left side 19, 18, 15: 3 MATCHED within 6 px, another hole skipped
    status[2, 14:18] = NOTEX  # left side 19, 18, 13 (7 px away): too far
    status[3, 17] = OUT  # left side 19, 18, then a barrier: not enough support
    status[4, 17] = FILLED  # an earlier fill is a hole pixel too
    dx[status != OK], dy[status != OK] = np.nan, np.nan
    res = postfilter(dx, dy, status, options=opts)
    st = res[2][:, 20:23]
    assert (st[[0, 1, 4]] == FILLED).all()
    assert (st[[2, 3]] == NOTEX).all()
    assert res[2][4, 17] == FILLED and res[2][3, 17] == OUT
    assert np.abs(res[0][[0, 1, 4], 20:23] - tx[[0, 1, 4], 20:23]).max() < 1e-4  # quadratic reproduced


@pytest.mark.parametrize("order", [0, 1, 2])
def test_fill_order(order: int):
    opts = PostFilterOptions(order=order, support=4)
    x = np.arange(60, dtype=np.float64)
    truth = {0: 0 * x + 2.5, 1: 0.1 * x - 1.0, 2: 1e-3 * (x - 20.0) ** 2 + 0.05 * x}[order]
    dx = np.tile(truth.astype(np.float32), (2, 1))
    dy = dx[::-1].copy()
    status = np.full(dx.shape, OK)
    status[:, 25:37] = NOTEX
    res = postfilter(dx, dy, status, options=opts)
    assert (res[2][:, 25:37] == FILLED).all()
    np.testing.assert_allclose(res[0][0, 25:37], truth[25:37], atol=1e-4)


def test_nonfinite_match_is_a_blunder():
    dx, dy = (a.astype(np.float32) for a in _smooth((1, 40)))
    status = np.full(dx.shape, OK)
    dy[0, 10] = np.nan
    dx[0, 30] = np.inf
    res = postfilter(dx, dy, status, options=PostFilterOptions(passes=0, max_gap=0))
    assert res[2][0, [10, 30]].tolist() == [BLUNDER, BLUNDER] and np.isnan(res[0][0, 30])
    res = postfilter(dx, dy, status)
    assert res[2][0, [10, 30]].tolist() == [FILLED, FILLED] and np.isfinite(res[1][0]).all()


@pytest.mark.parametrize(
    "options",
    [
        PostFilterOptions(),
        PostFilterOptions(window=5, k=3.0, min_dev=0.0, max_gap=7, support=2, order=1, passes=3),
        PostFilterOptions(window=3, min_dev=0.2, max_gap=30, support=1, order=2, passes=1),
        PostFilterOptions(window=11, passes=0, order=0),
    ],
)
def test_numba_matches_reference(options: PostFilterOptions):
    dx, dy, status = _mixed_field((40, 300), seed=4)
    status[3, 5:9] = FILLED
    dx[5, 7] = np.nan  # inconsistent MATCHED pixels
    status[6, 40:50] = 9  # an unknown code: a barrier, left alone
    got = postfilter(dx, dy, status, options=options)
    ref = postfilter_reference(dx, dy, status, options=options)
    np.testing.assert_array_equal(got[2], ref[2])
    for g, r in zip(got[:2], ref[:2]):
        np.testing.assert_array_equal(np.isnan(g), np.isnan(r))
        np.testing.assert_allclose(g, r, rtol=1e-6, atol=1e-5)
    assert (got[2] == FILLED).any()
    assert options.passes == 0 or ((got[2] == BLUNDER) & (status == OK)).any() or options.max_gap >= 30


def test_halo_formula():
    assert halo(PostFilterOptions()) == 2 * 4 + (24 - 1) + 2 * 6
    assert halo(PostFilterOptions(window=5, passes=3, max_gap=10, support=3)) == 3 * 2 + 9 + 6
    assert halo(PostFilterOptions(passes=0)) == 23 + 12
    assert halo(PostFilterOptions(max_gap=0)) == 8


@pytest.mark.parametrize(
    "options",
    [
        PostFilterOptions(),
        PostFilterOptions(window=5, k=3.0, min_dev=0.2, max_gap=12, support=3, order=1, passes=3),
        PostFilterOptions(window=7, max_gap=40, support=8, passes=1),
    ],
)
@pytest.mark.parametrize("pad_outside", [False, True])
def test_tiles_with_halo_match_the_whole_image(options: PostFilterOptions, pad_outside: bool):
    dx, dy, status = _mixed_field((48, 517), seed=5)
    whole = postfilter(dx, dy, status, options=options)
    assert (whole[2] == BLUNDER).any() and (whole[2] == FILLED).any()
    _assert_same(_tiled(dx, dy, status, options, pad_outside=pad_outside), whole)
    short = _tiled(dx, dy, status, options, depth=options.window // 2, pad_outside=pad_outside)
    assert (short[2] != whole[2]).any()  # the field is hard enough to need the halo


def test_halo_is_tight_for_the_fill():
    # A hole of max_gap px whose last pixel starts a tile and whose farthest left
    # support pixel sits exactly 2 * support px beyond its edge.
    opts = PostFilterOptions(passes=0, max_gap=5, support=3)
    h = halo(opts)
    c0 = 20
    tx, ty = _quadratic((1, 40))
    dx, dy = tx.astype(np.float32), ty.astype(np.float32)
    status = np.full(dx.shape, OK)
    s = c0 - opts.max_gap + 1
    status[0, s : c0 + 1] = NOTEX
    status[0, s - 5 : s - 2] = NOTEX  # support: s - 1, s - 2 and s - 6
    whole = postfilter(dx, dy, status, options=opts)
    assert whole[2][0, c0] == FILLED
    for depth, expect in ((h, FILLED), (h - 1, NOTEX)):
        part = postfilter(dx[:, c0 - depth :], dy[:, c0 - depth :], status[:, c0 - depth :], options=opts)
        assert part[2][0, depth] == expect


def test_halo_is_tight_for_the_blunder_passes():
    # Column 4 is judged in pass 2 on what pass 1 made of column 2, which needs column 0.
    opts = PostFilterOptions(window=5, passes=2, max_gap=0)
    h = halo(opts)
    assert h == 4
    dx = np.array([[0.0, 3.0, 0.0, 1.0, 3.0, 10.0, 0.0, 0.0, 3.0]], np.float32)
    dy = np.zeros_like(dx)
    status = np.full(dx.shape, OK)
    whole = postfilter(dx, dy, status, options=opts)[2][0, h]
    cut = postfilter(dx[:, 1:], dy[:, 1:], status[:, 1:], options=opts)[2][0, h - 1]
    assert whole != cut


def test_options_are_checked():
    z = np.zeros((2, 3), np.float32)
    s = np.ones((2, 3), np.uint8)
    for bad in ({"window": 4}, {"window": 1}, {"order": 3}, {"support": 0}, {"max_gap": -1}, {"passes": -1}, {"k": 0}):
        with pytest.raises(ValueError):
            postfilter(z, z, s, options=PostFilterOptions(**bad))
    with pytest.raises(ValueError):
        postfilter(z, z[:1], s)
    empty = postfilter(np.zeros((0, 5), np.float32), np.zeros((0, 5), np.float32), np.zeros((0, 5), np.uint8))
    assert empty[2].shape == (0, 5)
