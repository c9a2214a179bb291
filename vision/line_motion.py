"""Segments a single stereo pair cannot reconstruct, triangulated from the robot's motion.

A segment nearly parallel to the image rows has no disparity of its own (vision/line_segments.py leaves
those within ``min_epipolar_angle_deg`` out): box tops and bottoms and wall-floor lines seen frontally.
The robot's motion gives a second baseline: the same line seen from an earlier keyframe (pose known)
back-projects to another plane through that camera centre, and the two planes meet in the 3D line. The
baseline is well placed exactly when the stereo one is not: driving toward a frontal edge moves the
camera across the edge's plane.

Matching across frames first removes the rotation between the two views (the keyframe's segments mapped
by the infinite homography K R_now^T R_key K^-1: a robot turning 10 degrees between the frames moves every
line by ~70 px, mostly along a horizontal line), then uses direction, the contrast on both sides, the
distance across the line (the parallax the triangulation needs, at most ``max_shift_px``) and the gap
along it (``max_along_px``; a midpoint-distance gate refused most pairs of a turning robot); every candidate pair
of a segment becomes a rival hypothesis (one group), and the DLM's verification from three viewpoints
decides, as for stereo rivals (Fig. 11.4). The covariance comes from perturbing each image line by
``sigma_perp_px`` across itself (finite differences); a pair whose endpoints come out with a sigma above
``max_sigma_m`` (too little parallax across the line: motion along it) is not used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbnav.vision.line_segments import Segments2D, Segments3D


@dataclass(frozen=True)
class MotionParams:
    max_angle_deg: float = 20.0        # handles the segments stereo leaves out (below this to the rows)
    max_shift_px: float = 60.0         # parallax across the line allowed between the keyframe and now (rotation removed)
    max_along_px: float = 80.0         # shift along the line allowed (the segments must still overlap)
    match_angle_deg: float = 6.0
    side_tol: float = 25.0             # grey levels, both sides
    min_plane_angle_deg: float = 0.5   # the two back-projected planes must differ this much (the covariance says how well)
    sigma_perp_px: float = 0.3
    max_candidates: int = 3
    max_sigma_m: float = 0.1           # endpoint sigma (largest axis) above which a pair is not used


def _plane(seg: np.ndarray, R: np.ndarray, t: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    """World plane (n, d) with n.X = d through the camera centre and the image line of ``seg``."""
    a = R @ (K_inv @ np.array([seg[0], seg[1], 1.0]))
    b = R @ (K_inv @ np.array([seg[2], seg[3], 1.0]))
    n = np.cross(a, b)
    n /= np.linalg.norm(n)
    return np.append(n, n @ t)


def _line_from_planes(p: np.ndarray, q: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
    d = np.cross(p[:3], q[:3])
    s = np.linalg.norm(d)
    if s < 1e-9:
        return None
    d /= s
    A = np.vstack((p[:3], q[:3], d))
    x0 = np.linalg.solve(A, np.array([p[3], q[3], 0.0]))
    return x0, d


def _endpoints(seg: np.ndarray, R: np.ndarray, t: np.ndarray, K_inv: np.ndarray, x0, d) -> np.ndarray:
    """Points of the 3D line closest to the rays of ``seg``'s endpoints (from camera R, t)."""
    out = []
    for u, v in (seg[0:2], seg[2:4]):
        r = R @ (K_inv @ np.array([u, v, 1.0]))
        r /= np.linalg.norm(r)
        # Closest points between line x0 + s d and ray t + w r.
        w0 = x0 - t
        a, b, c = d @ d, d @ r, r @ r
        dd, e = d @ w0, r @ w0
        den = a * c - b * b
        s = (b * e - c * dd) / den if abs(den) > 1e-12 else 0.0
        out.append(x0 + s * d)
    return np.array(out)


def triangulate_two_views(seg_k: np.ndarray, R_k, t_k, seg_j: np.ndarray, R_j, t_j, K: np.ndarray,
                          params: MotionParams = MotionParams()) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """World endpoints (2, 3) on ``seg_k``'s extent and their covariances (2, 3, 3), or None if the planes
    are too close to parallel (no baseline across the line) or the line is behind either camera."""
    K_inv = np.linalg.inv(K)

    def solve(sk, sj):
        p, q = _plane(sk, R_k, t_k, K_inv), _plane(sj, R_j, t_j, K_inv)
        if abs(p[:3] @ q[:3]) > math.cos(math.radians(params.min_plane_angle_deg)):
            return None
        line = _line_from_planes(p, q)
        return None if line is None else _endpoints(sk, R_k, t_k, K_inv, *line)

    P = solve(seg_k, seg_j)
    if P is None:
        return None
    for cam_R, cam_t in ((R_k, t_k), (R_j, t_j)):
        if (((P - cam_t) @ cam_R)[:, 2] <= 0.1).any():
            return None
    # Covariance: shift each image line across itself by sigma (4 perturbations), sum the squared effects.
    cov = np.zeros((2, 3, 3))
    for which in (0, 1):
        seg = (seg_k if which == 0 else seg_j).astype(float)
        dvec = seg[2:4] - seg[0:2]
        n = np.array([-dvec[1], dvec[0]]) / max(np.linalg.norm(dvec), 1e-9)
        for end in (0, 1):                  # tilt-and-shift: move one endpoint at a time
            moved = seg.copy()
            moved[2 * end:2 * end + 2] += params.sigma_perp_px * n
            Q = solve(moved, seg_j) if which == 0 else solve(seg_k, moved)
            if Q is None:
                return None
            diff = Q - P
            cov += np.einsum("ei,ej->eij", diff, diff)
    return P, cov


