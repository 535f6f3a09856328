"""Composition of displacement fields: the kernel against analytic chains, and the tiled Dask stage."""

import numpy as np
import pytest
import xarray as xr
from cli_batch import run_batch

import geocoder
from geocoder import InputError, Status
from geocoder.kernels.compose import (
    FieldBlock,
    compose_fields,
    field_window,
    worse_status,
)

H, W = 96, 128


def grid(h=H, w=W):
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return xs, ys


def warp_ab(x, y):
    """A smooth, non-linear A -> B displacement (a few px, rotation-like and sinusoidal)."""
    return (3.2 + 0.01 * y - 0.004 * x + 0.8 * np.sin(y / 17.0), -2.1 + 0.006 * x + 0.5 * np.cos(x / 23.0))


def warp_bc(x, y):
    """A smooth, non-linear B -> C displacement."""
    return (-1.7 + 0.5 * np.sin(x / 29.0 + y / 41.0), 2.4 + 0.003 * x * (y / 100.0) + 0.4 * np.cos(y / 19.0))


def affine_bc(x, y):
    return (0.8 + 0.02 * x - 0.03 * y, -1.5 + 0.01 * x + 0.04 * y)


def test_composition_of_known_warps_is_exact_up_to_bilinear_interpolation():
    xs, ys = grid()
    d1 = warp_ab(xs, ys)
    d2 = warp_bc(xs, ys)  # sampled on B's grid
    c = compose_fields(FieldBlock(*d1), FieldBlock(*d2))
    qx, qy = xs + d1[0], ys + d1[1]
    tx, ty = warp_bc(qx, qy)
    truth_x, truth_y = d1[0] + tx, d1[1] + ty
    inside = (qx >= 0) & (qx <= W - 1) & (qy >= 0) & (qy <= H - 1)
    assert inside.mean() > 0.85
    np.testing.assert_array_equal(np.isfinite(c.dx), inside)
    assert (c.status[inside] == Status.MATCHED).all() and (c.status[~inside] == Status.OUTSIDE).all()
    # bilinear interpolation error <= (h^2 / 8) * max |second derivative|, h = 1 px
    bound = 0.25 * (0.5 / 29.0**2 + 0.5 / 41.0**2 + 0.4 / 19.0**2 + 0.003 / 100.0) + 1e-9
    assert np.abs(c.dx - truth_x)[inside].max() <= bound
    assert np.abs(c.dy - truth_y)[inside].max() <= bound
    assert np.abs(c.dx - truth_x)[inside].max() > 1e-6  # not trivially exact: the interpolation is there
    # an affine second field is interpolated exactly
    a = compose_fields(FieldBlock(*d1), FieldBlock(*affine_bc(xs, ys)))
    ax, ay = affine_bc(qx, qy)
    np.testing.assert_allclose(a.dx[inside], (d1[0] + ax)[inside], atol=1e-9)
    np.testing.assert_allclose(a.dy[inside], (d1[1] + ay)[inside], atol=1e-9)


