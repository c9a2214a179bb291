"""Windowed bundle adjustment (vision/bundle_adjust.py) on synthetic scenes with known truth."""
from __future__ import annotations

import numpy as np

from vbnav.vision.bundle_adjust import bundle_adjust, bundle_problem, exp_so3, tangent_axes

F = 700.0  # focal length, px


def _scene(seed: int, frames: int = 7, points: int = 150):
    """A camera driving forward 1 m per frame while turning 3 degrees per frame, points 5-40 m ahead."""
    rng = np.random.default_rng(seed)
    poses_wc = []
    W = np.eye(4)
    for _ in range(frames):
        poses_wc.append(W.copy())
        step = np.eye(4)
        step[:3, :3] = exp_so3(np.array([0.0, np.deg2rad(3.0), 0.0]))
        step[:3, 3] = [0.0, 0.0, 1.0]
        W = W @ step
    poses_cw = np.array([np.linalg.inv(W) for W in poses_wc])
    X = np.column_stack((rng.uniform(-15, 15, points), rng.uniform(-3, 2, points), rng.uniform(5, 40, points)))
    obs_f, obs_p, obs_r = [], [], []
    for k, M in enumerate(poses_cw):
        Xc = X @ M[:3, :3].T + M[:3, 3]
        vis = (Xc[:, 2] > 1.0) & (np.abs(Xc[:, 0] / Xc[:, 2]) < 0.9) & (np.abs(Xc[:, 1] / Xc[:, 2]) < 0.3)
        for j in np.flatnonzero(vis):
            ray = Xc[j] / np.linalg.norm(Xc[j])
            obs_f.append(k)
            obs_p.append(j)
            obs_r.append(ray)
    return poses_cw, X, np.array(obs_f), np.array(obs_p), np.array(obs_r), rng


def _noisy_rays(rays, rng, sigma_px):
    E = tangent_axes(rays)
    d = rng.normal(0, sigma_px / F, (len(rays), 2))
    out = rays + np.einsum("oa,oai->oi", d, E)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _scale_of(poses_cw, first=0, last=-1):
    c = [-M[:3, :3].T @ M[:3, 3] for M in poses_cw]
    return np.linalg.norm(c[last] - c[first])


def test_noisy_poses_and_points_converge_to_truth():
    poses, X, f, p, rays, rng = _scene(0)
    rays = _noisy_rays(rays, rng, 0.5)
    fixed = np.zeros(len(poses), bool)
    fixed[:2] = True
    start = poses.copy()
    for k in range(2, len(poses)):
        D = np.eye(4)
        D[:3, :3] = exp_so3(rng.normal(0, np.deg2rad(0.3), 3))
        D[:3, 3] = rng.normal(0, 0.1, 3)
        start[k] = D @ poses[k]
    X0 = X * rng.uniform(0.97, 1.03, (len(X), 1))
    res = bundle_adjust(start, fixed, X0, np.zeros(len(X), bool), f, p, rays, F, sigma_px=0.5)
    pos_err = [np.linalg.norm(-a[:3, :3].T @ a[:3, 3] + b[:3, :3].T @ b[:3, 3]) for a, b in zip(res.poses_cw, poses)]
    assert max(pos_err) < 0.03, pos_err  # from 0.1 m per axis; 7 m travelled
    start_err = [np.linalg.norm(-a[:3, :3].T @ a[:3, 3] + b[:3, :3].T @ b[:3, 3]) for a, b in zip(start, poses)]
    assert max(start_err) > 0.1
    seen = np.unique(p)
    assert np.median(np.linalg.norm(res.points[seen] - X[seen], axis=1) / X[seen, 2]) < 0.015  # from 3 %
    assert np.median(res.residual_px) < 1.0  # at the 0.5 px noise
    assert res.cost_after < 0.1 * res.cost_before


def test_scale_drift_in_the_window_is_removed():
    """Poses after the fixed two drift in scale by 4 % per frame and the points follow (what a
    monocular front end does): the adjustment brings the scale back to that of the fixed poses."""
    poses, X, f, p, rays, rng = _scene(1)
    rays = _noisy_rays(rays, rng, 1.0)
    drift = poses.copy()
    for k in range(2, len(poses)):
        c_true = -poses[k][:3, :3].T @ poses[k][:3, 3]
        c_prev = -poses[1][:3, :3].T @ poses[1][:3, 3]
        c = c_prev + (c_true - c_prev) * 1.04 ** (k - 1)
        drift[k][:3, 3] = -poses[k][:3, :3] @ c
    assert abs(_scale_of(drift) / _scale_of(poses) - 1) > 0.15
    fixed = np.zeros(len(poses), bool)
    fixed[:2] = True
    X0 = X * 1.1
    res = bundle_adjust(drift, fixed, X0, np.zeros(len(X), bool), f, p, rays, F)
    assert abs(_scale_of(res.poses_cw) / _scale_of(poses) - 1) < 0.01


def test_outliers_do_not_pull_the_solution():
    """10 % of the observations 30 px off: the Huber loss keeps the poses within a few cm."""
    poses, X, f, p, rays, rng = _scene(2)
    rays = _noisy_rays(rays, rng, 0.5)
    bad = rng.random(len(rays)) < 0.1
    E = tangent_axes(rays)
    rays[bad] = rays[bad] + 30.0 / F * E[bad, 0]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    fixed = np.zeros(len(poses), bool)
    fixed[:2] = True
    res = bundle_adjust(poses, fixed, X, np.zeros(len(X), bool), f, p, rays, F, sigma_px=0.5)
    pos_err = [np.linalg.norm(-a[:3, :3].T @ a[:3, 3] + b[:3, :3].T @ b[:3, 3]) for a, b in zip(res.poses_cw, poses)]
    assert max(pos_err) < 0.03, pos_err  # measured 14 mm on 2026-12-04, bar 2x
    assert np.median(res.residual_px[bad]) > 20  # the outliers stay outliers, to be rejected by the caller


def test_fixed_points_and_poses_do_not_move():
    poses, X, f, p, rays, rng = _scene(3, frames=4, points=60)
    fixed_pose = np.array([True, False, False, True])
    fixed_point = np.zeros(len(X), bool)
    fixed_point[::2] = True
    res = bundle_adjust(poses, fixed_pose, X + 0.01, fixed_point, f, p, _noisy_rays(rays, rng, 1.0), F)
    assert np.array_equal(res.poses_cw[fixed_pose], poses[fixed_pose])
    assert np.array_equal(res.points[fixed_point], X[fixed_point] + 0.01)


def test_analytic_jacobian_matches_finite_differences():
    """At a point away from the start (rotation updates of a few degrees), every column of the
    analytic Jacobian agrees with central differences of the residuals."""
    poses, X, f, p, rays, rng = _scene(4, frames=4, points=30)
    fixed_pose = np.array([True, False, False, False])
    fixed_point = np.zeros(len(X), bool)
    fixed_point[::3] = True
    prob = bundle_problem(poses, fixed_pose, X, fixed_point, f, p, rays, F)
    x = prob.x0 + rng.normal(0, 0.05, len(prob.x0))  # 3 degrees of rotation update, 5 cm, 5 cm
    J = prob.jacobian_dense(x)
    h = 1e-6
    num = np.column_stack([(prob.residuals(x + h * e) - prob.residuals(x - h * e)) / (2 * h)
                           for e in np.eye(len(x))])
    assert np.abs(J - num).max() < 1e-5 * max(1.0, np.abs(num).max())
    assert np.abs(num).max() > 1.0  # px per unit: the check is not of an empty matrix