def match_across_motion(cur: Segments2D, cur_sel: np.ndarray, key: Segments2D,
                        params: MotionParams = MotionParams(), H: Optional[np.ndarray] = None) -> list[tuple[int, list[int]]]:
    """For each selected current segment, the keyframe segments it may be (direction, both sides' grey
    levels, distance across the line and overlap along it after the keyframe's segments are mapped by
    ``H``, the rotation between the views), best first."""
    if len(key) == 0:
        return []
    kxy = key.xy if H is None else _map_segments(key.xy, H)
    kd = kxy[:, 2:4] - kxy[:, 0:2]
    klen = np.maximum(np.linalg.norm(kd, axis=1), 1e-9)
    kd = kd / klen[:, None]
    kn = np.column_stack((-kd[:, 1], kd[:, 0]))
    out = []
    for i in np.nonzero(cur_sel)[0]:
        d = cur.direction[i]
        mid = 0.5 * (cur.xy[i, 0:2] + cur.xy[i, 2:4])
        cosang = kd @ d                      # same polarity
        across = np.abs(((mid - kxy[:, 0:2]) * kn).sum(axis=1))
        s0 = ((cur.xy[i, 0:2] - kxy[:, 0:2]) * kd).sum(axis=1)
        s1 = ((cur.xy[i, 2:4] - kxy[:, 0:2]) * kd).sum(axis=1)
        lo, hi = np.minimum(s0, s1), np.maximum(s0, s1)
        along = np.maximum(np.maximum(-hi, lo - klen), 0.0)           # gap between the extents along the line
        side = np.abs(key.sides - cur.sides[i]).max(axis=1)
        ok = (cosang >= math.cos(math.radians(params.match_angle_deg))) & (across <= params.max_shift_px) \
            & (along <= params.max_along_px) & (side <= params.side_tol)
        cand = np.nonzero(ok)[0]
        if len(cand):
            cand = cand[np.argsort(side[cand] + 0.2 * across[cand])][:params.max_candidates]
            out.append((int(i), cand.tolist()))
    return out


def _map_segments(xy: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Segments (N, 4) mapped by the homography H (their endpoints)."""
    pts = np.column_stack((xy.reshape(-1, 2), np.ones(2 * len(xy)))) @ H.T
    return (pts[:, :2] / pts[:, 2:3]).reshape(-1, 4)


def motion_segments(cur: Segments2D, R_k, t_k, key: Segments2D, R_j, t_j, K: np.ndarray,
                    params: MotionParams = MotionParams(), first_group: int = 10 ** 6) -> Segments3D:
    """3D segments (current camera frame) of the near-horizontal current segments matched in the keyframe.
    Rival pairs of one current segment share a group (numbered from ``first_group``)."""
    sel = np.abs(cur.direction[:, 1]) < math.sin(math.radians(params.max_angle_deg))
    H = K @ R_k.T @ R_j @ np.linalg.inv(K)           # keyframe image -> current image, rotation only
    P, C, lx, grp = [], [], [], []
    for i, cands in match_across_motion(cur, sel, key, params, H):
        for j in cands:
            r = triangulate_two_views(cur.xy[i], R_k, t_k, key.xy[j], R_j, t_j, K, params)
            if r is None:
                continue
            Pw, Cw = r
            if max(np.linalg.eigvalsh(c).max() for c in Cw) > params.max_sigma_m ** 2:
                continue
            P.append((Pw - t_k) @ R_k)                          # into the current camera frame
            C.append(np.einsum("ji,ejk,kl->eil", R_k, Cw, R_k))
            lx.append(cur.xy[i])
            grp.append(first_group + i)
    if not P:
        return Segments3D.empty()
    n = len(P)
    return Segments3D(np.array(P), np.array(C), np.array(lx), np.full((n, 4), np.nan), np.ones(n),
                      np.array(grp), np.ones(n, bool))
