"""Tests of geocoder.adjust.models (sensor models of the block adjustment)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geocoder.adjust.models import (
    RPC,
    LineScannerModel,
    Polynomial2D,
    RPCModel,
    SensorModel,
    _central_difference,
    fit_rpc,
    rpc_terms,
)
from geocoder.simulate.satellite import (
    LineScanner,
    ecef_to_geodetic,
    geodetic_to_ecef,
    landsat_mss_like,
)

LAT0, LON0 = 39.0, -98.0


@pytest.fixture(scope="module")
def scanner() -> LineScanner:
    return landsat_mss_like(rows=600, cols=800, swath=45e3, seed=3)


@pytest.fixture(scope="module")
def ground(scanner: LineScanner) -> np.ndarray:
    """Ground points inside the frame at heights 0..3000 m, shape (m, 3)."""
    rng = np.random.default_rng(1)
    n = 200
    r = rng.uniform(0, scanner.rows - 1, n)
    c = rng.uniform(0, scanner.cols - 1, n)
    h = rng.uniform(0, 3000, n)
    X, Y, Z = scanner.image_to_ground(r, c, height=h)
    return np.stack([X, Y, Z], axis=-1)


@pytest.fixture(scope="module")
def rpc(scanner: LineScanner) -> RPC:
    return fit_rpc(scanner)


def _local_points(n: int, seed: int, radius: float = 30e3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lat = np.deg2rad(LAT0) + rng.uniform(-1, 1, n) * radius / 6.37e6
    lon = np.deg2rad(LON0) + rng.uniform(-1, 1, n) * radius / (6.37e6 * np.cos(np.deg2rad(LAT0)))
    h = rng.uniform(0, 2000, n)
    return np.stack(geodetic_to_ecef(lat, lon, h), axis=-1)


# --------------------------------------------------------------------------- #
# protocol
# --------------------------------------------------------------------------- #
def test_models_satisfy_protocol(scanner: LineScanner, rpc: RPC) -> None:
    for model in (Polynomial2D(2, LAT0, LON0), LineScannerModel(scanner), RPCModel(rpc)):
        assert isinstance(model, SensorModel)
        assert model.initial_params().shape == (model.n_params,)
        assert np.asarray(model.param_steps).shape == (model.n_params,)


def test_central_difference_helper() -> None:
    # shared parameters
    def f(p: np.ndarray) -> np.ndarray:
        t = np.linspace(0, 1, 5)
        return np.stack([p[0] * t + p[1] ** 2, np.sin(p[1]) * t], axis=-1)

    p = np.array([2.0, 0.5])
    J = _central_difference(f, p, [1e-4, 1e-4])
    t = np.linspace(0, 1, 5)
    assert J.shape == (5, 2, 2)
    np.testing.assert_allclose(J[:, 0, 0], t, atol=1e-9)
    np.testing.assert_allclose(J[:, 0, 1], 2 * 0.5, atol=1e-7)
    np.testing.assert_allclose(J[:, 1, 1], np.cos(0.5) * t, atol=1e-7)
    # per-point variables
    g = np.random.default_rng(0).normal(size=(7, 3))
    Jg = _central_difference(lambda x: np.stack([x[:, 0] * x[:, 1], x[:, 2] ** 3], axis=-1), g, [1e-5] * 3)
    assert Jg.shape == (7, 2, 3)
    np.testing.assert_allclose(Jg[:, 0, 0], g[:, 1], atol=1e-8)
    np.testing.assert_allclose(Jg[:, 1, 2], 3 * g[:, 2] ** 2, atol=1e-9)  # error h^2 exactly
    assert np.all(Jg[:, 1, :2] == 0)


# --------------------------------------------------------------------------- #
# Polynomial2D
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("order", [1, 2, 3])
def test_polynomial_fit_recovers_known_polynomial(order: int) -> None:
    model = Polynomial2D(order, LAT0, LON0, scale=3e4)
    assert model.n_params == (order + 1) * (order + 2)
    rng = np.random.default_rng(order)
    truth = rng.normal(size=model.n_params) * 50.0
    truth[0], truth[model.n_monomials] = 400.0, 300.0
    g = _local_points(100, seed=order)
    xy = model.project(truth, g)
    np.testing.assert_allclose(model.fit(g, xy), truth, rtol=1e-9, atol=1e-8)
    # weights: down-weighted outliers barely matter, zero weight not at all
    xy_bad = xy.copy()
    xy_bad[:5] += 100.0
    w = np.ones(len(g))
    w[:5] = 0.0
    np.testing.assert_allclose(model.fit(g, xy_bad, weights=w), truth, rtol=1e-9, atol=1e-8)


def test_polynomial_height_ignored_and_plane() -> None:
    model = Polynomial2D(1, LAT0, LON0, scale=1e3)
    lat, lon = np.deg2rad(LAT0 + 0.01), np.deg2rad(LON0 + 0.02)
    g = np.stack(geodetic_to_ecef([lat, lat], [lon, lon], [0.0, 1000.0]), axis=-1)
    uv = model.plane(g)
    # the vertical offset projects to (almost) nothing in the plane: relief ~ h * tilt of the normal
    assert np.abs(uv[1] - uv[0]).max() * 1e3 < 1000.0 * 4e-4
    # east and north of the origin are positive; ~0.02 deg lon * 86.5 km/deg, 0.01 deg lat * 111 km/deg
    assert uv[0, 0] == pytest.approx(0.02 * 86.6, rel=0.01)
    assert uv[0, 1] == pytest.approx(0.01 * 111.0, rel=0.01)
    p = np.array([10.0, 1.0, 0.0, 20.0, 0.0, -1.0])  # x = 10 + u, y = 20 - v
    np.testing.assert_allclose(model.project(p, g[:1]), [[10 + uv[0, 0], 20 - uv[0, 1]]])


@pytest.mark.parametrize("order", [1, 2, 3])
def test_polynomial_jacobians_match_central_differences(order: int) -> None:
    model = Polynomial2D(order, LAT0, LON0, scale=3e4)
    rng = np.random.default_rng(10 + order)
    p = rng.normal(size=model.n_params) * 30.0
    g = _local_points(50, seed=20 + order)
    Jp, Jg = model.jacobians(p, g)
    assert Jp.shape == (50, 2, model.n_params) and Jg.shape == (50, 2, 3)
    Jp_n = _central_difference(lambda q: model.project(q, g), p, model.param_steps)
    Jg_n = _central_difference(lambda x: model.project(p, x), g, np.full(3, model.ground_step))
    np.testing.assert_allclose(Jp, Jp_n, rtol=1e-5, atol=1e-9 * np.abs(Jp).max())
    np.testing.assert_allclose(Jg, Jg_n, rtol=1e-5, atol=1e-7 * np.abs(Jg).max())


def test_polynomial_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        Polynomial2D(4, LAT0, LON0)
    model = Polynomial2D(2, LAT0, LON0)
    with pytest.raises(ValueError):
        model.project(np.zeros(5), np.zeros((1, 3)))
    with pytest.raises(ValueError):
        model.fit(_local_points(4, 0), np.zeros((4, 2)))


# --------------------------------------------------------------------------- #
# LineScannerModel
# --------------------------------------------------------------------------- #
def test_line_scanner_model_matches_template(scanner: LineScanner, ground: np.ndarray) -> None:
    model = LineScannerModel(scanner)
    assert model.n_params == 32
    p0 = model.initial_params()
    np.testing.assert_array_equal(p0, scanner.parameters())
    xy = model.project(p0, ground)
    row, col = scanner.ground_to_image(ground[:, 0], ground[:, 1], ground[:, 2])
    # the model's own (lean, warm-started) time search converges to the same point
    np.testing.assert_allclose(xy[:, 0], col, rtol=0, atol=1e-9)  # measured ~1e-10 px
    np.testing.assert_allclose(xy[:, 1], row, rtol=0, atol=1e-9)
    assert np.all(np.isfinite(xy))
    # warm start: the next iterate's projection (points moved by metres, parameters changed)
    rng = np.random.default_rng(2)
    p1 = p0 + rng.normal(size=32) * model.param_steps * 100
    g1 = ground + rng.normal(0, 5.0, ground.shape)
    xy1 = model.project(p1, g1)
    row1, col1 = model.scanner(p1).ground_to_image(g1[:, 0], g1[:, 1], g1[:, 2])
    np.testing.assert_allclose(xy1, np.stack([col1, row1], axis=-1), rtol=0, atol=1e-9)
    assert np.abs(xy1 - xy).max() > 1.0


def test_line_scanner_model_perturbation_moves_points(scanner: LineScanner, ground: np.ndarray) -> None:
    model = LineScannerModel(scanner)
    p0 = model.initial_params()
    xy0 = model.project(p0, ground)
    names = model.names
    # +10 m along-track offset: ~0.13 rows (79 m lines), columns ~unchanged
    p = p0.copy()
    p[names.index("along_c0")] += 10.0
    d = model.project(p, ground) - xy0
    assert np.abs(d[:, 1]).min() > 0.08 and np.abs(d[:, 1]).max() < 0.2
    assert np.abs(d[:, 0]).max() < 0.02
    # roll of 1e-4 rad: ~92 m / 56 m per column ~ 1.6 columns
    p = p0.copy()
    p[names.index("roll_c0")] += 1e-4
    d = model.project(p, ground) - xy0
    assert np.abs(d[:, 0]).min() > 1.0
    assert np.abs(d[:, 1]).max() < 0.1


def test_line_scanner_model_free_masks(scanner: LineScanner, ground: np.ndarray) -> None:
    sets = LineScannerModel.parameter_sets()
    assert set(sets) == {"full", "attitude_only", "low_order"}
    expected = {"full": 32, "attitude_only": 20, "low_order": 12}
    for name, mask in sets.items():
        model = LineScannerModel(scanner, free=mask)
        assert mask.dtype == bool and mask.shape == (32,)
        assert model.n_params == expected[name] == len(model.names)
        np.testing.assert_array_equal(model.initial_params(), scanner.parameters()[mask])
        np.testing.assert_array_equal(model.full_parameters(model.initial_params()), scanner.parameters())
    low = LineScannerModel(scanner, free=sets["low_order"])
    assert low.names[:2] == ["along_c0", "along_c1"] and "yaw_c1" in low.names and "yaw_c2" not in low.names
    att = LineScannerModel(scanner, free=sets["attitude_only"])
    assert att.names[:8] == ["semi_major_axis", "eccentricity", "inclination", "raan", "arg_perigee",
                             "mean_anomaly0", "line_time", "t0"]  # fmt: skip
    assert all(n.split("_")[0] in ("roll", "pitch", "yaw") for n in att.names[8:])
    # integer indices work too
    assert LineScannerModel(scanner, free=np.array([8, 20])).n_params == 2
    # held parameters stay at the template's values
    xy = low.project(low.initial_params(), ground[:5])
    np.testing.assert_array_equal(xy, LineScannerModel(scanner).project(scanner.parameters(), ground[:5]))


def test_line_scanner_model_negative_eccentricity_is_smooth(scanner: LineScanner, ground: np.ndarray) -> None:
    model = LineScannerModel(scanner)
    p0 = model.initial_params()
    assert p0[1] == 0.0
    xs = []
    for e in (-2e-7, -1e-7, 0.0, 1e-7, 2e-7):
        p = p0.copy()
        p[1] = e
        xs.append(model.project(p, ground[:20]))
    xs = np.array(xs)
    # equal spacing in e gives (nearly) equal steps in the image: linear through e = 0
    d = np.diff(xs, axis=0)
    np.testing.assert_allclose(d, np.broadcast_to(d.mean(axis=0), d.shape), atol=1e-6)
    assert np.abs(d).max() > 1e-3


def test_line_scanner_model_jacobians(scanner: LineScanner, ground: np.ndarray) -> None:
    model = LineScannerModel(scanner)
    p0 = model.initial_params()
    g = ground[:60]
    Jp, Jg = model.jacobians(p0, g)
    assert Jp.shape == (60, 2, 32) and Jg.shape == (60, 2, 3)
    assert np.all(np.isfinite(Jp)) and np.all(np.isfinite(Jg))
    # ground: a finer (0.2 m) and a coarser (5 m) numeric check agree
    sc = model.scanner(p0)

    def img(x: np.ndarray) -> np.ndarray:
        r, c = sc.ground_to_image(x[:, 0], x[:, 1], x[:, 2])
        return np.stack([c, r], axis=-1)

    for h in (0.2, 5.0):
        np.testing.assert_allclose(Jg, _central_difference(img, g, [h] * 3), rtol=2e-5, atol=1e-6 * np.abs(Jg).max())
    # ~ 1 / 56 columns and 1 / 79 rows per metre in the horizontal
    norms = np.linalg.norm(Jg, axis=2)
    assert np.all((norms[:, 0] > 0.014) & (norms[:, 0] < 0.022))
    assert np.all((norms[:, 1] > 0.010) & (norms[:, 1] < 0.016))
    # parameters: steps 4x the default agree (the response is smooth, the iteration noise small)
    Jp4 = _central_difference(lambda q: model.project(q, g), p0, 4.0 * model.param_steps)
    scale = np.abs(Jp).max(axis=(0, 1))  # per parameter
    np.testing.assert_allclose(Jp / scale, Jp4 / scale, atol=1e-4)
    # every parameter moves the image by ~0.003..0.1 px per step (steps are sensibly scaled)
    moved = np.abs(Jp * model.param_steps).max(axis=(0, 1))
    assert np.all((moved > 1e-3) & (moved < 0.2)), moved
    # a subset's Jacobian is the corresponding columns
    low = LineScannerModel(scanner, free=LineScannerModel.parameter_sets()["low_order"])
    Jp_low, _ = low.jacobians(low.initial_params(), g)
    np.testing.assert_allclose(Jp_low, Jp[:, :, low.free], rtol=1e-6, atol=1e-9 * np.abs(Jp_low).max())


def _frame_points(sc: LineScanner, n: int, seed: int) -> np.ndarray:
    """Ground points inside the frame of ``sc`` at heights 0..3000 m, shape (n, 3)."""
    rng = np.random.default_rng(seed)
    r, c, h = rng.uniform(0, sc.rows - 1, n), rng.uniform(0, sc.cols - 1, n), rng.uniform(0, 3000, n)
    return np.stack(sc.image_to_ground(r, c, height=h), axis=-1)


@pytest.mark.parametrize("kind", ["pushbroom", "whiskbroom"])
def test_line_scanner_model_implicit_jacobians_match_brute_force(scanner: LineScanner, kind: str) -> None:
    """The implicit-differentiation Jacobians equal central differences of ``project`` (full Newton solves).

    Measured agreement (max |diff| / max |J| per column, 300 points, parameters off the
    template): <= 4.4e-8 for both scanner kinds and all three parameter sets, mainly the noise of the
    brute-force differences (~1e-10 rows of Newton convergence over a ~0.01 px step); 2e-7 is
    a few times that, while an error in the implicit formula (e.g. dropping the dt/dq term)
    shows up at order 1.
    """
    sc = scanner if kind == "pushbroom" else landsat_mss_like(rows=600, cols=800, swath=45e3, seed=3, kind=kind)
    assert sc.kind == kind
    g = _frame_points(sc, 300, seed=11)
    g = np.concatenate([g, 1.5 * g[:1]])  # a point in space above the orbit: behind the sensor, NaN image
    rng = np.random.default_rng(12)
    for name, mask in LineScannerModel.parameter_sets().items():
        model = LineScannerModel(sc, free=mask)
        p = model.initial_params() + rng.normal(size=model.n_params) * model.param_steps * 30  # a solver iterate
        xy = model.project(p, g)
        assert np.all(np.isfinite(xy[:-1])) and np.all(np.isnan(xy[-1]))
        # the solved time inverts the row formula: the image at that fixed time is the projection, F = 0
        sc_p = model.scanner(p)
        at_t = model._image_at_time(sc_p, sc_p.time(xy[:-1, 1], xy[:-1, 0]), g[:-1])
        np.testing.assert_allclose(at_t[:, :2], xy[:-1], rtol=0, atol=1e-11)  # measured <= 3e-12 px
        assert np.abs(at_t[:, 2]).max() < 1e-13  # measured <= 2e-14
        Jp, Jg = model.jacobians(p, g)
        assert Jp.shape == (len(g), 2, model.n_params) and Jg.shape == (len(g), 2, 3)
        assert np.all(np.isnan(Jp[-1])) and np.all(np.isnan(Jg[-1]))
        assert np.all(np.isfinite(Jp[:-1])) and np.all(np.isfinite(Jg[:-1]))
        Jp_bf = _central_difference(lambda q: model.project(q, g[:-1]), p, model.param_steps)
        Jg_bf = _central_difference(lambda x: model._image(sc_p, x), g[:-1], np.full(3, model.ground_step))
        for J, J_bf in ((Jp[:-1], Jp_bf), (Jg[:-1], Jg_bf)):
            rel = np.abs(J - J_bf).max(axis=(0, 1)) / np.abs(J_bf).max(axis=(0, 1))
            assert rel.max() < 2e-7, (kind, name, rel.max())


def test_line_scanner_model_jacobian_linearises(scanner: LineScanner, ground: np.ndarray) -> None:
    """A small finite parameter change is predicted by the Jacobian (Gauss-Newton usable)."""
    model = LineScannerModel(scanner, free=LineScannerModel.parameter_sets()["low_order"])
    p0 = model.initial_params()
    g = ground[:50]
    Jp, _ = model.jacobians(p0, g)
    dp = np.random.default_rng(5).normal(size=model.n_params) * model.param_steps * 20
    pred = model.project(p0, g) + Jp @ dp
    np.testing.assert_allclose(model.project(p0 + dp, g), pred, atol=2e-3)


# --------------------------------------------------------------------------- #
# RPC
# --------------------------------------------------------------------------- #
def test_rpc_terms_order() -> None:
    P, L, H = 0.3, -0.7, 0.2
    T = rpc_terms(P, L, H)
    expect = [1, L, P, H, L * P, L * H, P * H, L * L, P * P, H * H, P * L * H, L**3, L * P * P, L * H * H,
              L * L * P, P**3, P * H * H, L * L * H, P * P * H, H**3]  # fmt: skip
    np.testing.assert_allclose(T, expect)


def test_fit_rpc_reproduces_scanner(scanner: LineScanner, rpc: RPC) -> None:
    rng = np.random.default_rng(7)
    n = 3000
    r = rng.uniform(0, scanner.rows - 1, n)
    c = rng.uniform(0, scanner.cols - 1, n)
    h = rng.uniform(0, 3000, n)
    X, Y, Z = scanner.image_to_ground(r, c, height=h)
    lat, lon, hh = ecef_to_geodetic(X, Y, Z)
    rr, cc = rpc.project(np.rad2deg(lat), np.rad2deg(lon), hh)
    err = np.hypot(rr - r, cc - c)
    assert err.max() < 0.05, err.max()
    # ECEF entry point agrees
    xy = rpc.project_ecef(np.stack([X, Y, Z], axis=-1)[:10])
    np.testing.assert_allclose(xy, np.stack([cc[:10], rr[:10]], axis=-1), atol=1e-9)
    assert rpc.line_off == pytest.approx((scanner.rows - 1) / 2)
    assert rpc.samp_scale == pytest.approx((scanner.cols - 1) / 2)
    assert rpc.line_den_coeff[0] == 1.0 and rpc.samp_den_coeff[0] == 1.0


def test_fit_rpc_whiskbroom_and_subwindow() -> None:
    sc = landsat_mss_like(rows=600, cols=800, swath=45e3, seed=4, kind="whiskbroom")
    rpc = fit_rpc(sc, grid=(11, 11), rows=(100, 300), cols=(200, 500), heights=(500, 1500), layers=5)
    r, c = np.meshgrid(np.linspace(100, 300, 7), np.linspace(200, 500, 9), indexing="ij")
    X, Y, Z = sc.image_to_ground(r, c, height=1000.0)
    rr, cc = rpc.project(*(np.rad2deg(v) for v in ecef_to_geodetic(X, Y, Z)[:2]), 1000.0)
    assert np.abs(rr - r).max() < 0.01 and np.abs(cc - c).max() < 0.01


def test_rpc_rasterio_round_trip(rpc: RPC) -> None:
    from rasterio.rpc import RPC as RioRPC

    rio = rpc.to_rasterio()
    assert isinstance(rio, RioRPC)
    back = RPC.from_rasterio(rio)
    for name, value in rpc.to_dict().items():
        np.testing.assert_array_equal(getattr(back, name) if value is not None else None, value)
    # built directly from the fields, and via GDAL metadata strings
    direct = RioRPC(**rpc.to_dict())
    np.testing.assert_array_equal(RPC.from_rasterio(direct).line_num_coeff, rpc.line_num_coeff)
    via_gdal = RPC.from_rasterio(rio.to_gdal())
    np.testing.assert_array_equal(via_gdal.samp_den_coeff, rpc.samp_den_coeff)
    assert via_gdal.lat_off == rpc.lat_off


def test_rpc_geotiff_round_trip(rpc: RPC, ground: np.ndarray, tmp_path: Path) -> None:
    import rasterio

    path = tmp_path / "rpc.tif"
    profile = {"driver": "GTiff", "width": 80, "height": 60, "count": 1, "dtype": "uint8"}
    with rasterio.open(path, "w", **profile, rpcs=rpc.to_rasterio()) as dst:
        dst.write(np.zeros((1, 60, 80), dtype=np.uint8))
    with rasterio.open(path) as src:
        assert src.rpcs is not None
        back = RPC.from_rasterio(src.rpcs)
    np.testing.assert_allclose(back.project_ecef(ground), rpc.project_ecef(ground), rtol=0, atol=1e-8)
    np.testing.assert_allclose(back.line_num_coeff, rpc.line_num_coeff, rtol=1e-14, atol=1e-300)


def test_rpc_agrees_with_gdal(rpc: RPC, ground: np.ndarray) -> None:
    """GDAL's RPC transformer evaluates the same functions (it adds 0.5 px: corner convention)."""
    from rasterio.transform import RPCTransformer

    lat, lon, h = ecef_to_geodetic(ground[:, 0], ground[:, 1], ground[:, 2])
    lat, lon = np.rad2deg(lat), np.rad2deg(lon)
    row, col = rpc.project(lat, lon, h)
    with RPCTransformer(rpc.to_rasterio()) as tr:
        gr, gc = tr.rowcol(lon, lat, zs=h, op=np.positive)
    np.testing.assert_allclose(np.asarray(gr) - 0.5, row, atol=1e-6)
    np.testing.assert_allclose(np.asarray(gc) - 0.5, col, atol=1e-6)


