"""Initial depth structure for the VSLAM (section 11.3.3.1).

Two ways, as in the chapter:
- a known reference structure: an AprilTag grid (any layout of tags whose
  corners are known in the grid frame) detected with OpenCV's ArUco module;
  the pose of the grid follows from the motion recovery (11.15-11.17) with the
  corners as landmarks, and every tracked feature inside the grid lies on its
  plane, which gives its depth;
- two views: the essential matrix from >= 8 correspondences. The chapter
  tests planarity on its singular values (ideal (1, 1, 0)): the linear
  8-point estimate of E from a planar scene is not a true essential matrix
  (the constraints then leave a 3-dimensional solution space), so the ratio of
  its two largest singular values departs from 1. Above ``planar_ratio`` the
  homography is decomposed instead. Depths then come from spherical disparity
  (11.11), up to the scale of T (unit length unless a metric scale is given).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from vbnav.vision.motion import recover_motion, recover_motion_robust
from vbnav.vision.spherical import spherical_disparity

# OpenCV's ArUco corner order (clockwise from the marker's top-left as seen in the image) in the tag frame
# of a tag of side s centred at the origin, x right, y down in the image of an upright tag.
TAG_CORNERS_UNIT = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])


@dataclass
class TagGrid:
    """Corner coordinates (4, 3) of each tag id in the grid frame, OpenCV's corner order."""

    corners: dict[int, np.ndarray]
    dictionary: int = cv2.aruco.DICT_APRILTAG_36h11

    @classmethod
    def from_spec(cls, spec: dict) -> "TagGrid":
        """From the ``tag_grid`` block of a camera YAML: ``corners: {id: [[x, y, z] x 4]}`` (metres, grid
        frame, OpenCV corner order), or ``tag_size`` with ``rows``, ``cols``, ``spacing`` (centre to
        centre), ``first_id`` (row-major ids, tags in the z = 0 plane)."""
        family = spec.get("family", "36h11")
        dic = {"36h11": cv2.aruco.DICT_APRILTAG_36h11, "25h9": cv2.aruco.DICT_APRILTAG_25h9,
               "16h5": cv2.aruco.DICT_APRILTAG_16h5}.get(str(family))
        if dic is None:
            raise ValueError(f"tag_grid.family: unsupported AprilTag family {family!r} (36h11, 25h9, 16h5)")
        if "corners" in spec:
            corners = {int(k): np.asarray(v, float).reshape(4, 3) for k, v in spec["corners"].items()}
        else:
            try:
                s, rows, cols, sp = float(spec["tag_size"]), int(spec["rows"]), int(spec["cols"]), float(spec["spacing"])
            except KeyError as exc:
                raise ValueError(f"tag_grid: missing key {exc} (need corners, or tag_size/rows/cols/spacing)") from None
            first = int(spec.get("first_id", 0))
            corners = {first + r * cols + c: TAG_CORNERS_UNIT * s + [c * sp, r * sp, 0.0]
                       for r in range(rows) for c in range(cols)}
        return cls(corners, dic)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Detected corners: pixels (M, 2), grid-frame points (M, 3), tag id per corner (M,)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(self.dictionary), params)
        corners, ids, _ = det.detectMarkers(grey)
        px, P, tid = [], [], []
        if ids is not None:
            for c, i in zip(corners, ids.ravel()):
                if int(i) in self.corners:
                    px.append(c.reshape(4, 2))
                    P.append(self.corners[int(i)])
                    tid += [int(i)] * 4
        if not px:
            return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, int)
        return np.vstack(px).astype(float), np.vstack(P), np.array(tid)


@dataclass
class StructureInit:
    """Landmarks in the camera frame of the initialising image and the camera pose in the world."""

    pixels: np.ndarray  # (N, 2)
    points_cam: np.ndarray  # (N, 3) metric (or unit-baseline) coordinates in the camera frame
    pose_wc: np.ndarray  # 4x4 world-from-camera
    info: dict


