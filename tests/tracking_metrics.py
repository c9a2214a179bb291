"""Feature tracking on a real hand-held sequence without ground truth (``target_sequence``: 501 grey frames,
384x288, a planar dot target in front of clutter; shared data README: "use for tracking robustness: feature
survival, re-detection, drift of a static scene point").

Measured over every frame, for vbnav's ``FeatureTracker`` and a naive OpenCV peer (GFTT + pyramidal LK with
OpenCV's defaults, the status flag only, re-detection at the same fill level):

- tracks per frame (re-detection keeps the count up);
- survival: how many of the first frame's tracks are still tracked 50, 100, 200 and 499 frames later;
- drift of static scene points: from frame i every track is followed forward through the next W frames and
  then backward through the same frames to frame i; a static point tracked without drift comes back where it
  started, so the return error is twice the one-way drift over W frames (errors that reverse exactly with the
  motion, such as a fixed offset on one texture, cancel and are not seen). Windows start every W frames;
  only points followed both ways count, and how many is reported beside the error;
- the same over the whole sequence (``whole_return``): the first frame's corners followed to the last frame
  and back. A point that comes back more than 2 px off (``WRONG_PX``: 2x the 1 px forward-backward gate of
  a single step) drifted or jumped to another corner somewhere on the way; the share of such points among
  those a tracker still reports is what a map built on its tracks would take in as wrong.

Used by ``benchmarks/tracking_real.py`` (figures and ratio) and ``tests/test_features.py`` (bars).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vbnav.vision.features import FeatureTracker

MAX_FEATURES = 200
MIN_DISTANCE = 8.0
SURVIVAL_AT = (50, 100, 200, 499)
WRONG_PX = 2.0


def load_sequence(folder: Path) -> list[np.ndarray]:
    files = sorted(Path(folder).glob("image.*.png"))
    if not files:
        raise FileNotFoundError(f"{folder}: no image.NNNN.png frames")
    images = []
    for f in files:
        im = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if im is None:
            raise ValueError(f"{f}: not a readable image")
        images.append(im)
    return images


class NaiveTracker:
    """The peer: GFTT corners followed by OpenCV's pyramidal LK with its default window (21 px) and levels (3),
    kept when LK's status says found and inside the image; re-detection like ours below 85 % of the budget."""

    def __init__(self, max_features: int = MAX_FEATURES, min_distance: float = MIN_DISTANCE):
        self.max_features, self.min_distance = max_features, min_distance
        self.ids = np.zeros(0, np.int64)
        self.pts = np.zeros((0, 2), np.float32)
        self.prev = None
        self.next_id = 0

    def follow(self, image: np.ndarray) -> None:
        if self.prev is not None and len(self.pts):
            p1, st, _ = cv2.calcOpticalFlowPyrLK(self.prev, image, self.pts.reshape(-1, 1, 2), None)
            p1 = p1.reshape(-1, 2)
            h, w = image.shape
            ok = (st.ravel() == 1) & (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] < w) & (p1[:, 1] < h)
            self.ids, self.pts = self.ids[ok], p1[ok]
        self.prev = image

    def track(self, image: np.ndarray):
        self.follow(image)
        if len(self.pts) < 0.85 * self.max_features:
            mask = np.full(image.shape, 255, np.uint8)
            for x, y in self.pts.astype(int):
                cv2.circle(mask, (int(x), int(y)), int(self.min_distance), 0, -1)
            new = cv2.goodFeaturesToTrack(image, self.max_features - len(self.pts), 0.01, self.min_distance,
                                          mask=mask)
            if new is not None:
                new = new.reshape(-1, 2).astype(np.float32)
                self.ids = np.concatenate([self.ids, np.arange(self.next_id, self.next_id + len(new))])
                self.pts = np.concatenate([self.pts, new])
                self.next_id += len(new)
        return self.ids, self.pts


def _ours() -> FeatureTracker:
    return FeatureTracker(max_features=MAX_FEATURES, min_distance=MIN_DISTANCE)


