"""Camera calibration from views of a planar target: chessboard or ChArUco board.

Pure: grey images in, corners, intrinsics, stereo extrinsics and the camera's pose over a floor out.
The steps are OpenCV's (findChessboardCorners + cornerSubPix, or the ChArUco detector; calibrateCamera,
stereoCalibrate, solvePnP); what this module adds is the choice of views and the mounting geometry:

- a **blurred** view is rejected: its sharpness, the variance of the Laplacian over the board's bounding box
  divided by the squared contrast there (grey levels between the 5th and 95th percentile), times 1e4, is below
  ``SHARPNESS_MIN`` = 20. Normalising by the contrast makes the measure independent of exposure and print.
  Measured on OpenCV's 26 stereo sample views and the ChArUco tutorial views: sharp views score 87-1700; a
  Gaussian blur of sigma 1 px keeps every one above 24, sigma 2 px brings every one below 18. So 20 rejects
  views blurred by more than about 1.5 px (motion or focus), whose corners are off by a similar amount and
  would dominate the reprojection error of views at ~0.4 px;
- a **duplicate** view is rejected: its corners lie on average within ``DUPLICATE_SHARE`` (1 %) of the image
  diagonal of an accepted view's same corners (6 px at 640x480), i.e. the board did not move. Duplicates add
  no information and weigh one pose twice (a live capture of a board held still makes many).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

SHARPNESS_MIN = 20.0
DUPLICATE_SHARE = 0.01
SUBPIX_WINDOW = (11, 11)        # half-size, px: OpenCV's calibration sample's (corners 25-40 px apart)
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
MIN_CHARUCO_CORNERS = 6         # a homography needs 4; 6 keeps a view from being decided by one marker
CHESSBOARD_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
# OpenCV's predefined ArUco dictionaries, by name (cv2.aruco has other attributes, a name must be one of these)
ARUCO_DICTIONARIES = tuple(sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_")))


@dataclass(frozen=True)
class Board:
    """A calibration target. Chessboard: ``cols`` x ``rows`` inner corners; ChArUco: ``cols`` x ``rows``
    squares with ArUco markers of side ``marker`` from ``dictionary``. ``square``: side of a square in the
    unit of the results (m for a metric baseline and mount height)."""

    kind: str = "chessboard"
    cols: int = 9
    rows: int = 6
    square: float = 0.025
    marker: float = 0.0
    dictionary: str = "DICT_6X6_250"

    def __post_init__(self):
        if self.kind not in ("chessboard", "charuco"):
            raise ValueError(f"board kind {self.kind!r}: expected chessboard or charuco")
        if self.cols < 2 or self.rows < 2 or not self.square > 0:
            raise ValueError(f"board {self.cols}x{self.rows}, square {self.square}: expected at least 2x2 and a "
                             f"square > 0")
        if self.kind == "charuco":
            if not 0 < self.marker < self.square:
                raise ValueError(f"ChArUco marker side {self.marker} must be > 0 and smaller than the square "
                                 f"{self.square}")
            if self.dictionary not in ARUCO_DICTIONARIES:
                raise ValueError(unknown_dictionary(self.dictionary))

    def charuco(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, d)

    def corner_grid(self) -> np.ndarray:
        """(N, 3) chessboard corners on the board plane z = 0, row by row, in ``square`` units."""
        g = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
        return np.hstack([g * self.square, np.zeros((len(g), 1))]).astype(np.float32)


def unknown_dictionary(name: str) -> str:
    return f"unknown ArUco dictionary {name!r}: expected one of {', '.join(ARUCO_DICTIONARIES)}"


@dataclass
class View:
    """One image's board corners: pixels and the matching board points (z = 0)."""

    name: str
    image_points: np.ndarray          # (N, 2) float32
    object_points: np.ndarray         # (N, 3) float32
    ids: np.ndarray                   # (N,) corner ids (chessboard: 0..N-1)
    sharpness: float = 0.0


