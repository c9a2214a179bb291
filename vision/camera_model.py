"""Camera models: pixels to unit rays (equation 11.9) and back.

Everything downstream of rays works on unit direction vectors n in the camera
frame and must not assume z > 0 (fisheye rays can point sideways or back).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np


#: How many distortion coefficients OpenCV takes per lens model (0: no distortion).
DISTORTION_COUNTS = {"pinhole": (0, 4, 5, 8, 12, 14), "fisheye": (0, 4)}


def check_distortion(model: str, dist) -> tuple:
    """The distortion coefficients of a ``model`` ('pinhole' or 'fisheye') lens as a tuple of floats; a
    ValueError says what OpenCV would refuse (a count it does not take, numbers that are not finite). Every
    reader of a camera (config, calibration files, routes, datasets) checks with this; the message is
    the caller's to prefix with the file and field."""
    d = tuple(float(x) for x in np.asarray(dist, dtype=float).ravel())
    counts = DISTORTION_COUNTS[model]
    if len(d) not in counts:
        raise ValueError(f"{model} expects {', '.join(map(str, counts[1:-1]))}"
                         f"{' or ' if len(counts) > 2 else ''}{counts[-1]} coefficients (or none), got {len(d)}")
    if not np.isfinite(d).all():
        raise ValueError(f"expected finite numbers, got {list(d)}")
    return d


@dataclass(frozen=True)
class CameraIntrinsics:
    """Image size (px) and the linear intrinsics every camera model here shares."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def in_image(self, px: np.ndarray, margin: float = 0.0) -> np.ndarray:
        return ((px[:, 0] >= margin) & (px[:, 0] < self.width - margin)
                & (px[:, 1] >= margin) & (px[:, 1] < self.height - margin))


@dataclass(frozen=True)
class PinholeCamera(CameraIntrinsics):
    """Pinhole with OpenCV's distortion (k1, k2, p1, p2[, k3[, k4, k5, k6]])."""

    dist: tuple = field(default_factory=tuple)

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=float) if len(self.dist) else np.zeros(0)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    def normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates (u, v) for focal length 1, (N, 2)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return np.column_stack(((px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy))
        und = cv2.undistortPoints(px.reshape(-1, 1, 2), self.K, self.dist_array)
        return und.reshape(-1, 2)

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit rays n = (u, v, 1)/|(u, v, 1)|, (N, 3)."""
        uv = self.normalized(pixels)
        n = np.column_stack((uv, np.ones(len(uv))))
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) of camera-frame points (N, 3) and a mask of those in front."""
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        front = P[:, 2] > 1e-9
        z = np.where(front, P[:, 2], 1.0)
        if not self.has_distortion:
            px = np.column_stack((self.fx * P[:, 0] / z + self.cx, self.fy * P[:, 1] / z + self.cy))
        else:
            q = np.column_stack((P[:, 0] / z, P[:, 1] / z, np.ones(len(P))))
            px, _ = cv2.projectPoints(q, np.zeros(3), np.zeros(3), self.K, self.dist_array)
            px = px.reshape(-1, 2)
        return px, front

    def scaled(self, factor: float) -> "PinholeCamera":
        """Same camera at another resolution (intrinsics scale, distortion does not)."""
        return replace(self, width=int(round(self.width * factor)), height=int(round(self.height * factor)),
                       fx=self.fx * factor, fy=self.fy * factor,
                       cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5)


@dataclass(frozen=True)
class FisheyeCamera(CameraIntrinsics):
    """OpenCV fisheye (equidistant with k1..k4): theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8).

    Rays are computed by inverting theta_d directly, so fields of view beyond
    180 degrees give rays with z <= 0 (cv2.fisheye.undistortPoints cannot).
    """

    dist: tuple = (0.0, 0.0, 0.0, 0.0)

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = (list(self.dist) + [0.0] * 4)[:4]
        t2 = theta * theta
        return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        a = (px[:, 0] - self.cx) / self.fx
        b = (px[:, 1] - self.cy) / self.fy
        theta_d = np.hypot(a, b)
        theta = theta_d.copy()
        for _ in range(20):  # Newton on f(theta) = theta_d(theta) - theta_d
            h = 1e-7
            f = self._theta_d(theta) - theta_d
            df = (self._theta_d(theta + h) - self._theta_d(theta - h)) / (2 * h)
            theta = theta - f / np.where(np.abs(df) < 1e-12, 1e-12, df)
        phi = np.arctan2(b, a)
        s = np.sin(theta)
        return np.column_stack((s * np.cos(phi), s * np.sin(phi), np.cos(theta)))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        r = np.hypot(P[:, 0], P[:, 1])
        theta = np.arctan2(r, P[:, 2])
        td = self._theta_d(theta)
        scale = np.where(r > 1e-12, td / np.maximum(r, 1e-12), 0.0)
        px = np.column_stack((self.fx * P[:, 0] * scale + self.cx, self.fy * P[:, 1] * scale + self.cy))
        return px, np.ones(len(P), dtype=bool)


def azimuth_elevation(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """alpha = atan2(x, z), beta = atan2(y, sqrt(x^2 + z^2)) of camera-frame directions (N, 3)."""
    n = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    alpha = np.arctan2(n[:, 0], n[:, 2])
    beta = np.arctan2(n[:, 1], np.hypot(n[:, 0], n[:, 2]))
    return alpha, beta


def rays_from_angles(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Inverse of azimuth_elevation: unit rays from (alpha, beta)."""
    cb = np.cos(beta)
    return np.column_stack((cb * np.sin(alpha), np.sin(beta), cb * np.cos(alpha)))