def init_from_tags(image: np.ndarray, camera, grid: TagGrid, extra_pixels: Optional[np.ndarray] = None,
                   min_tags: int = 2) -> StructureInit:
    """Pose of the tag grid by the alternation on its corners; the world frame is the grid frame.

    ``extra_pixels`` (e.g. corners found by the tracker) that fall inside the
    detected tags' convex hull get their depth from the grid plane.
    """
    px, P, tid = grid.detect(image)
    if len(set(tid.tolist())) < min_tags:
        raise ValueError(f"tag initialisation: {len(set(tid.tolist()))} known tags visible, need {min_tags}")
    rays = camera.rays(px)
    side = np.median(np.linalg.norm(px[0::4] - px[1::4], axis=1))
    size = np.median(np.linalg.norm(P[0::4] - P[1::4], axis=1))
    d0 = float(getattr(camera, "fx", 500.0)) * size / max(side, 1e-6)  # distance from the apparent tag size
    centre = P.mean(axis=0)
    est = recover_motion_robust(P - centre, rays, depths=d0, threshold=3.0 / float(getattr(camera, "fx", 500.0)),
                                tol=1e-10)
    R, T = est.R, est.T - est.R @ centre  # undo the centring: X = R (P - c) + T'
    X = P @ R.T + T
    pix, pts = [px[est.inliers]], [X[est.inliers]]
    if extra_pixels is not None and len(extra_pixels):
        hull = cv2.convexHull(px.astype(np.float32))
        inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) > 0 for x, y in extra_pixels])
        if inside.any():
            # plane of the grid in the camera frame: normal R e_z through T (grid z = 0 plane)
            normal = R[:, 2]
            n_r = camera.rays(extra_pixels[inside])
            D = (normal @ T) / (n_r @ normal)
            ok = D > 0
            pix.append(extra_pixels[inside][ok])
            pts.append(n_r[ok] * D[ok, None])
    pose_wc = np.eye(4)
    pose_wc[:3, :3], pose_wc[:3, 3] = R.T, -R.T @ T
    return StructureInit(np.vstack(pix), np.vstack(pts), pose_wc,
                         {"tags": sorted(set(tid.tolist())), "iterations": est.iterations,
                          "residual_px": est.residual * float(getattr(camera, "fx", 1.0))})


@dataclass
class TwoViewInit:
    R: np.ndarray  # first -> second camera: X2 = R X1 + T
    T: np.ndarray
    depths1: np.ndarray  # radial depths in the first view (nan where not reconstructed)
    valid: np.ndarray
    model: str  # "essential" or "homography"
    singular_values: np.ndarray  # of the linear 8-point E, normalised to s1 = 1
    planar_ratio: float  # s1/s2 of the linear E (chapter's test)
    null_space_ratio: float  # sigma_7/sigma_8 of the 8-point system


def linear_essential(rays1: np.ndarray, rays2: np.ndarray, with_spectrum: bool = False):
    """8-point estimate of E with n2^T E n1 = 0 (no rank constraint: its spectrum is the planarity test).

    With ``with_spectrum`` also the singular values of the N x 9 constraint
    matrix: a plane leaves a 3-dimensional (near) null space, so the 7th and 8th
    of them fall to the level of the 9th."""
    A = np.einsum("ni,nj->nij", rays2, rays1).reshape(-1, 9)
    _, sv, Vt = np.linalg.svd(A)
    E = Vt[-1].reshape(3, 3)
    return (E, sv) if with_spectrum else E


def _points_in_front(R, T, r1, r2) -> tuple[int, np.ndarray, np.ndarray]:
    rec = spherical_disparity(r1, r2, R, T, min_parallax=0.0, max_residual_ratio=np.inf)
    return int(rec.valid.sum()), rec.depth_ref, rec.valid


def _refine_two_view(r1, r2, R, T, rounds: int = 10):
    """Alternate spherical disparity (structure given motion) and the motion recovery (motion given
    structure) on the inliers; |T| stays 1. The minimal-sample estimate of RANSAC is only a start."""
    for _ in range(rounds):
        rec = spherical_disparity(r1, r2, R, T, min_parallax=np.deg2rad(0.2), max_residual_ratio=np.inf)
        if rec.valid.sum() < 6:
            break
        v = rec.valid
        est = recover_motion(rec.depth_ref[v, None] * r1[v], r2[v], prior=(R, T), angular=True)
        scale = np.linalg.norm(est.T)
        if not np.isfinite(scale) or scale < 1e-12:
            break
        R, T = est.R, est.T / scale
    return R, T


