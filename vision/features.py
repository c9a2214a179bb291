"""Feature tracks and keyframe re-acquisition.

``FeatureTracker`` keeps about ``max_features`` Shi-Tomasi corners alive with
pyramidal KLT, checked forward-backward (a point tracked forward and then
back must land within ``fb_threshold`` px of where it started, which rejects
points that slid along edges or onto occluders). Each track keeps an integer
id for its whole life. Lost tracks are replaced by detecting only in image
cells that have room, away from surviving tracks, and only when the count has
dropped below ``redetect_fraction`` of the target: detection is the costly
step, so steady-state frames only pay for the two KLT passes.

``describe`` / ``match_descriptors`` / ``geometric_inliers`` re-acquire a
keyframe after a jump or an occlusion: ORB descriptors at given points, ratio
test + mutual check in Hamming space, then an epipolar (fundamental-matrix)
RANSAC on normalised coordinates from the camera model.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def to_grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


# The strict forward-backward bound (a track refined at full resolution comes back within ~0.1 px)
# holds for most tracks of a sharp, textured image; when fewer than half of the tracks LK found pass it,
# the image, not the tracks, is at fault and the per-level bound of ``fb_threshold_px`` applies.
FB_STRICT_MIN_FRACTION = 0.5
# Deepest pyramid for the independent backward pass of a predicted track: level 5 (1/32) reaches
# 16 * win px, and a 375-px-high KITTI image is still 12 px high there.
MAX_BACK_LEVELS = 5


def fb_threshold_px(residual_px: np.ndarray, base_px: float, win: int, levels: int) -> np.ndarray:
    """Forward-backward threshold (px, full resolution) for tracks whose KLT had to find ``residual_px``.

    Pyramidal LK finds a displacement only at the level where it is within the window's half-width
    (``win / 2``): a residual ``d`` (displacement left after the initial guess) needs level
    ``L = ceil(log2(d / (win / 2)))``, clipped to ``[0, levels]``. What LK settles at level L is only
    as precise as one pixel of that level, i.e. ``2**L`` px of the full image, and the finer levels
    refine it only where the patch has texture at their scale (blur, low texture and exposure change
    remove exactly that). So a good track that needed level L can come back ``base_px * 2**L`` px
    from where it started; a fixed full-resolution threshold throws away every large-motion track
    whose fine levels could not sharpen it (issue 13: 13 of 110 kept on a hand-held loop). Tracks
    found near their guess (residual within the window) keep the strict ``base_px``. Outliers let
    through by the looser bound are the pose RANSAC's to reject.
    """
    half = max(win / 2.0, 1.0)
    d = np.maximum(np.asarray(residual_px, float), half)
    level = np.clip(np.ceil(np.log2(d / half) - 1e-9), 0, max(levels, 0))
    return base_px * 2.0 ** level


def klt_forward_backward(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, *, win: int, levels: int,
                         criteria: tuple, fb_threshold: float, border: int = 0,
                         guess: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) float32 of ``pts`` of ``prev`` in ``cur``, and a mask of good tracks.

    ``guess``: predicted positions in ``cur`` (from a motion model). When plain KLT keeps fewer
    than ``FB_STRICT_MIN_FRACTION`` of the points, those it lost (LK failed or the strict check
    rejects them) are tracked again with the guess as LK's initial flow, so LK only has to find
    the deviation from the motion model. The prediction is the second try, not the first: on
    KITTI forward motion, starting every track at the predicted position made the monocular
    trajectory worse (Sim(3) APE 0.15-0.18 m against 0.06-0.08 m over three RANSAC seeds,
    kitti06 left images), and so did rescuing the few tracks plain KLT loses there.

    Good: both LK passes found the point, the backward pass lands within ``fb_threshold`` px of
    where it started (or, when fewer than ``FB_STRICT_MIN_FRACTION`` of the found tracks pass that,
    within ``fb_threshold_px`` of their residual motion), and the point is at least
    ``border`` px inside the image (and 1 px from the far edges, which LK's bilinear
    interpolation needs).
    """
    p0 = np.asarray(pts, np.float32).reshape(-1, 1, 2)
    if len(p0) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    lk = dict(winSize=(win, win), maxLevel=levels, criteria=criteria)
    h, w = cur.shape[:2]
    far = max(border, 1)

    def run(start: np.ndarray, q0: np.ndarray, back_levels: int = levels
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, q0, start.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        if start is q0:
            # Plain track: the backward pass starts at the origin; a good track converges there in a step.
            q0r, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, q0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                  **lk)
        else:
            # Predicted track: the backward pass must not know the prediction. Started at the origin, a
            # patch that cannot move LK (flat, or an edge along the motion) would stay at the prediction
            # forward and at the origin backward and pass: an outlier that agrees with the motion model,
            # which the pose RANSAC cannot reject. So it starts from no motion, with a pyramid deep
            # enough for the whole displacement.
            q0r, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, winSize=(win, win), maxLevel=back_levels,
                                                  criteria=criteria)
        fb = np.linalg.norm((q0r - q0).reshape(-1, 2), axis=1)
        p1 = p1.reshape(-1, 2)
        residual = np.linalg.norm(p1 - start.reshape(-1, 2), axis=1)
        inside = (p1[:, 0] >= border) & (p1[:, 0] < w - far) & (p1[:, 1] >= border) & (p1[:, 1] < h - far)
        found = (st1.ravel() == 1) & (st2.ravel() == 1) & inside
        return p1, found, np.where(found, fb, np.inf), residual

    p1, found, fb, residual = run(p0, p0)
    if guess is not None and (found & (fb < fb_threshold)).sum() < FB_STRICT_MIN_FRACTION * len(p0):
        # Plain KLT lost most points (motion beyond the pyramid, blur): those it lost (not found, or
        # not back within the strict bound) are tracked again from the prediction; each keeps the
        # better of its two tracks. Only then: while plain KLT holds, the few tracks the prediction
        # would add made the monocular KITTI 06 trajectory worse (0.15 m against 0.07 m).
        g = np.asarray(guess, np.float32).reshape(-1, 1, 2)
        moved = np.linalg.norm((g - p0).reshape(-1, 2), axis=1) > 0.5
        idx = np.flatnonzero(moved & (fb >= fb_threshold))
        if len(idx):
            far_px = float(np.max(np.linalg.norm((g[idx] - p0[idx]).reshape(-1, 2), axis=1))) * 1.5
            back = int(min(MAX_BACK_LEVELS, max(levels, np.ceil(np.log2(max(far_px / (win / 2.0), 1.0))))))
            p1b, foundb, fbb, resb = run(g[idx], p0[idx], back)
            better = fbb < fb[idx]
            j = idx[better]
            p1[j], found[j], fb[j], residual[j] = p1b[better], foundb[better], fbb[better], resb[better]
            residual[j] = np.linalg.norm(p1[j] - p0[j].reshape(-1, 2), axis=1)  # what the backward pass found
    good = found & (fb < fb_threshold)
    if good.sum() < FB_STRICT_MIN_FRACTION * found.sum():
        # Most tracks fail the strict bound: the fine levels lack texture (blur, exposure, low
        # texture), so hold each track to the precision of the level its motion needed.
        good = found & (fb < fb_threshold_px(residual, fb_threshold, win, levels))
    return p1, good


