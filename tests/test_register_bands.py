"""``register(..., bands=...)``: the dense matching on several bands at once (seed 003 sec. 11),
end to end on a local cluster, against the truth of a real 3-band crop warped by a known field
whose band 1 has no texture over the left half."""

from __future__ import annotations

import click
import numpy as np
import pytest
from cli_batch import run_batch
from conftest import read_band
from scipy.ndimage import gaussian_filter

from geocoder import Status, register
from geocoder.cli import _band_list
from geocoder.scene import write_geotiff
from geocoder.simulate.warp import make_pair

AERIAL = "baviaanskloof/ngi_rgb_byte_1.tif"
SIZE = 256


@pytest.fixture(scope="module")
def weak_pair(shared_data, tmp_path_factory):
    margin = 32
    n = SIZE + 2 * margin
    src = np.stack([read_band(shared_data / AERIAL, b, (60, 60 + n, 107, 107 + n)) for b in (1, 2, 3)])
    src[0, :, : n // 2] = gaussian_filter(src[0], 8.0)[:, : n // 2]
    pair = make_pair(src, shape=(SIZE, SIZE), seed=21, margin=margin, turbulence=(1.0, 3.0))
    out = tmp_path_factory.mktemp("bands")
    write_geotiff(out / "base.tif", pair.base)
    write_geotiff(out / "dist.tif", pair.distorted)
    return out / "base.tif", out / "dist.tif", pair


def _left_figures(ds, pair):
    st = ds.status.values
    left = np.zeros(st.shape, bool)
    left[:, 40 : SIZE // 2 - 30] = True
    inside = (st != Status.OUTSIDE) & np.isfinite(pair.dx) & left
    good = ((st == Status.MATCHED) | (st == Status.FILLED)) & inside
    err = np.hypot(ds.dx.values - pair.dx, ds.dy.values - pair.dy)
    matched_all = (st == Status.MATCHED) | (st == Status.FILLED)
    return {
        "coverage_left": good.sum() / inside.sum(),
        "rmse_left": float(np.sqrt(np.mean(err[good] ** 2))) if good.any() else float("nan"),
        "unflagged_over_1px": int((err[matched_all & np.isfinite(err)] > 1.0).sum()),
    }


def test_bands_match_where_one_band_is_flat(weak_pair, client):
    base, dist, pair = weak_pair
    one = _left_figures(register(base, dist, tile=128, client=client), pair)
    ds = register(base, dist, tile=128, client=client, bands=(1, 2, 3))
    every = _left_figures(ds, pair)
    print("band 1:", one, "bands 1,2,3:", every)
    assert one["coverage_left"] < 0.3  # measured 0.0
    # the flat half is not matched wrongly either (starts carried 64-512 px into it from the
    # textured half by the global polynomial, poorly determined there, made 769 such matches)
    assert one["unflagged_over_1px"] == 0
    assert every["coverage_left"] > 0.8  # measured 0.97, RMSE 0.052 px
    assert every["rmse_left"] < 0.08
    assert every["unflagged_over_1px"] == 0
    # the same result whatever the tiling (the bands are scaled for the whole scene, not per tile)
    other = register(base, dist, tile=256, client=client, bands=(1, 2, 3))  # one tile: no halo exchange
    both = (other.status.values == Status.MATCHED) & (ds.status.values == Status.MATCHED)
    assert (other.status.values == ds.status.values).mean() >= 0.995
    assert np.hypot(other.dx.values - ds.dx.values, other.dy.values - ds.dy.values)[both].max() <= 0.01


def test_a_flat_half_is_not_matched_wrongly(shared_data, tmp_path, client):
    # band 1 of a 512^2 aerial crop flat over its left half: the every-pixel pass carries its
    # starts past the lines' ends only as far as the matches' curvature allows (a sign error
    # that let the leftward reach run to 512 px matched 22 % of the half 0.65 px off, 4240
    # pixels by more than 1 px, unflagged)
    margin = 48
    n = 512 + 2 * margin
    src = np.stack([read_band(shared_data / AERIAL, b, (60, 60 + n, 107, 107 + n)) for b in (1, 2, 3)]).astype(np.float32)
    src[0, :, : n // 2] = gaussian_filter(src[0], 8.0)[:, : n // 2]
    pair = make_pair(src, shape=(512, 512), seed=21, margin=margin, turbulence=(1.0, 3.0))
    write_geotiff(tmp_path / "base.tif", pair.base)
    write_geotiff(tmp_path / "dist.tif", pair.distorted)
    ds = register(tmp_path / "base.tif", tmp_path / "dist.tif", tile=256, client=client)
    st = ds.status.values
    err = np.hypot(ds.dx.values - pair.dx, ds.dy.values - pair.dy)
    good = ((st == Status.MATCHED) | (st == Status.FILLED)) & np.isfinite(err)
    left = good[:, :256]
    print("left matched", left.mean(), "RMSE", np.sqrt(np.mean(err[:, :256][left] ** 2)), "> 1 px", (err[good] > 1).sum())
    assert (err[good] > 1.0).sum() == 0
    assert np.sqrt(np.mean(err[:, :256][left] ** 2)) <= 0.1  # measured 0.028 px over 5 % of the half


def test_bad_bands_are_refused(weak_pair, tmp_path):
    base, dist, _ = weak_pair
    # both command lines in one fresh process (see cli_batch): the refusals themselves take
    # 0.15 s, a process of its own ~4 s of interpreter start and imports
    results = run_batch({bands: ["register", base, dist, "--out", tmp_path / "o.zarr", "--bands", bands, *flags]
                         for bands, flags in (("1,2", ["--no-dense"]), ("1,2,5", []))}, tmp_path)

    assert _band_list("3,1,2") == (3, 1, 2)
    with pytest.raises(click.BadParameter, match="'1,x' is not a comma-separated list of band numbers"):
        _band_list("1,x")
    for bad in ("2", "1,1", "0,1"):
        with pytest.raises(click.BadParameter, match="give two or more distinct 1-based bands"):
            _band_list(bad)
    r, after = results["1,2"]
    assert r.returncode == 2 and "they need dense matching (not --no-dense)" in r.stderr
    assert not any(k.startswith("o.zarr") for k in after)
    r, after = results["1,2,5"]
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == f"geocoder: error: {base}: has 3 band(s); band 5 does not exist"
    assert not any(k.startswith("o.zarr") for k in after)
    assert not (tmp_path / "o.zarr").exists()