def test_rpc_model_bias(rpc: RPC, ground: np.ndarray) -> None:
    model = RPCModel(rpc)
    assert model.n_params == 6
    p0 = model.initial_params()
    np.testing.assert_array_equal(p0, np.zeros(6))
    xy0 = model.project(p0, ground)
    np.testing.assert_array_equal(xy0, rpc.project_ecef(ground))
    # pure shift
    d = model.project(np.array([2.5, 0, 0, -1.5, 0, 0]), ground) - xy0
    np.testing.assert_allclose(d, np.broadcast_to([2.5, -1.5], d.shape), atol=1e-9)
    # scale/shear terms
    p = np.array([0.0, 1e-3, -2e-3, 0.0, 5e-4, 1e-3])
    d = model.project(p, ground) - xy0
    x, y = xy0[:, 0], xy0[:, 1]
    np.testing.assert_allclose(d[:, 0], 1e-3 * x - 2e-3 * y, atol=1e-9)
    np.testing.assert_allclose(d[:, 1], 5e-4 * x + 1e-3 * y, atol=1e-9)


def test_rpc_model_jacobians(rpc: RPC, scanner: LineScanner, ground: np.ndarray) -> None:
    model = RPCModel(rpc)
    p = np.array([1.0, 2e-3, -1e-3, -2.0, 5e-4, 3e-3])
    Jp, Jg = model.jacobians(p, ground)
    assert Jp.shape == (len(ground), 2, 6) and Jg.shape == (len(ground), 2, 3)
    Jp_n = _central_difference(lambda q: model.project(q, ground), p, model.param_steps)
    np.testing.assert_allclose(Jp, Jp_n, rtol=1e-6, atol=1e-6)
    Jg_n = _central_difference(lambda x: model.project(p, x), ground, [0.25] * 3)
    np.testing.assert_allclose(Jg, Jg_n, rtol=1e-4, atol=1e-7)
    # with zero bias the RPC's ground Jacobian approximates the scanner's
    _, Jg0 = model.jacobians(np.zeros(6), ground)
    _, Jg_sc = LineScannerModel(scanner).jacobians(scanner.parameters(), ground)
    np.testing.assert_allclose(Jg0, Jg_sc, atol=2e-4 * np.abs(Jg_sc).max())


