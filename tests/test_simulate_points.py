"""Tests of geocoder.simulate.points (control, check, tie and edge points)."""

from __future__ import annotations

import numpy as np
import pytest

from geocoder.simulate import airborne
from geocoder.simulate.points import (
    EDGE_CONFIGURATIONS,
    GroundPoints,
    block_of_strips,
    edge_points,
    edge_weight,
    grid_points,
    observe,
    perturb_ground,
    perturbation,
    point_weight,
    tie_points,
)
from geocoder.simulate.satellite import (
    ecef_to_geodetic,
    geodetic_to_ecef,
    landsat_mss_like,
)


@pytest.fixture(scope="module")
def block():
    return block_of_strips(strips=3, frames=3, seed=7)


@pytest.fixture(scope="module")
def frame():
    return landsat_mss_like(seed=3)


def _terrain(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    return 800.0 + 600.0 * np.sin(lat * 300.0) * np.cos(lon * 200.0)


# --------------------------------------------------------------------------- #
# footprint geometry helpers (tangent plane at the block centre)
# --------------------------------------------------------------------------- #
def _enu(X, Y, Z, lat0=1.0210176124166828, lon0=-1.710422666954443):
    """ENU plane at 58.5 N, 98 W (radians in the defaults)."""
    O = np.array(geodetic_to_ecef(lat0, lon0, 0.0))
    e = np.array([-np.sin(lon0), np.cos(lon0), 0.0])
    n = np.array([-np.sin(lat0) * np.cos(lon0), -np.sin(lat0) * np.sin(lon0), np.cos(lat0)])
    d = np.stack([X, Y, Z], axis=-1) - O
    return np.stack([d @ e, d @ n], axis=-1)


def _footprint(sc) -> np.ndarray:
    r = np.array([0.0, 0.0, sc.rows - 1.0, sc.rows - 1.0])
    c = np.array([0.0, sc.cols - 1.0, sc.cols - 1.0, 0.0])
    p = _enu(*sc.image_to_ground(r, c, height=0.0))
    if _area(p) < 0:  # counter-clockwise
        p = p[::-1]
    return p


def _area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: subject polygon clipped by a convex CCW polygon."""
    out = list(subject)
    for a, b in zip(clipper, np.roll(clipper, -1, axis=0)):
        inp, out = out, []
        if not inp:
            break

        def side(p, a=a, b=b):
            return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

        for k, q in enumerate(inp):
            p = inp[k - 1]
            sp, sq = side(p), side(q)
            if sq >= 0:
                if sp < 0:
                    out.append(p + (q - p) * sp / (sp - sq))
                out.append(q)
            elif sp >= 0:
                out.append(p + (q - p) * sp / (sp - sq))
    return np.array(out)


def _overlap(a, b) -> float:
    pa, pb = _footprint(a), _footprint(b)
    inter = _clip(pa, pb)
    return (_area(inter) if len(inter) >= 3 else 0.0) / _area(pa)


# --------------------------------------------------------------------------- #
# weights
# --------------------------------------------------------------------------- #
def test_point_weight() -> None:
    np.testing.assert_allclose(point_weight(0.5), 4.0 * np.eye(2))
    with pytest.raises(ValueError):
        point_weight(0.0)


def test_edge_weight_eigen_structure() -> None:
    sp, kappa = 0.5, 50.0
    theta = np.random.default_rng(0).uniform(-np.pi, np.pi, 200)
    W = edge_weight(theta, sigma_p=sp, kappa=kappa)
    assert W.shape == (200, 2, 2)
    np.testing.assert_array_equal(W, np.swapaxes(W, -1, -2))
    lam, vec = np.linalg.eigh(W)
    np.testing.assert_allclose(lam[:, 0], 1.0 / (kappa * sp) ** 2, rtol=1e-9)
    np.testing.assert_allclose(lam[:, 1], 1.0 / sp**2, rtol=1e-12)
    assert np.all(lam >= 0)
    # eigenvector of the small eigenvalue runs along the edge (cos, sin) in (x, y)
    d = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    np.testing.assert_allclose(np.abs(np.sum(vec[:, :, 0] * d, axis=-1)), 1.0, atol=1e-12)
    # W equals the inverse of the (regular) covariance of eq. 7
    R = np.stack([np.stack([np.cos(theta), -np.sin(theta)], -1), np.stack([np.sin(theta), np.cos(theta)], -1)], -2)
    cov = R @ np.diag([(kappa * sp) ** 2, sp**2]) @ np.swapaxes(R, -1, -2)
    np.testing.assert_allclose(W @ cov, np.broadcast_to(np.eye(2), W.shape), atol=1e-9)


def test_edge_weight_theta_zero_and_limits() -> None:
    np.testing.assert_allclose(edge_weight(0.0), np.diag([1.0 / 25.0**2, 1.0 / 0.25]), atol=1e-15)
    np.testing.assert_allclose(edge_weight(np.pi / 2), np.diag([4.0, 1.0 / 625.0]), atol=1e-15)
    # kappa -> inf: singular covariance, but a finite PSD weight (rank 1, across only)
    W = edge_weight(0.3, kappa=np.inf)
    assert np.all(np.isfinite(W))
    np.testing.assert_allclose(np.linalg.eigvalsh(W), [0.0, 4.0], atol=1e-12)


def test_edge_pair_at_right_angles_is_a_point() -> None:
    th = np.random.default_rng(1).uniform(0, np.pi, 50)
    W = edge_weight(th) + edge_weight(th + np.pi / 2)
    lam = np.linalg.eigvalsh(W)
    assert np.all(lam >= 1.0 / 0.5**2 - 1e-12)
    np.testing.assert_allclose(lam, 4.0 + 1.0 / 625.0, rtol=1e-12)  # exactly isotropic


# --------------------------------------------------------------------------- #
# perturbations
# --------------------------------------------------------------------------- #
def test_perturbation_statistics() -> None:
    n = 400_000
    d = perturbation(n, sigma=0.5, uniform=0.5, seed=11)
    se = np.sqrt(1 / 3) / np.sqrt(n)
    assert abs(d.mean()) < 5 * se
    np.testing.assert_allclose(d.std(), np.sqrt(0.25 + 0.25 / 3), rtol=5e-3)
    # normal part only / uniform part only
    assert np.allclose(perturbation(n, sigma=0.0, uniform=0.5, seed=1).std(), np.sqrt(1 / 12), rtol=5e-3)
    assert np.abs(perturbation(n, sigma=0.0, uniform=0.5, seed=1)).max() <= 0.5
    # reproducible
    np.testing.assert_array_equal(
        perturbation(10, sigma=1, uniform=1, seed=5), perturbation(10, sigma=1, uniform=1, seed=5)
    )
    assert not np.array_equal(perturbation(10, sigma=1, seed=5), perturbation(10, sigma=1, seed=6))


def test_perturb_ground_statistics(frame) -> None:
    g = grid_points(frame, spacing=5e3, role="control")
    assert len(g) > 1000
    p = perturb_ground(g, sigma=15.0, seed=2)
    d = p.xyz - p.true_xyz
    assert np.all(np.abs(d.mean(axis=0)) < 5 * 15 / np.sqrt(len(g)))
    np.testing.assert_allclose(d.std(axis=0), 15.0, rtol=0.08)
    np.testing.assert_array_equal(p.xyz, perturb_ground(g, seed=2).xyz)
    np.testing.assert_array_equal(p.true_xyz, g.true_xyz)
    np.testing.assert_array_equal(g.xyz, g.true_xyz)  # grid points start unperturbed
    np.testing.assert_array_equal(p.sigma, 15.0)


# --------------------------------------------------------------------------- #
# grids and observations
# --------------------------------------------------------------------------- #
def test_control_and_check_grids(block) -> None:
    ctrl = grid_points(block, spacing=20e3, role="control", heights=_terrain)
    chk = grid_points(block, spacing=20e3, offset=(10e3, 10e3), role="check", heights=_terrain, id_start=10_000)
    assert 350 < len(ctrl) < 550 and 350 < len(chk) < 550  # seed: 454 / 453
    # no common points: every check point is >= 10 sqrt(2) km from every control point (in plan)
    lat1, lon1, h1 = ecef_to_geodetic(ctrl.X, ctrl.Y, ctrl.Z)
    lat2, lon2, _ = ecef_to_geodetic(chk.X, chk.Y, chk.Z)
    a, b = _enu(*geodetic_to_ecef(lat1, lon1, 0.0)), _enu(*geodetic_to_ecef(lat2, lon2, 0.0))
    dist = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    assert dist.min() > 0.99 * 10e3 * np.sqrt(2)
    # nearest neighbours within a grid are 20 km apart; heights follow the terrain
    dd = np.linalg.norm(a[:, None, :] - a[None, :, :], axis=-1) + np.eye(len(a)) * 1e9
    np.testing.assert_allclose(dd.min(axis=1), 20e3, rtol=0.01)
    np.testing.assert_allclose(h1, _terrain(lat1, lon1), atol=1e-3)
    merged = GroundPoints.concatenate([ctrl, chk])
    assert set(np.unique(merged.role)) == {"control", "check"}
    with pytest.raises(ValueError):
        GroundPoints.concatenate([ctrl, ctrl])


def test_observe_exact_without_perturbation(block) -> None:
    g = grid_points(block, spacing=20e3, role="control")
    obs = observe(block, g, seed=None, image_uniform=0.0, image_sigma=0.0)
    np.testing.assert_array_equal(obs.row, obs.true_row)
    np.testing.assert_array_equal(obs.col, obs.true_col)
    idx = np.searchsorted(g.id, obs.point)
    for k, sc in enumerate(block):
        m = obs.frame == k
        assert m.sum() > 50
        i = idx[m]
        r, c = sc.ground_to_image(g.true_X[i], g.true_Y[i], g.true_Z[i])
        np.testing.assert_allclose(obs.row[m], r, atol=1e-9)
        np.testing.assert_allclose(obs.col[m], c, atol=1e-9)
        assert np.all((obs.row[m] >= 0) & (obs.row[m] <= sc.rows - 1))
        assert np.all((obs.col[m] >= 0) & (obs.col[m] <= sc.cols - 1))
        # complete: every point inside the frame is observed
        ra, ca = sc.ground_to_image(g.X, g.Y, g.Z)
        inside = (ra >= 0) & (ra <= sc.rows - 1) & (ca >= 0) & (ca <= sc.cols - 1)
        assert inside.sum() == m.sum()
    assert np.all(obs.kind == "point") and np.all(np.isnan(obs.theta))
    np.testing.assert_allclose(obs.weight, np.broadcast_to(4.0 * np.eye(2), (len(obs), 2, 2)))


def test_observe_perturbation(block) -> None:
    g = grid_points(block, spacing=10e3, role="check")
    obs = observe(block, g, seed=5)
    d = np.concatenate([obs.row - obs.true_row, obs.col - obs.true_col])
    assert len(obs) > 2500
    np.testing.assert_allclose(d.std(), np.sqrt(0.25 + 1 / 12), rtol=0.05)
    assert abs(d.mean()) < 5 * 0.58 / np.sqrt(d.size)
    obs2 = observe(block, g, seed=5)
    np.testing.assert_array_equal(obs.row, obs2.row)
    for k, sc in enumerate(block):  # true point inside; measured within the error bound
        m = obs.frame == k
        assert np.all((obs.true_row[m] >= 0) & (obs.true_row[m] <= sc.rows - 1))
        assert np.all((obs.row[m] > -4) & (obs.row[m] < sc.rows + 3))


def test_airborne_grid_and_observe() -> None:
    sc = airborne.atm(rows=400, attitude=airborne.Attitude.turbulent(400, seed=1, roll_sigma=1e-3, pitch_sigma=1e-3,
                                                                       yaw_sigma=1e-3))  # fmt: skip
    g = grid_points(sc, spacing=200.0, role="control", heights=lambda X, Y: 50.0 + 0.01 * X)
    assert len(g) > 10
    np.testing.assert_allclose(g.Z, 50.0 + 0.01 * g.X)
    obs = observe(sc, g, seed=None, image_uniform=0.0, image_sigma=0.0)
    assert len(obs) == len(g)
    r, _ = sc.ground_to_image(g.X, g.Y, g.Z)
    np.testing.assert_allclose(obs.row, r[np.searchsorted(g.id, obs.point)])


# --------------------------------------------------------------------------- #
# block and tie points
# --------------------------------------------------------------------------- #
def test_block_overlaps(block) -> None:
    assert len(block) == 9
    along = [_overlap(block[s * 3 + f], block[s * 3 + f + 1]) for s in range(3) for f in range(2)]
    side = [_overlap(block[s * 3 + f], block[(s + 1) * 3 + f]) for s in range(2) for f in range(3)]
    np.testing.assert_allclose(along, 0.15, atol=0.02)
    np.testing.assert_allclose(side, 0.60, atol=0.03)
    # frames of one strip are windows of one physical orbit
    a, b = block[0], block[1]
    t = np.array([0.0, 5.0])
    dt = b.orbit.mean_anomaly0 - a.orbit.mean_anomaly0
    pa, _ = a.orbit.position_velocity_ecef(t + dt / a.orbit.mean_motion)
    pb, _ = b.orbit.position_velocity_ecef(t)
    np.testing.assert_allclose(pa, pb, atol=1e-3)
    # seeded random deviations
    assert not np.allclose(block[0].deviations, block[1].deviations)
    np.testing.assert_array_equal(block_of_strips(seed=7)[4].deviations, block[4].deviations)
    assert np.all(block_of_strips(seed=None)[0].deviations == 0)


def test_tie_points_in_overlaps(block) -> None:
    tie = tie_points(block, per_overlap=8, seed=3, heights=_terrain, id_start=50_000)
    assert np.all(tie.role == "tie")
    assert len(tie) >= 8 * 12  # at least the 6 along-strip and 6 across-strip overlaps
    lat, lon, h = ecef_to_geodetic(tie.true_X, tie.true_Y, tie.true_Z)
    np.testing.assert_allclose(h, _terrain(lat, lon), atol=1e-3)
    obs = observe(block, tie, seed=1)
    counts = np.bincount(np.searchsorted(tie.id, obs.point), minlength=len(tie))
    assert counts.min() >= 2
    np.testing.assert_array_equal(tie.sigma[:, :2], np.inf)
    np.testing.assert_array_equal(
        tie.id, tie_points(block, per_overlap=8, seed=3, heights=_terrain, id_start=50_000).id
    )


# --------------------------------------------------------------------------- #
# edge points
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("configuration", sorted(EDGE_CONFIGURATIONS))
def test_edge_configurations(frame, configuration) -> None:
    n = 41
    g, obs = edge_points(frame, n_pairs=n, seed=configuration, configuration=configuration, id_start=7)
    assert len(obs) == 2 * n and np.all(obs.kind == "edge") and np.all(g.role == "control")
    shared = configuration in (1, 2, 3, 4, 9)
    assert len(g) == (n if shared else 2 * n)
    assert np.all(np.isin(obs.point, g.id))
    # the true image points are the projections of the true ground points
    idx = np.searchsorted(g.id, obs.point)
    r, c = frame.ground_to_image(g.true_X[idx], g.true_Y[idx], g.true_Z[idx])
    np.testing.assert_allclose(r, obs.true_row, atol=1e-6)
    np.testing.assert_allclose(c, obs.true_col, atol=1e-6)
    assert np.all((obs.true_row >= 0) & (obs.true_row <= frame.rows - 1))
    tr, tc = obs.true_row.reshape(n, 2), obs.true_col.reshape(n, 2)
    th = obs.theta.reshape(n, 2)
    if configuration in (1, 2, 3, 4, 9):
        np.testing.assert_array_equal(tr[:, 0], tr[:, 1])
    if configuration in (5, 6, 7, 8):
        dev = np.maximum(np.abs(tr[:, 0] - tr[:, 1]), np.abs(tc[:, 0] - tc[:, 1]))
        assert dev.max() <= 100.0 and dev.max() > 50.0
    ang = np.rad2deg(np.abs(np.remainder(th[:, 0] - th[:, 1] + np.pi / 2, np.pi) - np.pi / 2))  # acute, 0..90
    if configuration in (1, 5, 9):
        np.testing.assert_allclose(ang, 90.0, atol=1e-9)
    elif configuration in (2, 6):
        assert ang.min() >= 60.0 - 1e-9
    elif configuration in (3, 7):
        assert ang.min() >= 30.0 - 1e-9 and ang.min() < 60.0
    else:
        assert ang.min() < 30.0
    if configuration == 9:  # a pair is one control point: isotropic weight
        W = obs.weight.reshape(n, 2, 2, 2).sum(axis=1)
        np.testing.assert_allclose(np.linalg.eigvalsh(W), 4.0 + 1 / 625, rtol=1e-9)


def test_edge_perturbation_along_and_across(frame) -> None:
    n = 20_000
    _, obs = edge_points(frame, n_pairs=n, seed=4, configuration=10)
    dx, dy = obs.col - obs.true_col, obs.row - obs.true_row
    along = dx * np.cos(obs.theta) + dy * np.sin(obs.theta)
    across = -dx * np.sin(obs.theta) + dy * np.cos(obs.theta)
    np.testing.assert_allclose(along.std(), np.sqrt(25.0**2 + 1 / 12), rtol=0.02)
    np.testing.assert_allclose(across.std(), np.sqrt(0.25 + 1 / 12), rtol=0.02)
    assert abs(across.mean()) < 0.02 and abs(along.mean()) < 1.0
    W = edge_weight(obs.theta[:5], sigma_p=0.5, kappa=50.0)
    np.testing.assert_allclose(obs.weight[:5], W)
    _, obs2 = edge_points(frame, n_pairs=n, seed=4, configuration=10)
    np.testing.assert_array_equal(obs.row, obs2.row)


def test_edge_grid_sizes(frame) -> None:
    for n in (25, 41, 61, 85, 113, 145):
        g, _ = edge_points(frame, n_pairs=n, seed=0, configuration=1)
        assert len(g) == n
    with pytest.raises(ValueError):
        edge_points(frame, n_pairs=30, seed=0, configuration=1)
    with pytest.raises(ValueError):
        edge_points(frame, n_pairs=25, seed=0, configuration=11)
