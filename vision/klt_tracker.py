"""Minimal point tracker for the VSLAM front end: Shi-Tomasi corners + pyramidal KLT.

Written here because ``vision/features.py`` (the shared tracker of the VBC
work) was not on main when VSLAM was built; switch to it once it is. Tracks
are kept only if the forward-backward round trip returns within
``fb_threshold`` pixels, which removes most occlusion and drift failures.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class KltTracker:
    window: int = 21
    levels: int = 3
    fb_threshold: float = 1.0
    quality: float = 0.01
    min_distance: float = 12.0
    block_size: int = 7

    def _lk_params(self, levels=None):
        return dict(winSize=(self.window, self.window), maxLevel=self.levels if levels is None else levels,
                     criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))

    def track(self, prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, guess: np.ndarray | None = None,
              levels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Positions of ``pts`` (N, 2) of ``prev`` in ``cur`` and a mask of good tracks."""
        pts = np.asarray(pts, np.float32).reshape(-1, 1, 2)
        if len(pts) == 0:
            return np.zeros((0, 2)), np.zeros(0, bool)
        params = self._lk_params(levels)
        flags = 0
        nxt = None
        if guess is not None:
            nxt = np.asarray(guess, np.float32).reshape(-1, 1, 2).copy()
            flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        fwd, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts, nxt, flags=flags, **params)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, fwd, pts.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                **params)
        fb = np.linalg.norm((back - pts).reshape(-1, 2), axis=1)
        fwd = fwd.reshape(-1, 2).astype(np.float64)
        h, w = cur.shape[:2]
        inside = (fwd[:, 0] >= 0) & (fwd[:, 0] < w - 1) & (fwd[:, 1] >= 0) & (fwd[:, 1] < h - 1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.fb_threshold) & inside
        return fwd, ok

    def detect(self, image: np.ndarray, count: int, existing: np.ndarray | None = None,
               mask: np.ndarray | None = None) -> np.ndarray:
        """Up to ``count`` new corners (M, 2) at least ``min_distance`` from ``existing``."""
        if count <= 0:
            return np.zeros((0, 2))
        m = np.full(image.shape[:2], 255, np.uint8) if mask is None else mask.copy()
        if existing is not None and len(existing):
            for x, y in np.asarray(existing).reshape(-1, 2):
                cv2.circle(m, (int(round(x)), int(round(y))), int(self.min_distance), 0, -1)
        pts = cv2.goodFeaturesToTrack(image, maxCorners=int(count), qualityLevel=self.quality,
                                      minDistance=self.min_distance, mask=m, blockSize=self.block_size)
        if pts is None:
            return np.zeros((0, 2))
        pts = cv2.cornerSubPix(image, pts.astype(np.float32), (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))
        return pts.reshape(-1, 2).astype(np.float64)