# --------------------------------------------------------------------------- #
# Exact line-scanner Jacobians (jets + implicit time)
# --------------------------------------------------------------------------- #
def test_jets_propagate_derivatives() -> None:
    """A jet expression's derivatives equal the hand-derived ones (per point, two directions)."""
    from geocoder.adjust import jet

    x = np.linspace(0.1, 2.0, 7)
    a = jet.seed(0.7, 2, 0)  # a frame-level scalar
    u = jet.seed(x, 2, 1)  # per-point values
    f = jet.arctan2(jet.sin(u) * a, jet.cos(u) + 2.0) + jet.sqrt(u * u + 1.0) / a - 3.0 / u
    vec = jet.stack([u, a * u, u * u])
    g = jet.dot(jet.unit(vec), jet.cross(vec, jet.stack([a, u, 1.0 - u])))
    for fn, expr in (
        (lambda aa, xx: np.arctan2(np.sin(xx) * aa, np.cos(xx) + 2) + np.sqrt(xx * xx + 1) / aa - 3 / xx, f),
        (lambda aa, xx: np.zeros_like(xx), g),  # v . (v x w) = 0
    ):
        h = 1e-6
        da = (fn(0.7 + h, x) - fn(0.7 - h, x)) / (2 * h)
        dx = (fn(0.7, x + h) - fn(0.7, x - h)) / (2 * h)
        np.testing.assert_allclose(expr.v, fn(0.7, x), atol=1e-12)
        np.testing.assert_allclose(expr.d, np.stack([da, dx], axis=-1), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("kind", ["pushbroom", "whiskbroom"])
@pytest.mark.parametrize("ecc", [0.0, 2e-3, -2e-3])
def test_line_scanner_analytic_jacobians_match_central_differences(scanner: LineScanner, kind: str, ecc: float) -> None:
    """All 32 parameters and the ground point, against central differences of ``project``.

    Relative error = max |analytic - numeric| / max |numeric| per column (parameter or ground
    coordinate), parameters off the template (a solver iterate), circular, elliptical and
    negative-eccentricity orbits.  The numeric parameter derivatives are Richardson-extrapolated
    central differences (steps ``param_steps`` and twice that), the ground ones 1 m central
    differences.  Measured worst: 3.0e-8 (parameters), 1.4e-8 (ground): the noise of the Newton
    solves inside ``project`` over ~0.01 px steps.
    """
    sc = scanner if kind == "pushbroom" else landsat_mss_like(rows=600, cols=800, swath=45e3, seed=3, kind=kind)
    g = _frame_points(sc, 300, seed=11)
    model = LineScannerModel(sc)
    rng = np.random.default_rng(11)
    p = model.initial_params() + rng.normal(size=32) * model.param_steps * 30
    p[1] = ecc
    Jp, Jg = model.jacobians(p, g)
    assert np.all(np.isfinite(Jp)) and np.all(np.isfinite(Jg))

    def proj(q: np.ndarray) -> np.ndarray:
        return model.project(q, g)

    d1 = _central_difference(proj, p, model.param_steps)
    d2 = _central_difference(proj, p, 2.0 * model.param_steps)
    Jp_num = (4.0 * d1 - d2) / 3.0
    sc_p = model.scanner(p)
    Jg_num = _central_difference(lambda x: model._image(sc_p, x), g, np.full(3, 1.0))
    for J, J_num, bound in ((Jp, Jp_num, 1e-6), (Jg, Jg_num, 1e-6)):
        rel = np.abs(J - J_num).max(axis=(0, 1)) / np.abs(J_num).max(axis=(0, 1))
        assert rel.max() < bound, (kind, ecc, int(np.argmax(rel)), rel.max())
    # every column carries signal (no parameter silently dropped): e.g. the orbit elements too
    assert np.all(np.abs(Jp).max(axis=(0, 1)) > 0)


def test_line_scanner_fixed_time_partials_match_differences(scanner: LineScanner) -> None:
    """The jets' partial derivatives at a fixed time (before the implicit step) are exact.

    Compared with central differences of :meth:`LineScannerModel._image_at_time`, which has
    no Newton solve inside, for the acquisition time and the ground point.
    """
    from geocoder.adjust.linescanner_jacobian import image_jets

    model = LineScannerModel(scanner)
    g = _frame_points(scanner, 100, seed=4)
    xy = model.project(model.initial_params(), g)
    t = scanner.time(xy[:, 1], xy[:, 0])
    col, row, F = image_jets(scanner, t, g)
    at = model._image_at_time(scanner, t, g)
    np.testing.assert_allclose(np.stack([col.v, row.v, F.v], axis=-1), at, rtol=0, atol=1e-9)
    J = np.stack([col.d, row.d, F.d], axis=1)  # (m, 3, 16)
    lt = scanner.orbit.line_time
    dt = _central_difference(lambda tt: model._image_at_time(scanner, tt[:, 0], g), t[:, None], 0.1 * lt)
    dg = _central_difference(lambda x: model._image_at_time(scanner, t, x), g, np.full(3, 1.0))
    for a, b in ((J[:, :, 6:7], dt), (J[:, :, 13:], dg)):
        scale = np.abs(b).max(axis=0)
        rel = np.abs(a - b).max(axis=0) / np.where(scale > 0, scale, 1.0)  # a pushbroom row ignores the ground
        assert rel.max() < 1e-7, rel


def test_line_scanner_jacobians_reuse_last_projection(scanner: LineScanner, ground: np.ndarray) -> None:
    """Projection then Jacobians at the same point solve once; a changed point is solved anew."""
    model = LineScannerModel(scanner, free=LineScannerModel.parameter_sets()["low_order"])
    p = model.initial_params()
    xy = model.project(p, ground[:20])
    xy[:] = 0.0  # the returned array is a copy: the cache is not touched
    Jp, _ = model.jacobians(p, ground[:20])
    fresh = LineScannerModel(scanner, free=model.free)
    np.testing.assert_array_equal(Jp, fresh.jacobians(p, ground[:20])[0])
    q = p.copy()
    q[0] += 5.0  # along-track offset 5 m
    moved = model.project(q, ground[:20])
    np.testing.assert_array_equal(moved, fresh.project(q, ground[:20]))
    assert np.abs(moved - fresh.project(p, ground[:20])).max() > 0.05