@dataclass
class KltTracker:
    """Stateless GFTT + forward-backward KLT, for a caller that keeps its own landmarks (the VSLAM).

    ``FeatureTracker`` below is the stateful version with track ids, cell-balanced re-detection and
    keyframe re-acquisition, used by teach-and-repeat; both track with ``klt_forward_backward``.
    """

    window: int = 21
    levels: int = 3
    fb_threshold: float = 1.0
    quality: float = 0.01
    min_distance: float = 12.0
    block_size: int = 7

    def track(self, prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, levels: int | None = None,
              guess: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 2) float64 of ``pts`` of ``prev`` in ``cur`` and a mask of good tracks
        (``guess``: predicted positions in ``cur``, see ``klt_forward_backward``)."""
        new, ok = klt_forward_backward(prev, cur, pts, win=self.window,
                                       levels=self.levels if levels is None else levels,
                                       criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
                                       fb_threshold=self.fb_threshold, guess=guess)
        return new.astype(np.float64), ok

    def detect(self, image: np.ndarray, count: int, existing: np.ndarray | None = None,
               mask: np.ndarray | None = None, cells: int = 0) -> np.ndarray:
        """Up to ``count`` new sub-pixel corners (M, 2) at least ``min_distance`` from ``existing``.

        ``cells`` > 0: spread them over about that many square cells (each gets its share, ranked
        by its own strongest corner, so a dim or low-texture part of the image still gets corners
        next to a bright textured one), then fill what the cells left from the whole image."""
        if count <= 0:
            return np.zeros((0, 2))
        m = np.full(image.shape[:2], 255, np.uint8) if mask is None else mask.copy()
        if existing is not None and len(existing):
            for x, y in np.asarray(existing).reshape(-1, 2):
                cv2.circle(m, (int(round(x)), int(round(y))), int(self.min_distance), 0, -1)
        found = []
        if cells > 0:
            h, w = image.shape[:2]
            side = np.sqrt(h * w / cells)
            gy, gx = max(int(round(h / side)), 1), max(int(round(w / side)), 1)
            share = int(np.ceil(count / (gx * gy)))
            for r in range(gy):
                for c in range(gx):
                    cm = np.zeros_like(m)
                    ys, xs = slice(r * h // gy, (r + 1) * h // gy), slice(c * w // gx, (c + 1) * w // gx)
                    cm[ys, xs] = m[ys, xs]
                    p = cv2.goodFeaturesToTrack(image, maxCorners=share, qualityLevel=self.quality,
                                                minDistance=self.min_distance, mask=cm, blockSize=self.block_size)
                    if p is not None:
                        found.append(p.reshape(-1, 2))
                        for x, y in p.reshape(-1, 2):
                            cv2.circle(m, (int(round(x)), int(round(y))), int(self.min_distance), 0, -1)
        left = count - sum(len(p) for p in found)
        if left > 0:
            p = cv2.goodFeaturesToTrack(image, maxCorners=int(left), qualityLevel=self.quality,
                                        minDistance=self.min_distance, mask=m, blockSize=self.block_size)
            if p is not None:
                found.append(p.reshape(-1, 2))
        if not found:
            return np.zeros((0, 2))
        pts = np.vstack(found)[:count].reshape(-1, 1, 2)
        pts = cv2.cornerSubPix(image, pts.astype(np.float32), (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))
        return pts.reshape(-1, 2).astype(np.float64)


@dataclass
class Tracks:
    """Current tracks: ids (N,) int64, pts (N, 2) float32 pixels, age (N,) frames since detection."""

    ids: np.ndarray
    pts: np.ndarray
    age: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> "Tracks":
        return Tracks(np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.int32))

    def subset(self, mask: np.ndarray) -> "Tracks":
        return Tracks(self.ids[mask], self.pts[mask], self.age[mask])


class FeatureTracker:
    """GFTT + forward-backward pyramidal KLT with persistent track ids."""

    def __init__(self, max_features: int = 200, min_distance: float = 12.0, quality: float = 0.01,
                 block_size: int = 5, win_size: int = 15, levels: int = 3, fb_threshold: float = 1.0,
                 grid: tuple[int, int] = (4, 3), redetect_fraction: float = 0.85,
                 mask: np.ndarray | None = None, border: int = 8):
        self.max_features = max_features
        self.min_distance = min_distance
        self.quality = quality
        self.block_size = block_size
        self.win = (win_size, win_size)
        self.levels = levels
        self.fb_threshold = fb_threshold
        self.grid = grid
        self.redetect_fraction = redetect_fraction
        self.mask = mask
        self.border = border
        self._criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.03)
        self.reset()

    def reset(self) -> None:
        self.tracks = Tracks.empty()
        self._prev_pyr = None
        self._next_id = 0
        self.stats = {"tracked": 0, "lost": 0, "detected": 0}

    def _pyramid(self, grey: np.ndarray):
        # Python cannot pass prebuilt pyramids to calcOpticalFlowPyrLK (opencv issue #4777), so the
        # "pyramid" kept between frames is the image itself and LK builds its levels per call.
        return grey

    def track(self, image: np.ndarray) -> Tracks:
        """Track into ``image`` (grey or BGR), re-detect if needed; returns the current tracks."""
        grey = to_grey(image)
        pyr = self._pyramid(grey)
        lost = 0
        if self._prev_pyr is not None and len(self.tracks):
            keep, new_pts = self._klt(self._prev_pyr, pyr, self.tracks.pts, grey.shape)
            lost = int((~keep).sum())
            self.tracks = Tracks(self.tracks.ids[keep], new_pts[keep], self.tracks.age[keep] + 1)
        detected = 0
        if len(self.tracks) < self.redetect_fraction * self.max_features:
            detected = self._detect(grey)
        self._prev_pyr = pyr
        self.stats = {"tracked": len(self.tracks) - detected, "lost": lost, "detected": detected}
        return self.tracks

    def snapshot(self) -> tuple:
        """The tracks and the image they are in, for ``restore``."""
        return self.tracks, self._prev_pyr

    def restore(self, snapshot: tuple) -> None:
        """Go back to a ``snapshot``: the next image is tracked from its image, as if the images
        tracked since had not come (track ids issued since are not given out again)."""
        self.tracks, self._prev_pyr = snapshot

    def track_points(self, image: np.ndarray, pts: np.ndarray, ids: np.ndarray) -> Tracks:
        """Replace the tracks by given points (e.g. re-acquired keyframe landmarks) in ``image``."""
        grey = to_grey(image)
        self.tracks = Tracks(np.asarray(ids, np.int64), np.asarray(pts, np.float32).reshape(-1, 2),
                             np.zeros(len(ids), np.int32))
        self._prev_pyr = self._pyramid(grey)
        if len(ids):
            self._next_id = max(self._next_id, int(np.max(ids)) + 1)
        return self.tracks

    def add_points(self, pts: np.ndarray, ids: np.ndarray) -> None:
        """Add points (in the last tracked image) with given ids, skipping ids already tracked."""
        ids = np.asarray(ids, np.int64)
        new = ~np.isin(ids, self.tracks.ids)
        if not new.any():
            return
        self.tracks = Tracks(np.concatenate([self.tracks.ids, ids[new]]),
                             np.concatenate([self.tracks.pts, np.asarray(pts, np.float32).reshape(-1, 2)[new]]),
                             np.concatenate([self.tracks.age, np.zeros(int(new.sum()), np.int32)]))
        self._next_id = max(self._next_id, int(ids.max()) + 1)

    def _klt(self, prev_pyr, pyr, p0: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
        p1, keep = klt_forward_backward(prev_pyr, pyr, p0, win=self.win[0], levels=self.levels,
                                        criteria=self._criteria, fb_threshold=self.fb_threshold,
                                        border=self.border)
        return keep, p1

    def _detect(self, grey: np.ndarray) -> int:
        want = self.max_features - len(self.tracks)
        if want <= 0:
            return 0
        mask = self._free_mask(grey.shape)
        pts = cv2.goodFeaturesToTrack(grey, maxCorners=want, qualityLevel=self.quality,
                                      minDistance=self.min_distance, mask=mask, blockSize=self.block_size)
        if pts is None:
            return 0
        pts = pts.reshape(-1, 2).astype(np.float32)
        n = len(pts)
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        self.tracks = Tracks(np.concatenate([self.tracks.ids, ids]), np.concatenate([self.tracks.pts, pts]),
                             np.concatenate([self.tracks.age, np.zeros(n, np.int32)]))
        return n

    def _free_mask(self, shape) -> np.ndarray:
        """Where new corners may go: inside the border, outside full cells and away from tracks."""
        h, w = shape[:2]
        mask = np.zeros((h, w), np.uint8)
        b = self.border
        mask[b:h - b, b:w - b] = 255
        if self.mask is not None:
            mask &= self.mask
        if not len(self.tracks):
            return mask
        gx, gy = self.grid
        cap = int(np.ceil(self.max_features / (gx * gy)))
        cx = np.clip((self.tracks.pts[:, 0] * gx / w).astype(int), 0, gx - 1)
        cy = np.clip((self.tracks.pts[:, 1] * gy / h).astype(int), 0, gy - 1)
        counts = np.bincount(cy * gx + cx, minlength=gx * gy)
        for cell in np.flatnonzero(counts >= cap):           # full cells get nothing new
            r, c = divmod(int(cell), gx)
            mask[r * h // gy:(r + 1) * h // gy, c * w // gx:(c + 1) * w // gx] = 0
        rad = int(self.min_distance)
        for x, y in self.tracks.pts.astype(int):
            mask[max(y - rad, 0):y + rad + 1, max(x - rad, 0):x + rad + 1] = 0
        return mask


_ORB = None


def _orb():
    global _ORB
    if _ORB is None:
        # Upright descriptors (keypoint angle 0): a ground robot's camera does not roll, and
        # skipping orientation makes matching more discriminative.
        _ORB = cv2.ORB_create(nfeatures=1000, edgeThreshold=19, patchSize=19)
    return _ORB


def describe(image: np.ndarray, pts: np.ndarray, size: float = 19.0) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors at given points: (descriptors (M, 32) uint8, index of each described point).

    Points too close to the border to describe are dropped (their index is absent).
    """
    grey = to_grey(image)
    pts = np.asarray(pts, np.float32).reshape(-1, 2)
    kps = [cv2.KeyPoint(float(x), float(y), size, 0.0, 0.0, 0, i) for i, (x, y) in enumerate(pts)]
    kps, desc = _orb().compute(grey, kps)
    if desc is None or not kps:
        return np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
    return desc, np.array([k.class_id for k in kps], np.int64)


