"""Synthetic scenes with known truth for spherical disparity (11.11), the depth update (11.13) and
motion recovery (11.15-11.17), at metre scale and at the millimetre scale of the endoscope case."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vbnav.vision.geometry import absolute_orientation, rot_x, rot_y, rot_z, rotation_angle
from vbnav.vision.motion import recover_motion, recover_motion_robust
from vbnav.vision.spherical import depth_update, depth_update_3, spherical_disparity


def random_rotation(rng, max_angle):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return cv2.Rodrigues(axis * rng.uniform(0, max_angle))[0]


def scene(rng, n, scale, all_around=False):
    """Points in the reference frame and a motion (R, T): X_cur = R X_ref + T."""
    if all_around:  # landmarks in every direction (spherical camera)
        d = rng.normal(size=(n, 3))
        P = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2, 6, (n, 1)) * scale
    else:
        P = np.column_stack((rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(3, 10, n))) * scale
    R = random_rotation(rng, 0.3)
    T = rng.normal(0, 0.4, 3) * scale
    return P, R, T


def unit(X):
    return X / np.linalg.norm(X, axis=1, keepdims=True)


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_spherical_disparity_recovers_radial_depths(rng, scale):
    P, R, T = scene(rng, 40, scale, all_around=True)
    X = P @ R.T + T
    rec = spherical_disparity(unit(P), unit(X), R, T)
    assert rec.valid.mean() > 0.9
    v = rec.valid
    np.testing.assert_allclose(rec.depth_ref[v], np.linalg.norm(P, axis=1)[v], rtol=1e-9)
    np.testing.assert_allclose(rec.depth_cur[v], np.linalg.norm(X, axis=1)[v], rtol=1e-9)
    # Parallax is the conditioning: it matches the angle between n' and R n.
    cosang = np.einsum("ij,ij->i", unit(X), unit(P) @ R.T)
    np.testing.assert_allclose(rec.parallax, np.arccos(np.clip(cosang, -1, 1)), atol=1e-9)


def test_spherical_disparity_gates_low_parallax_and_inconsistent_rays(rng):
    P, R, _ = scene(rng, 20, 1.0)
    T = np.array([1e-4, 0, 0])  # almost pure rotation: no parallax
    X = P @ R.T + T
    rec = spherical_disparity(unit(P), unit(X), R, T, min_parallax=np.deg2rad(0.5))
    assert not rec.valid.any()
    T = np.array([0.5, 0, 0])
    X = P @ R.T + T
    bad = unit(X)
    bad[:5] = unit(bad[:5] + np.array([0, 0.2, 0]))  # rays that do not meet
    rec = spherical_disparity(unit(P), bad, R, T)
    assert not rec.valid[:5].any() and rec.valid[5:].mean() > 0.8


def test_spherical_disparity_with_a_motion_per_landmark_equals_one_at_a_time(rng):
    """Monocular candidates each carry their own first view: the batched (N, 3, 3) / (N, 3) form
    gives what N single-motion calls give, gates included."""
    n = 30
    P = scene(rng, n, 1.0)[0]
    Rs = np.array([random_rotation(rng, 0.2) for _ in range(n)])
    Ts = rng.normal(0, 0.3, (n, 3))
    Ts[:4] *= 1e-4  # no parallax: gated out
    X = np.einsum("nij,nj->ni", Rs, P) + Ts
    batch = spherical_disparity(unit(P), unit(X), Rs, Ts, min_parallax=np.deg2rad(1.0))
    assert not batch.valid[:4].any() and batch.valid[4:].mean() > 0.8
    for k in range(n):
        one = spherical_disparity(unit(P[k:k + 1]), unit(X[k:k + 1]), Rs[k], Ts[k], min_parallax=np.deg2rad(1.0))
        assert one.valid[0] == batch.valid[k]
        if one.valid[0]:  # (the gated rows are ill-conditioned: rounding differs between the two forms)
            np.testing.assert_allclose([one.depth_ref[0], one.residual[0]], [batch.depth_ref[k], batch.residual[k]],
                                       rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(batch.depth_ref[batch.valid], np.linalg.norm(P, axis=1)[batch.valid], rtol=1e-9)


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_depth_update_needs_rotation_only(rng, scale):
    P, R, T = scene(rng, 30, scale)
    X = P @ R.T + T
    D, D_true = np.linalg.norm(P, axis=1), np.linalg.norm(X, axis=1)
    np.testing.assert_allclose(depth_update_3(unit(P[:3]), unit(X[:3]), R, D[:3]), D_true[:3], rtol=1e-9)
    np.testing.assert_allclose(depth_update(unit(P), unit(X), R, D), D_true, rtol=1e-9)
    # With noisy rays the N-point least squares beats the 3-point formula.
    noisy = unit(unit(X) + rng.normal(0, 1e-3, X.shape))
    err_n = np.abs(depth_update(unit(P), noisy, R, D) - D_true)[:3]
    err_3 = np.abs(depth_update_3(unit(P[:3]), noisy[:3], R, D[:3]) - D_true[:3])
    assert err_n.mean() < err_3.mean()


def test_absolute_orientation_never_returns_a_reflection(rng):
    P = rng.normal(size=(10, 3))
    Q = P * np.array([1, 1, -1])  # mirror image: the best orthogonal map is a reflection
    R, _, s = absolute_orientation(P, Q)
    assert np.linalg.det(R) == pytest.approx(1.0) and s == 1.0
    # the best rotation keeps the two large axes and turns the mirrored one: the fitted scale shrinks
    Pflat = P * np.array([3.0, 2.0, 0.1])
    R, _, s = absolute_orientation(Pflat, Pflat * np.array([1, 1, -1]), with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0) and 0 < s < 1
    R_true = random_rotation(rng, 2.0)
    R, T, _ = absolute_orientation(P, P @ R_true.T + [1, 2, 3])
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(T, [1, 2, 3], atol=1e-12)


@pytest.mark.parametrize("n", [3, 4, 50])
def test_absolute_orientation_recovers_rotation_translation_and_scale(rng, n):
    P = rng.normal(size=(n, 3)) * [4.0, 1.0, 2.0]
    R_true, t_true, s_true = random_rotation(rng, 3.0), rng.normal(size=3) * 5, 0.37
    Q = s_true * P @ R_true.T + t_true
    R, t, s = absolute_orientation(P, Q, with_scale=True)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert s == pytest.approx(s_true, rel=1e-12)
    # SE(3) only: the scale stays 1, the centroids still meet
    R, t, s = absolute_orientation(P, Q)
    assert s == 1.0
    np.testing.assert_allclose(R, R_true, atol=1e-9)
    np.testing.assert_allclose(R @ P.mean(0) + t, Q.mean(0), atol=1e-12)
    # weights: outliers with zero weight change nothing
    Qo = Q.copy()
    Qo[0] += 100.0
    w = np.ones(n)
    w[0] = 0.0
    if n > 3:
        R, t, s = absolute_orientation(P, Qo, weights=w, with_scale=True)
        np.testing.assert_allclose(R, R_true, atol=1e-12)
        np.testing.assert_allclose(t, t_true, atol=1e-12)
        assert s == pytest.approx(s_true, rel=1e-12)


def test_absolute_orientation_solves_a_batch_like_one_problem_at_a_time(rng):
    P = rng.normal(size=(6, 5, 3))
    Q = rng.normal(size=(6, 5, 3))
    w = rng.uniform(0.5, 2.0, size=(6, 5))
    R, t, s = absolute_orientation(P, Q, weights=w, with_scale=True)
    assert R.shape == (6, 3, 3) and t.shape == (6, 3) and s.shape == (6,)
    for k in range(6):
        Rk, tk, sk = absolute_orientation(P[k], Q[k], weights=w[k], with_scale=True)
        np.testing.assert_allclose(R[k], Rk, atol=1e-12)
        np.testing.assert_allclose(t[k], tk, atol=1e-12)
        assert s[k] == pytest.approx(sk, rel=1e-12)
        assert np.linalg.det(R[k]) == pytest.approx(1.0)


@pytest.mark.parametrize("overrelax", [1.0, 2.0])
@pytest.mark.parametrize("scale", [1.0, 1e-3])
@pytest.mark.parametrize("n", [3, 4, 6, 50])
def test_alternation_recovers_exact_motion(rng, scale, n, overrelax):
    P, R, T = scene(rng, n, scale)
    X = P @ R.T + T
    prior = (R @ rot_y(0.03) @ rot_x(0.02), T + 0.03 * scale)  # the previous frame's pose
    est = recover_motion(P, unit(X), prior=prior, tol=1e-12, overrelax=overrelax)
    assert est.converged
    assert rotation_angle(est.R.T @ R) < 1e-6
    assert np.linalg.norm(est.T - T) < 1e-6 * scale
    np.testing.assert_allclose(est.depths, np.linalg.norm(X, axis=1), rtol=1e-6)
    assert est.residual < 1e-7


def test_alternation_from_constant_depth_guess_and_all_around_rays(rng):
    """D_init for every landmark (first frame), landmarks behind the camera too (spherical model)."""
    P, R, T = scene(rng, 30, 1.0, all_around=True)
    X = P @ R.T + T
    assert (X[:, 2] < 0).any()
    est = recover_motion(P, unit(X), depths=4.0, tol=1e-12, max_iter=2000)
    assert rotation_angle(est.R.T @ R) < 1e-6 and np.linalg.norm(est.T - T) < 1e-6


def test_alternation_matches_sqpnp_accuracy_and_converges_in_few_iterations(rng):
    f, c = 500.0, np.array([320.0, 240.0])
    K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1]])
    ours, sqp, iters = [], [], []
    for _ in range(60):
        P, R, T = scene(rng, 50, 1.0)
        X = P @ R.T + T
        px = X[:, :2] / X[:, 2:] * f + c + rng.normal(0, 1.0, (50, 2))
        rays = unit(np.column_stack(((px - c) / f, np.ones(50))))
        prior = (R @ rot_z(0.02), T + rng.normal(0, 0.05, 3))
        est = recover_motion(P, rays, prior=prior)
        plain = recover_motion(P, rays, prior=prior, overrelax=1.0)
        assert rotation_angle(est.R.T @ plain.R) < 1e-4  # over-relaxation keeps the fixed point
        iters.append(est.iterations)
        ours.append(rotation_angle(est.R.T @ R))
        _, rv, _ = cv2.solvePnP(P, px, K, None, flags=cv2.SOLVEPNP_SQPNP)
        sqp.append(rotation_angle(cv2.Rodrigues(rv)[0].T @ R))
    assert np.median(ours) <= 1.05 * np.median(sqp)
    assert np.median(iters) <= 10


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_robust_motion_rejects_outliers(rng, scale):
    P, R, T = scene(rng, 60, scale)
    X = P @ R.T + T
    rays = unit(unit(X) + rng.normal(0, 5e-4, X.shape))
    out = rng.choice(60, 12, replace=False)  # 20 % gross mismatches
    rays[out] = unit(rng.normal(size=(12, 3)) * [0.3, 0.3, 0] + [0, 0, 1])
    est = recover_motion_robust(P, rays, depths=6.0 * scale, rng=np.random.default_rng(3))
    assert rotation_angle(est.R.T @ R) < 1e-3  # measured 5.1e-4 rad on 2026-11-30, bar 2x
    assert np.linalg.norm(est.T - T) < 0.008 * scale  # measured 0.0038 * scale on 2026-11-30, bar 2x
    assert not est.inliers[out].any() and est.inliers.sum() >= 45
    plain = recover_motion(P, rays, depths=6.0 * scale)
    assert rotation_angle(plain.R.T @ R) > 5 * rotation_angle(est.R.T @ R)


def test_landmark_weights_let_well_known_points_dominate(rng):
    """Half the landmarks carry position errors too small for the inlier gate to catch (poorly
    triangulated); weighting them down recovers the motion of the well-known half."""
    P, R, T = scene(rng, 80, 1.0)
    rays = unit(P @ R.T + T)
    noisy = np.arange(80) >= 40
    P_used = P.copy()
    P_used[noisy] += rng.normal(0, 0.01, (40, 3)) + [0.02, 0.0, 0.0]  # biased along x
    w = np.where(noisy, 0.01, 1.0)
    kw = dict(depths=6.0, threshold=0.01, rng=np.random.default_rng(1))
    plain = recover_motion_robust(P_used, rays, **kw)
    weighted = recover_motion_robust(P_used, rays, weights=w, **kw)
    # measured 0.011 x on 2026-11-30, bar 2x
    assert np.linalg.norm(weighted.T - T) < 0.025 * np.linalg.norm(plain.T - T)
    assert rotation_angle(weighted.R.T @ R) < 2e-5  # measured 9e-6 rad on 2026-11-30, bar 2x
