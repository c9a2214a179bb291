"""Structure on the sphere: spherical disparity (11.11) and rotation-only depth update (11.13).

A landmark seen along unit ray n from one camera pose and along n' from
another, related by P' = R P + T, satisfies (11.14)

    D' n' = R D n + T,   i.e.   [n', -R n] (D', D)^T = T        (11.11)

a 3x2 least-squares problem per landmark. Its normal matrix is
[[1, -c], [-c, 1]] with c = n' . R n = cos(parallax), so its conditioning is
the parallax angle itself: det = sin^2(parallax). Nothing here assumes z > 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Reconstruction:
    """Radial depths of landmarks from two views; ``valid`` passed the gates."""

    depth_cur: np.ndarray  # D' along n' (second view)
    depth_ref: np.ndarray  # D along n (first view)
    parallax: np.ndarray  # rad, angle between n' and R n
    residual: np.ndarray  # |[n', -R n](D', D) - T| (ray miss distance), same unit as T
    valid: np.ndarray  # bool


def spherical_disparity(rays_ref: np.ndarray, rays_cur: np.ndarray, R: np.ndarray, T: np.ndarray,
                        min_parallax: float = np.deg2rad(0.5), max_residual_ratio: float = 0.05,
                        ) -> Reconstruction:
    """Solve (11.11) for every landmark, vectorised.

    rays_ref (N, 3) in the first view, rays_cur (N, 3) in the second,
    (R, T) maps first-view coordinates to second-view coordinates: one (3, 3), (3,) for all, or one
    per landmark, (N, 3, 3) and (N, 3) (monocular candidates each have their own first view).
    Gates: parallax >= min_parallax (the conditioning of the 3x2 system), both
    depths positive, and the rays' miss distance <= max_residual_ratio * |T|.
    """
    n = np.asarray(rays_ref, float).reshape(-1, 3)
    n_cur = np.asarray(rays_cur, float).reshape(-1, 3)
    R = np.asarray(R, float)
    per_row = R.ndim == 3
    T = np.asarray(T, float).reshape(-1, 3) if per_row else np.asarray(T, float).reshape(3)
    Rn = np.einsum("nij,nj->ni", R, n) if per_row else n @ R.T
    c = np.einsum("ij,ij->i", n_cur, Rn)  # cos(parallax)
    p = np.einsum("ij,ij->i", n_cur, T) if per_row else n_cur @ T  # n' . T
    q = -np.einsum("ij,ij->i", Rn, T) if per_row else -(Rn @ T)  # -(R n) . T
    det = 1.0 - c * c
    safe = np.where(det > 1e-15, det, 1.0)
    # [[1, -c], [-c, 1]]^-1 = [[1, c], [c, 1]] / det
    d_cur = (p + c * q) / safe
    d_ref = (c * p + q) / safe
    miss = d_cur[:, None] * n_cur - d_ref[:, None] * Rn - T
    residual = np.linalg.norm(miss, axis=1)
    parallax = np.arccos(np.clip(c, -1.0, 1.0))
    valid = ((det > 1e-15) & (parallax >= min_parallax) & (d_cur > 0) & (d_ref > 0)
             & (residual <= max_residual_ratio * np.maximum(np.linalg.norm(T, axis=-1), 1e-300)))
    return Reconstruction(d_cur, d_ref, parallax, residual, valid)


def depth_update_3(rays_ref: np.ndarray, rays_cur: np.ndarray, R: np.ndarray, depths_ref: np.ndarray
                   ) -> np.ndarray:
    """Equation (11.13) for three non-collinear points: D' = F'^-1 R F D, no translation needed.

    F = [-2 n_1, n_2, n_3] maps the depth vector to the diagonal v_1 + v_2 of
    the plane segment spanned by the three points.
    """
    n = np.asarray(rays_ref, float).reshape(3, 3)
    m = np.asarray(rays_cur, float).reshape(3, 3)
    F = np.column_stack((-2.0 * n[0], n[1], n[2]))
    F_cur = np.column_stack((-2.0 * m[0], m[1], m[2]))
    return np.linalg.solve(F_cur, np.asarray(R, float) @ F @ np.asarray(depths_ref, float).reshape(3))


def depth_update(rays_ref: np.ndarray, rays_cur: np.ndarray, R: np.ndarray, depths_ref: np.ndarray
                 ) -> np.ndarray:
    """N-point generalisation of (11.13): least squares over the difference vectors

        D'_j n'_j - D'_1 n'_1 = R (D_j n_j - D_1 n_1) =: b_j,   j = 2..N.

    For a given D'_1 each D'_j is its own 1-D least squares, D'_j = n'_j . (D'_1 n'_1 + b_j),
    leaving the residual (I - n'_j n'_j^T)(D'_1 n'_1 + b_j); minimising over D'_1
    is then a scalar least squares. O(N), exact for noise-free data, and T never enters.
    """
    n = np.asarray(rays_ref, float).reshape(-1, 3)
    m = np.asarray(rays_cur, float).reshape(-1, 3)
    D = np.asarray(depths_ref, float).reshape(-1)
    if len(n) < 3:
        raise ValueError(f"depth update needs at least 3 points, got {len(n)}")
    P = (D[:, None] * n) @ np.asarray(R, float).T  # R D_j n_j
    b = P[1:] - P[0]
    mj = m[1:]
    # Project n'_1 and b_j onto the plane orthogonal to n'_j.
    a_perp = m[0] - (mj @ m[0])[:, None] * mj
    b_perp = b - np.einsum("ij,ij->i", mj, b)[:, None] * mj
    denom = np.einsum("ij,ij->", a_perp, a_perp)
    if denom < 1e-18:
        raise ValueError("depth update is singular: all rays are parallel to the first one")
    d1 = -np.einsum("ij,ij->", a_perp, b_perp) / denom
    dj = mj @ (d1 * m[0]) + np.einsum("ij,ij->i", mj, b)
    return np.concatenate(([d1], dj))