def orb_matches(a: np.ndarray, b: np.ndarray, features: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (K, 2) in ``a`` and in ``b`` of oriented multi-scale ORB corners matched between the two
    images (ratio test + mutual best): what survives a jump that KLT's pyramid cannot follow (a turn of
    tens of degrees, frames a second apart), where upright single-scale descriptors stop matching."""
    orb = cv2.ORB_create(nfeatures=features)
    ka, da = orb.detectAndCompute(to_grey(a), None)
    kb, db = orb.detectAndCompute(to_grey(b), None)
    if da is None or db is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = match_descriptors(da, db)
    pa = np.array([ka[i].pt for i in pairs[:, 0]], float).reshape(-1, 2)
    pb = np.array([kb[j].pt for j in pairs[:, 1]], float).reshape(-1, 2)
    return pa, pb


def match_descriptors(query: np.ndarray, train: np.ndarray, ratio: float = 0.8,
                      max_distance: int = 64) -> np.ndarray:
    """Pairs (K, 2) of (query index, train index): Lowe's ratio test and mutual best match."""
    if len(query) < 2 or len(train) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(query, train, k=2)
    back = bf.match(train, query)
    best_back = np.full(len(train), -1, np.int64)
    for m in back:
        best_back[m.queryIdx] = m.trainIdx
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in fwd
             if len(m) == 2 and m[0].distance < ratio * m[1].distance and m[0].distance <= max_distance
             and best_back[m[0].trainIdx] == m[0].queryIdx]
    return np.array(pairs, np.int64).reshape(-1, 2)