class BoardDetector:
    """Finds the board's corners in grey images (ChArUco: a detector built once)."""

    def __init__(self, board: Board):
        self.board = board
        self._charuco = cv2.aruco.CharucoDetector(board.charuco()) if board.kind == "charuco" else None
        self._charuco_points = board.charuco().getChessboardCorners() if self._charuco else None

    def detect(self, grey: np.ndarray, name: str = "") -> Optional[View]:
        """The board's corners in ``grey`` refined to sub-pixel, or None if the board is not (fully) seen."""
        if self._charuco is None:
            size = (self.board.cols, self.board.rows)
            ok, corners = cv2.findChessboardCorners(grey, size, CHESSBOARD_FLAGS)
            if not ok:
                return None
            corners = cv2.cornerSubPix(grey, corners, subpix_window(corners.reshape(size[1], size[0], 2)), (-1, -1),
                                       SUBPIX_CRITERIA)
            pts = corners.reshape(-1, 2).astype(np.float32)
            obj, ids = self.board.corner_grid(), np.arange(len(pts))
        else:
            corners, ids, _, _ = self._charuco.detectBoard(grey)
            if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
                return None
            pts, ids = np.asarray(corners, np.float32).reshape(-1, 2), np.asarray(ids).ravel()
            obj = np.asarray(self._charuco_points, np.float32)[ids]
        return View(name, pts, obj, ids, sharpness(grey, pts))


def subpix_window(grid: np.ndarray) -> tuple[int, int]:
    """cornerSubPix's half window for a (rows, cols, 2) corner grid: SUBPIX_WINDOW, but under 0.4 of the
    smallest corner spacing, so that a window never reaches a neighbouring corner (a board far away or seen
    at a grazing angle, like one lying on the floor, has corners a few pixels apart)."""
    d = min(float(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=-1))),
            float(np.min(np.linalg.norm(np.diff(grid, axis=1), axis=-1))))
    half = int(np.clip(0.4 * d, 2, SUBPIX_WINDOW[0]))
    return half, half


def sharpness(grey: np.ndarray, pts: np.ndarray) -> float:
    """1e4 * var(Laplacian) / contrast^2 over the bounding box of ``pts`` (see the module's docstring)."""
    x, y, w, h = cv2.boundingRect(np.asarray(pts, np.float32))
    roi = grey[max(0, y):y + h, max(0, x):x + w].astype(np.float64)
    if roi.size < 9:
        return 0.0
    lo, hi = np.percentile(roi, [5, 95])
    if hi - lo < 1:
        return 0.0
    return float(1e4 * cv2.Laplacian(roi, cv2.CV_64F).var() / (hi - lo) ** 2)


def duplicate_of(view: View, accepted: list[View], size: tuple[int, int]) -> Optional[View]:
    """The accepted view ``view`` repeats (its shared corners within DUPLICATE_SHARE of the diagonal)."""
    limit = DUPLICATE_SHARE * math.hypot(*size)
    for other in accepted:
        common, i, j = np.intersect1d(view.ids, other.ids, return_indices=True)
        if len(common) < 4:
            continue
        if float(np.mean(np.linalg.norm(view.image_points[i] - other.image_points[j], axis=1))) < limit:
            return other
    return None


@dataclass
class Intrinsics:
    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    rms: float                                        # px, over all corners of all views
    per_view: list[float] = field(default_factory=list)   # px, RMS of each view
    rvecs: list = field(default_factory=list)
    tvecs: list = field(default_factory=list)


def per_view_errors(views: list[View], K, dist, rvecs, tvecs) -> list[float]:
    out = []
    for v, r, t in zip(views, rvecs, tvecs):
        proj, _ = cv2.projectPoints(v.object_points, r, t, K, dist)
        out.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - v.image_points) ** 2, axis=1)))))
    return out


def calibrate_intrinsics(views: list[View], size: tuple[int, int], flags: int = 0) -> Intrinsics:
    """OpenCV's calibrateCamera on the views (5 coefficients k1 k2 p1 p2 k3 unless ``flags`` say otherwise)."""
    if len(views) < 3:
        raise ValueError(f"{len(views)} usable views: calibration needs at least 3 (10-20 recommended)")
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera([v.object_points for v in views],
                                                     [v.image_points for v in views], tuple(size), None, None,
                                                     flags=flags)
    return Intrinsics(K, dist.ravel(), tuple(size), float(rms), per_view_errors(views, K, dist, rvecs, tvecs),
                      list(rvecs), list(tvecs))