def test_a_window_of_the_second_field_gives_the_same_result():
    xs, ys = grid()
    d1, d2 = warp_ab(xs, ys), warp_bc(xs, ys)
    whole = compose_fields(FieldBlock(*d1), FieldBlock(*d2))
    r0, r1, c0, c1 = 20, 60, 30, 90
    block = FieldBlock(d1[0][r0:r1, c0:c1], d1[1][r0:r1, c0:c1], row0=r0, col0=c0)
    wr0, wr1, wc0, wc1 = field_window(block, (H, W))
    assert (wr1 - wr0) < H and (wc1 - wc0) < W  # only what the block needs
    part = compose_fields(block, FieldBlock(d2[0][wr0:wr1, wc0:wc1], d2[1][wr0:wr1, wc0:wc1], row0=wr0, col0=wc0))
    np.testing.assert_allclose(part.dx, whole.dx[r0:r1, c0:c1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(part.dy, whole.dy[r0:r1, c0:c1], rtol=0, atol=1e-12)


def test_sigma_propagation_on_a_linear_chain():
    """B -> C affine: J = I + M exactly, so C_AC = J diag(s1^2) J^T + diag(s2^2) at every pixel."""
    xs, ys = grid()
    m = np.array([[0.02, -0.03], [0.01, 0.04]])
    d1 = (np.full((H, W), 2.3), np.full((H, W), -1.6))
    s1 = (np.full((H, W), 0.10), np.full((H, W), 0.20))
    s2 = (np.full((H, W), 0.05), np.full((H, W), 0.07))
    c = compose_fields(FieldBlock(*d1, *s1), FieldBlock(*affine_bc(xs, ys), *s2))
    j = np.eye(2) + m
    cov = j @ np.diag([0.1**2, 0.2**2]) @ j.T + np.diag([0.05**2, 0.07**2])
    ok = np.isfinite(c.dx)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(c.var_x[ok], cov[0, 0], rtol=1e-9)
    np.testing.assert_allclose(c.var_y[ok], cov[1, 1], rtol=1e-9)
    np.testing.assert_allclose(c.cov_xy[ok], cov[0, 1], rtol=1e-9)
    np.testing.assert_allclose(c.sigma_x[ok], np.sqrt(cov[0, 0]), rtol=1e-9)
    # Monte Carlo of the same linear chain: the spread of the composed displacement
    rng = np.random.default_rng(3)
    n = 20000
    e1 = rng.normal(size=(2, n)) * np.array([[0.1], [0.2]])
    e2 = rng.normal(size=(2, n)) * np.array([[0.05], [0.07]])
    np.testing.assert_allclose(np.cov(j @ e1 + e2), cov, rtol=0.05, atol=2e-5)


def test_status_is_the_worse_of_the_two_and_nodata_breaks_the_chain():
    assert worse_status(Status.MATCHED, Status.FILLED) == Status.FILLED
    assert worse_status(Status.ESTIMATED, Status.FILLED) == Status.ESTIMATED
    assert worse_status(Status.MODEL, Status.ESTIMATED) == Status.MODEL
    assert worse_status(Status.BLUNDER, Status.MATCHED) == Status.BLUNDER
    assert worse_status(Status.OUTSIDE, Status.MATCHED) == Status.OUTSIDE
    d1 = (np.full((16, 16), 0.5), np.zeros((16, 16)))  # halfway between two B columns
    st1 = np.full((16, 16), Status.MATCHED, dtype=np.uint8)
    st1[2, 2] = Status.FILLED
    st1[3, 3] = Status.OUTSIDE
    dx2, dy2 = np.zeros((16, 16)), np.zeros((16, 16))
    st2 = np.full((16, 16), Status.MATCHED, dtype=np.uint8)
    st2[8, 8] = Status.ESTIMATED  # reached from A pixels (7, 8) and (8, 8): both neighbours weigh 1/2
    dx2[12, 12] = np.nan  # a B pixel without displacement
    c = compose_fields(FieldBlock(*d1, status=st1), FieldBlock(dx2, dy2, status=st2))
    assert c.status[2, 2] == Status.FILLED and c.status[3, 3] == Status.OUTSIDE and np.isnan(c.dx[3, 3])
    assert c.status[8, 7] == Status.ESTIMATED and c.status[8, 8] == Status.ESTIMATED and c.status[8, 9] == Status.MATCHED
    assert np.isnan(c.dx[12, 11]) and np.isnan(c.dx[12, 12]) and c.status[12, 12] == Status.OUTSIDE
    assert c.status[:, 15].tolist() == [Status.OUTSIDE] * 16  # x + 0.5 > 15 leaves B's grid
    assert c.dx[0, 0] == 0.5 and c.status[0, 0] == Status.MATCHED
    # a position exactly on B's pixel uses that pixel alone (its neighbour's NaN does not matter)
    d1 = (np.zeros((16, 16)), np.zeros((16, 16)))
    c = compose_fields(FieldBlock(*d1), FieldBlock(dx2, dy2))
    assert np.isfinite(c.dx[12, 11]) and np.isnan(c.dx[12, 12])


def field_store(path, d, s=None, status=None, *, chunks=64, corr=None):
    data = {"dx": (("y", "x"), d[0].astype(np.float32)), "dy": (("y", "x"), d[1].astype(np.float32))}
    if s is not None:
        data["sigma_x"] = (("y", "x"), s[0].astype(np.float32))
        data["sigma_y"] = (("y", "x"), s[1].astype(np.float32))
    if status is not None:
        data["status"] = (("y", "x"), status.astype(np.uint8))
    if corr is not None:
        data["correlation"] = (("y", "x"), corr.astype(np.float32))
    h, w = d[0].shape
    ds = xr.Dataset(data, coords={"y": np.arange(h, dtype=float), "x": np.arange(w, dtype=float)})
    ds.chunk(chunks).to_zarr(path, mode="w", zarr_format=3, consolidated=False)
    return path


@pytest.mark.cluster
def test_compose_stage_on_the_cluster_is_independent_of_the_tiling(tmp_path, client):
    h, w = 300, 420
    xs, ys = grid(h, w)
    rng = np.random.default_rng(5)
    d1 = tuple(a + 0.05 * rng.normal(size=a.shape) for a in warp_ab(xs * 2.5, ys * 2.5))  # a few px over the scene
    d2 = warp_bc(xs * 2.5, ys * 2.5)
    s1 = (np.full((h, w), 0.1), np.full((h, w), 0.15))
    s2 = (np.full((h, w), 0.05), np.full((h, w), 0.08))
    st1 = np.where(rng.random((h, w)) < 0.05, Status.FILLED, Status.MATCHED).astype(np.uint8)
    st2 = np.where(rng.random((h, w)) < 0.05, Status.ESTIMATED, Status.MATCHED).astype(np.uint8)
    corr = np.full((h, w), 0.9)
    ab = field_store(tmp_path / "ab.zarr", d1, s1, st1, chunks=100, corr=corr)
    bc = field_store(tmp_path / "bc.zarr", d2, s2, st2, chunks=100, corr=corr * 0.95)
    a = geocoder.compose(ab, bc, out=tmp_path / "ac64.zarr", tile=64, client=client)
    b = geocoder.compose(ab, bc, out=tmp_path / "ac128.zarr", tile=128, client=client)
    assert a.dx.data.chunksize == (64, 64) and b.dx.data.chunksize == (128, 128)
    assert a.attrs["geocoder_product"] == "compose"
    for k in ("dx", "dy", "sigma_x", "sigma_y", "correlation", "status"):
        np.testing.assert_array_equal(a[k].values, b[k].values, err_msg=k)
    # the eager kernel on whole arrays gives the same field as the tiled stage
    whole = compose_fields(FieldBlock(*d1, *s1, status=st1, correlation=corr),
                           FieldBlock(*d2, *s2, status=st2, correlation=corr * 0.95))
    whole32 = FieldBlock(*(x.astype(np.float32) for x in d1), *(x.astype(np.float32) for x in s1), status=st1,
                         correlation=corr.astype(np.float32))
    exact = compose_fields(whole32, FieldBlock(*(x.astype(np.float32) for x in d2), *(x.astype(np.float32) for x in s2),
                                               status=st2, correlation=(corr * 0.95).astype(np.float32)))
    np.testing.assert_array_equal(a.status.values, exact.status)
    np.testing.assert_allclose(a.dx.values, exact.dx.astype(np.float32), atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(a.sigma_y.values, exact.sigma_y.astype(np.float32), rtol=1e-6, equal_nan=True)
    np.testing.assert_allclose(a.dx.values, whole.dx, atol=1e-4, equal_nan=True)
    # against the analytic chain (the noise of d1 moves the positions; the bilinear error is tiny)
    qx, qy = xs + d1[0], ys + d1[1]
    ok = a.status.values != Status.OUTSIDE
    assert ok.mean() > 0.9
    tx, _ = warp_bc(qx * 2.5, qy * 2.5)
    assert np.abs(a.dx.values - (d1[0] + tx))[ok].max() < 0.01
    assert a.correlation.values[ok].max() == pytest.approx(0.855, abs=1e-6)
    counts = np.bincount(a.status.values.ravel(), minlength=len(Status))
    assert counts[Status.FILLED] > 0 and counts[Status.ESTIMATED] > 0


@pytest.mark.cluster
def test_compose_command_and_bad_input(tmp_path, client):
    xs, ys = grid()
    ab = field_store(tmp_path / "ab.zarr", warp_ab(xs, ys))
    bc = field_store(tmp_path / "bc.zarr", affine_bc(xs, ys))
    out = tmp_path / "ac.zarr"
    # both command lines in one process, one after the other (see cli_batch); the second, to the same output, is refused
    runs = run_batch({"compose": ["-q", "compose", ab, bc, "--out", out, "--tile", 64, "--scheduler", client.scheduler.address],
                      "again": ["-q", "compose", ab, bc, "--out", out, "--scheduler", client.scheduler.address]}, tmp_path)
    r, _ = runs["compose"]
    assert r.returncode == 0, r.stderr
    assert "matched" in r.stdout and f"wrote {out}" in r.stdout
    ds = xr.open_zarr(out, consolidated=False)
    d1 = warp_ab(xs, ys)
    ax, _ = affine_bc(xs + d1[0], ys + d1[1])
    ok = ds.status.values == Status.MATCHED
    assert ok.mean() > 0.85
    np.testing.assert_allclose(ds.dx.values[ok], (d1[0] + ax)[ok], atol=1e-5)
    # a second run to the same output is refused; a store without dx is named
    r, _ = runs["again"]
    assert r.returncode == 2 and str(out) in r.stderr
    bad = tmp_path / "bad.zarr"
    xr.Dataset({"foo": (("y", "x"), np.zeros((8, 8)))}).to_zarr(bad, zarr_format=3, consolidated=False)
    with pytest.raises(InputError, match="bad.zarr.*no 'dx'"):
        geocoder.compose(ab, bad, client=client)