_ORB_DETECT = {}


def detect_and_describe(image: np.ndarray, max_features: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """Fresh corners and their upright ORB descriptors for re-acquisition: (pts (N, 2) float32, desc (N, 32)).

    ORB's own FAST + Harris ranking on one pyramid level (~4x cheaper than GFTT + describe
    here); the orientation it assigns is reset to 0 so the descriptors compare with the
    upright ones stored in keyframes (``describe``).
    """
    grey = to_grey(image)
    orb = _ORB_DETECT.get(max_features)
    if orb is None:
        orb = _ORB_DETECT[max_features] = cv2.ORB_create(nfeatures=max_features, nlevels=1, edgeThreshold=19,
                                                          patchSize=19)
    kps = orb.detect(grey)
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    for k in kps:
        k.angle = 0.0
    kps, desc = _orb().compute(grey, kps)
    if desc is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    return cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32), desc


def geometric_inliers(rays_a: np.ndarray, rays_b: np.ndarray, threshold: float = 2e-3,
                      seed: int = 0) -> np.ndarray:
    """Mask of correspondences consistent with one epipolar geometry (RANSAC).

    rays_*: unit rays (N, 3) from the camera model (so distortion is already
    removed); threshold: epipolar distance in normalised image units (~ pixels
    / focal length). The 8-point fundamental-matrix RANSAC on normalised
    coordinates is used rather than the 5-point essential matrix: it is ~10x
    faster and, as a consistency check, loses nothing. Rays behind either
    camera are rejected; with fewer than 8 pairs all in-front pairs pass.
    """
    a = np.asarray(rays_a, np.float64).reshape(-1, 3)
    b = np.asarray(rays_b, np.float64).reshape(-1, 3)
    front = (a[:, 2] > 1e-3) & (b[:, 2] > 1e-3)
    mask = np.zeros(len(a), bool)
    if front.sum() < 8:
        mask[front] = True
        return mask
    # Scale normalised coordinates to ~pixel magnitude so RANSAC's threshold is well conditioned.
    k = 1.0 / threshold
    pa = (a[front, :2] / a[front, 2:]) * k
    pb = (b[front, :2] / b[front, 2:]) * k
    cv2.setRNGSeed(seed)
    F, inl = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.99, 300)
    if F is None or inl is None:
        return mask
    mask[np.flatnonzero(front)] = inl.ravel()[: front.sum()] > 0
    return mask