def _ours_track(tr: FeatureTracker, image: np.ndarray):
    t = tr.track(image)
    return t.ids, t.pts


def _naive_track(tr: NaiveTracker, image: np.ndarray):
    return tr.track(image)


TRACKERS = {"vbnav": (_ours, _ours_track), "opencv_lk": (NaiveTracker, _naive_track)}


@dataclass
class TrackingFigures:
    counts: np.ndarray            # tracks per frame
    survival: dict                # frames later -> first-frame tracks still tracked
    return_px: np.ndarray         # forward-backward return errors of every point followed both ways
    returned: int                 # points followed both ways
    started: int                  # points at the windows' first frames

    def summary(self) -> dict:
        r = self.return_px
        return {"tracks_min": int(self.counts[1:].min()), "tracks_median": float(np.median(self.counts)),
                "survival": {int(k): int(v) for k, v in self.survival.items()},
                "return_median_px": float(np.median(r)) if len(r) else float("nan"),
                "return_p90_px": float(np.percentile(r, 90)) if len(r) else float("nan"),
                "returned": self.returned, "started": self.started}


def _follow(make, track, images: list[np.ndarray], start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Follow ``start`` points of images[0] through ``images`` (no re-detection counted); returns the indices of
    the points still tracked at the end and their positions."""
    tr = make()
    if isinstance(tr, FeatureTracker):
        tr.redetect_fraction = 0.0
        tr.track_points(images[0], start, np.arange(len(start)))
        for im in images[1:]:
            t = tr.track(im)
        return t.ids.astype(int), t.pts
    tr.ids, tr.pts, tr.prev = np.arange(len(start)), start.astype(np.float32), images[0]
    for im in images[1:]:
        tr.follow(im)
    return tr.ids.astype(int), tr.pts


def measure(images: list[np.ndarray], tracker: str, window: int = 50) -> TrackingFigures:
    make, track = TRACKERS[tracker]
    tr = make()
    counts, first, survival, points = [], None, {}, []
    for k, im in enumerate(images):
        ids, pts = track(tr, im)
        counts.append(len(ids))
        points.append(pts.copy())
        if first is None:
            first = set(ids.tolist())
        if k in SURVIVAL_AT:
            survival[k] = len(first & set(ids.tolist()))
    errs, started = [], 0
    for i in range(0, len(images) - window, window):
        start = points[i]
        started += len(start)
        fwd_ids, fwd_pts = _follow(make, track, images[i:i + window + 1], start)
        back_ids, back_pts = _follow(make, track, images[i:i + window + 1][::-1], fwd_pts)
        orig = start[fwd_ids[back_ids]]
        errs.append(np.linalg.norm(back_pts - orig, axis=1))
    return TrackingFigures(np.array(counts), survival, np.concatenate(errs) if errs else np.zeros(0),
                           int(sum(len(e) for e in errs)), started)


@dataclass
class WholeReturn:
    started: int                  # first-frame corners
    reported: int                 # still tracked at the last frame
    returned: int                 # of those, followed all the way back
    errors_px: np.ndarray         # their return errors

    @property
    def wrong(self) -> int:
        return int((self.errors_px > WRONG_PX).sum())

    @property
    def wrong_share(self) -> float:
        return self.wrong / max(self.returned, 1)


def whole_return(images: list[np.ndarray], tracker: str) -> WholeReturn:
    make, track = TRACKERS[tracker]
    start = cv2.goodFeaturesToTrack(images[0], MAX_FEATURES, 0.01, MIN_DISTANCE).reshape(-1, 2).astype(np.float32)
    f_ids, f_pts = _follow(make, track, images, start)
    b_ids, b_pts = _follow(make, track, images[::-1], f_pts)
    return WholeReturn(len(start), len(f_ids), len(b_ids), np.linalg.norm(b_pts - start[f_ids[b_ids]], axis=1))