def init_two_view(rays1: np.ndarray, rays2: np.ndarray, planar_ratio: float = 1.5, null_space_ratio: float = 2.5,
                  scale: float = 1.0,
                  min_parallax_deg: float = 0.5, threshold: float = 1e-3,
                  translation_hint: Optional[np.ndarray] = None) -> TwoViewInit:
    """Motion and structure from two views, switching to a homography for planar scenes.

    rays1, rays2 (N, 3) corresponding unit rays (N >= 8, z > 0 for the OpenCV
    estimators). ``scale`` is the metric length of T (1 when unknown).
    ``threshold`` is the RANSAC threshold on normalised image coordinates.
    Planar when the chapter's ratio s1/s2 of the linear E exceeds ``planar_ratio``,
    or when the 8-point system shows a 3-dimensional null space (sigma_7/sigma_8 below
    ``null_space_ratio``: with noise the linear E of a plane is often close to
    (1, 1, 0) by chance, the null-space dimension is not) and a homography explains
    at least 90 % of the points the essential matrix explains.
    """
    r1 = np.asarray(rays1, float)
    r2 = np.asarray(rays2, float)
    if len(r1) < 8:
        raise ValueError(f"two-view initialisation needs >= 8 correspondences, got {len(r1)}")
    u1 = (r1[:, :2] / r1[:, 2:]).astype(np.float64)
    u2 = (r2[:, :2] / r2[:, 2:]).astype(np.float64)
    E5, mask = cv2.findEssentialMat(u1, u2, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=threshold)
    inl = mask.ravel().astype(bool) if mask is not None else np.ones(len(r1), bool)
    if inl.sum() < 8:
        inl = np.ones(len(r1), bool)
    E_lin, sv = linear_essential(r1[inl], r2[inl], with_spectrum=True)
    s = np.linalg.svd(E_lin, compute_uv=False)
    s = s / s[0]
    ratio = float(s[0] / max(s[1], 1e-12))
    null_ratio = float(sv[6] / max(sv[7], 1e-300))
    H, hmask = cv2.findHomography(u1, u2, cv2.RANSAC, 3.0 * threshold)  # transfer error: noise of both views
    h_inl = hmask.ravel().astype(bool) if hmask is not None else np.zeros(len(r1), bool)
    # A small null-space ratio alone also happens with noise on real, deep scenes: require that the
    # homography explains (nearly) every point the essential matrix explains.
    planar = ratio > planar_ratio or (null_ratio < null_space_ratio and h_inl.sum() >= 0.9 * inl.sum())
    if not planar and E5 is not None:
        E = E5[:3] if E5.shape[0] > 3 else E5
        R1, R2, t = cv2.decomposeEssentialMat(E)
        cands = [(R1, t.ravel()), (R1, -t.ravel()), (R2, t.ravel()), (R2, -t.ravel())]
        model = "essential"
    else:
        inl = h_inl
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
        cands = [(Rk, tk.ravel()) for Rk, tk in zip(Rs, ts)]
        model = "homography"
    scored = []
    for Rk, tk in cands:
        nt = np.linalg.norm(tk)
        if nt < 1e-12:
            continue
        count, _, _ = _points_in_front(Rk, tk / nt, r1[inl], r2[inl])
        scored.append((count, Rk, tk / nt))
    top = max(c for c, _, _ in scored)
    # A plane seen from two views leaves two decompositions with every point in front (a true
    # ambiguity). Pick the one agreeing with a translation hint (odometry), else the smaller rotation
    # (the views are close in time).
    finalists = [(R_, t_) for c, R_, t_ in scored if c >= 0.95 * top]
    if translation_hint is not None:
        h = np.asarray(translation_hint, float) / np.linalg.norm(translation_hint)
        R, T = max(finalists, key=lambda rt: float(rt[1] @ h))
    else:
        R, T = min(finalists, key=lambda rt: np.arccos(np.clip((np.trace(rt[0]) - 1) / 2, -1, 1)))
    R, T = _refine_two_view(r1[inl], r2[inl], R, T)
    rec = spherical_disparity(r1, r2, R, T * scale, min_parallax=np.deg2rad(min_parallax_deg),
                              max_residual_ratio=np.inf)  # RANSAC already removed inconsistent pairs
    valid = rec.valid & inl
    depths = np.where(valid, rec.depth_ref, np.nan)
    return TwoViewInit(R, T * scale, depths, valid, model, s, ratio, null_ratio)