@dataclass
class StereoExtrinsics:
    R: np.ndarray               # right camera from left camera rotation
    T: np.ndarray               # right camera from left camera translation (board units)
    rms: float                  # px, both cameras
    baseline: float             # |T|
    rectified: dict             # the rectified pair: fx, fy, cx, cy of the rectified left camera, baseline


def calibrate_stereo(pairs: list[tuple[View, View]], left: Intrinsics, right: Intrinsics) -> StereoExtrinsics:
    """OpenCV's stereoCalibrate with each camera's intrinsics fixed (calibrated alone on more views),
    then stereoRectify (alpha 0: only valid pixels) for the rectified pair the obstacle stage uses."""
    if len(pairs) < 3:
        raise ValueError(f"{len(pairs)} views with the board in both images: stereo calibration needs at least 3")
    obj, pl, pr = [], [], []
    for a, b in pairs:
        common, i, j = np.intersect1d(a.ids, b.ids, return_indices=True)
        obj.append(a.object_points[i])
        pl.append(a.image_points[i])
        pr.append(b.image_points[j])
    out = cv2.stereoCalibrate(obj, pl, pr, left.K, left.dist, right.K, right.dist, left.size,
                              flags=cv2.CALIB_FIX_INTRINSIC)
    rms, R, T = float(out[0]), out[5], out[6].reshape(3, 1)
    _, _, P1, P2, _, _, _ = cv2.stereoRectify(left.K, left.dist, right.K, right.dist, left.size, R, T, alpha=0)
    T = T.ravel()
    rect = {"fx": float(P1[0, 0]), "fy": float(P1[1, 1]), "cx": float(P1[0, 2]), "cy": float(P1[1, 2]),
            "baseline": float(-P2[0, 3] / P2[0, 0])}
    return StereoExtrinsics(R, T, rms, float(np.linalg.norm(T)), rect)


@dataclass(frozen=True)
class FloorPose:
    """The camera over a floor: height of the optical centre (board units), pitch (positive looking down)
    and roll (positive: the image's right side lower), rad, as vision.geometry.CameraMount defines them."""

    height: float
    pitch: float
    roll: float
    rms: float                  # px, the board's reprojection error


def floor_pose_from_down(down_cam: np.ndarray, height: float, rms: float = 0.0) -> FloorPose:
    """Pitch and roll from the floor's downward normal in camera coordinates.

    With CameraMount.rotation() = rot_y(yaw) rot_x(-pitch) rot_z(roll) and the robot's y axis pointing down,
    the down direction in the camera frame is rot_z(roll)^T rot_x(pitch) (0, 1, 0)
    = (sin roll cos pitch, cos roll cos pitch, sin pitch)."""
    d = np.asarray(down_cam, float)
    d = d / np.linalg.norm(d)
    pitch = math.asin(float(np.clip(d[2], -1.0, 1.0)))
    roll = math.atan2(float(d[0]), float(d[1]))
    return FloorPose(float(height), pitch, roll, rms)


def floor_pose_from_board(view: View, K, dist) -> FloorPose:
    """The camera's pose over the floor from one view of a board lying on it (the board plane is the floor)."""
    if len(view.image_points) < 4:
        raise ValueError("the board on the floor: at least 4 corners are needed")
    ok, rvec, tvec = cv2.solvePnP(view.object_points, view.image_points, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("solvePnP found no pose of the board")
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    n = R[:, 2]                           # board normal (its z axis) in camera coordinates
    # the camera centre (origin) is on the up side of the floor: the down normal points from it to the plane
    down = n if float(n @ t) > 0 else -n
    height = abs(float(n @ t))
    proj, _ = cv2.projectPoints(view.object_points, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - view.image_points) ** 2, axis=1))))
    return floor_pose_from_down(down, height, rms)
