"""The OpenCV peer of ``benchmarks/vo_real.py``: the "afternoon baseline" of issue 13, sharing nothing with vbnav.

Recipe (plain OpenCV, no bundle adjustment):
- Shi-Tomasi corners (cv2.goodFeaturesToTrack), tracked frame to frame by plain pyramidal KLT
  (cv2.calcOpticalFlowPyrLK) with only a loose forward-backward check;
- every frame: cv2.solvePnPRansac against a map of 3D points, refined on its inliers
  (cv2.solvePnPRefineLM); tracks the refined pose does not explain are dropped;
- the map starts and grows by
  - stereo: new corners matched left -> right by KLT on the same rows, depth from disparity;
  - depth: new corners back-projected with the depth image (where the frame has one);
  - (stereo and depth: a tracked point is measured again once it has come ``REMEASURE_CLOSER`` closer);
  - monocular (and depth frames without depth): a two-view start (cv2.findEssentialMat + recoverPose
    with cv2.USAC_ACCURATE on the first frame pair whose median flow passes ``INIT_FLOW_PX``), then every
    tracked corner is triangulated between the keyframe where it was detected and the current frame once
    their rays part by ``MIN_TRI_DEG`` (kept with positive depth and a small reprojection error in both
    views), and again every later frame while it is tracked (the baseline only grows);
- corners are detected again (masked around the live ones) whenever fewer than ``MIN_TRACKS`` are alive;
  the frame where they are detected is their keyframe;
- when KLT loses the map (no PnP pose), ORB matching against the last posed frame gives the pose and new tracks.

Every threshold is in pixels or degrees, with its reason beside it; none is fitted to one sequence.
"""
from __future__ import annotations

import cv2
import numpy as np

# Corners: quality 1 % of the strongest (OpenCV's usual), 10 px apart so that KLT windows (21 px) barely overlap.
GFTT_QUALITY, GFTT_MIN_DIST_PX, GFTT_BLOCK = 0.01, 10, 7
MAX_TRACKS = 1500  # corners alive at most: enough for PnP RANSAC to average pixel noise, cheap for KLT
MIN_TRACKS = 1000  # detect again below this, so that triangulation always has fresh corners in reserve
# KLT: a 21 px window on 4 levels (0-3) follows flow of up to about 10 px * 2^3 = 80 px, a 6 degree turn between
# frames at f = 700 px; mapped corners start from the constant-velocity prediction, so only the change of motion counts.
LK = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
FB_MAX_PX = 2.0  # loose forward-backward check: KLT is good to a few tenths of a pixel, 2 px only drops jumps
PNP_REPROJ_PX = 3.0  # PnP inlier bound: map points reproject with a median of about 1 px (KLT drift along a track plus
#                     triangulation error, measured on KITTI), so 3 px keeps the consistent ones and drops jumps
PNP_ITERS, PNP_CONFIDENCE = 300, 0.999
INIT_FLOW_PX = 50.0  # two-view start: 50 px is 4 degrees at f = 700 px, so that under forward motion (where corners
#                    near the focus of expansion hardly move) most corners still part by more than MIN_TRI_DEG
E_THRESH_PX = 1.0  # essential-matrix RANSAC bound: about twice KLT's precision
E_METHOD = cv2.USAC_ACCURATE  # RANSAC with local optimisation: plain cv2.RANSAC's start heading was off by 0.2-1.4
#                                degrees over four seeds on both KITTI sequences, USAC_ACCURATE's by 0.2-0.35
MIN_TRI_DEG = 1.0  # rays parting by 1 degree: 0.5 px of noise at f = 700 px moves depth by about 4 %, and the point
#                   is triangulated again every frame from its keyframe while tracked, so the baseline only grows
TRI_REPROJ_PX = 2.0  # a triangulated point must reproject this well in its two views (twice KLT's ~1 px track drift)
STEREO_ROW_PX = 1.0  # rectified pair: a match off its row by more than 1 px is wrong
MIN_DISPARITY_PX = 1.0  # below 1 px of disparity the depth is mostly noise
# Stereo / depth: a tracked point is measured again once it is this much closer than when it was measured: the depth
# error grows with depth squared, so 1.2x closer cuts it by 30 %; smaller gains are not worth putting the current
# pose's error into the map.
REMEASURE_CLOSER = 1.2
MIN_PNP_POINTS = 12  # fewer PnP inliers than this is no pose: 6 is the minimum, twice that for a margin
# Fallback when KLT loses the map (flow beyond its pyramid, e.g. frames a second apart): ORB corners matched to the
# last posed frame's, Lowe's ratio 0.8 (his figure for rejecting most false matches), each tied to the mapped corner
# within 3 px of it there (about the ORB keypoint's own localisation error on pyramid level 1).
ORB_FEATURES, ORB_RATIO, ORB_TIE_PX = 2000, 0.8, 3.0


def detect(img, n, existing=None):
    """Up to ``n`` Shi-Tomasi corners, none within GFTT_MIN_DIST_PX of ``existing``."""
    if n <= 0:
        return np.zeros((0, 2), np.float32)
    mask = np.full(img.shape[:2], 255, np.uint8)
    if existing is not None:
        for x, y in np.asarray(existing).reshape(-1, 2):
            cv2.circle(mask, (int(x), int(y)), GFTT_MIN_DIST_PX, 0, -1)
    p = cv2.goodFeaturesToTrack(img, n, GFTT_QUALITY, GFTT_MIN_DIST_PX, mask=mask, blockSize=GFTT_BLOCK)
    return np.zeros((0, 2), np.float32) if p is None else p.reshape(-1, 2).astype(np.float32)


def klt(a, b, p, guess=None, fb_px=FB_MAX_PX):
    """Pixels of ``p`` (in ``a``) in ``b`` and which were followed (status, inside, forward-backward)."""
    if len(p) == 0:
        return p, np.zeros(0, bool)
    p = p.reshape(-1, 1, 2).astype(np.float32)
    flags = 0
    if guess is not None:
        guess, flags = guess.reshape(-1, 1, 2).astype(np.float32).copy(), cv2.OPTFLOW_USE_INITIAL_FLOW
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p, guess, flags=flags, **LK)
    ok = st.ravel() == 1
    if fb_px is not None:
        r, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, q, p.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **LK)
        ok &= (st2.ravel() == 1) & (np.linalg.norm((r - p).reshape(-1, 2), axis=1) < fb_px)
    q = q.reshape(-1, 2)
    h, w = b.shape[:2]
    ok &= (q[:, 0] >= 0) & (q[:, 0] < w - 1) & (q[:, 1] >= 0) & (q[:, 1] < h - 1)
    return q, ok


def project(K, cw, X):
    """Pixels of world points X in the camera ``cw`` (camera-from-world) and their depths."""
    Xc = X @ cw[:3, :3].T + cw[:3, 3]
    uv = Xc @ K.T
    return uv[:, :2] / uv[:, 2:3], Xc[:, 2]


def rays_deg(K, cw0, px0, cw1, px1):
    """Angle (degrees) between the world rays of px0 seen from cw0 (N,4,4) and px1 seen from cw1 (4,4)."""
    Kinv = np.linalg.inv(K)
    r0 = np.column_stack((px0, np.ones(len(px0)))) @ Kinv.T
    r1 = np.column_stack((px1, np.ones(len(px1)))) @ Kinv.T
    r0w = np.einsum("nji,nj->ni", cw0[:, :3, :3], r0)  # R^T r: world directions
    r1w = r1 @ cw1[:3, :3]
    c = np.sum(r0w * r1w, 1) / np.linalg.norm(r0w, axis=1) / np.linalg.norm(r1w, axis=1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def triangulate(K, cw0, px0, cw1, px1):
    """Linear (DLT) triangulation of pixel pairs, each with its own first camera cw0 (N,4,4); world points."""
    P0 = K @ cw0[:, :3]  # (N,3,4)
    P1 = K @ cw1[:3]
    A = np.stack((px0[:, :1] * P0[:, 2] - P0[:, 0], px0[:, 1:] * P0[:, 2] - P0[:, 1],
                  px1[:, :1] * P1[2] - P1[0], px1[:, 1:] * P1[2] - P1[1]), axis=1)
    Xh = np.linalg.svd(A)[2][:, -1]
    return Xh[:, :3] / Xh[:, 3:4]


def pose_matrix(rv, tv):
    cw = np.eye(4)
    cw[:3, :3], cw[:3, 3] = cv2.Rodrigues(rv)[0], np.ravel(tv)
    return cw


class PeerVo:
    """The peer: live tracks (pixel now, pixel and camera at their keyframe, 3D point once known)."""

    def __init__(self, ds, mode: str, seed: int = 0, fb_px: float | None = FB_MAX_PX):
        if mode not in ("mono", "stereo", "depth"):
            raise ValueError(f"peer mode {mode!r}: expected mono, stereo or depth")
        self.ds, self.mode, self.K, self.fb_px = ds, mode, ds.camera.K.astype(float), fb_px
        # OpenCV's RANSAC draws from a fixed seed, so the order of the points it is given decides its draws
        self.rng = np.random.default_rng(seed)
        self.px = np.zeros((0, 2), np.float32)  # pixel in the current frame
        self.px0 = np.zeros((0, 2), np.float32)  # pixel in the keyframe where the corner was detected
        self.cw0 = np.zeros((0, 4, 4))  # that keyframe's camera-from-world
        self.X = np.zeros((0, 3))  # world point, NaN until known
        self.tri = np.zeros(0, bool)  # the point comes from triangulation (not from stereo or depth)
        self.zm = np.zeros(0)  # stereo / depth: the depth at which the point was measured (inf if triangulated)

    # ---- tracks -------------------------------------------------------------------------------------------
    def _keep(self, m):
        self.px, self.px0, self.cw0, self.X, self.tri = self.px[m], self.px0[m], self.cw0[m], self.X[m], self.tri[m]
        self.zm = self.zm[m]

    def _add(self, px, cw, X=None):
        self.px = np.vstack((self.px, px))
        self.px0 = np.vstack((self.px0, px))
        self.cw0 = np.concatenate((self.cw0, np.repeat(cw[None], len(px), 0)))
        self.X = np.vstack((self.X, np.full((len(px), 3), np.nan) if X is None else X))
        self.tri = np.concatenate((self.tri, np.full(len(px), X is None)))
        self.zm = np.concatenate((self.zm, np.full(len(px), np.inf) if X is None else (X @ cw[2, :3] + cw[2, 3])))

    def _follow(self, prev, img, guess_cw=None):
        guess = None
        known = ~np.isnan(self.X[:, 0])
        if guess_cw is not None and known.any():
            # constant-velocity prediction for mapped corners (in front of the camera), flow as is for the rest
            guess = self.px.copy()
            uv, z = project(self.K, guess_cw, self.X[known])
            h, w = img.shape[:2]
            good = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h)
            idx = np.flatnonzero(known)[good]
            guess[idx] = uv[good]
        self.px, ok = klt(prev, img, self.px, guess, self.fb_px)
        self._keep(ok)

    # ---- map growth ---------------------------------------------------------------------------------------
    def _metric_points(self, i, img, px, cw):
        """World points of new corners from stereo or depth (NaN where there is none), or None without depth."""
        ds, cam = self.ds, self.ds.camera
        if self.mode == "stereo":
            pr, ok = klt(img, ds.right_image(i), px, fb_px=self.fb_px)
            d = px[:, 0] - pr[:, 0]
            ok &= (np.abs(pr[:, 1] - px[:, 1]) < STEREO_ROW_PX) & (d > MIN_DISPARITY_PX)
            z = np.where(ok, cam.fx * ds.stereo_baseline / np.maximum(d, 1e-6), np.nan)
        else:
            depth = ds.depth_image(i)
            if depth is None:
                return None
            ij = np.round(px).astype(int)
            z = depth[np.clip(ij[:, 1], 0, depth.shape[0] - 1), np.clip(ij[:, 0], 0, depth.shape[1] - 1)]
            z = np.where(z > 0, z, np.nan)
        Xc = np.column_stack(((px[:, 0] - cam.cx) / cam.fx * z, (px[:, 1] - cam.cy) / cam.fy * z, z))
        wc = np.linalg.inv(cw)
        return Xc @ wc[:3, :3].T + wc[:3, 3]

    def _remeasure(self, i, img, cw):
        """Stereo / depth: new world points for the metric tracks now REMEASURE_CLOSER times closer than when
        they were measured."""
        metric = np.flatnonzero(~self.tri)
        if len(metric) == 0:
            return
        X = self._metric_points(i, img, self.px[metric], cw)
        if X is None:
            return
        z = X @ cw[2, :3] + cw[2, 3]
        closer = ~np.isnan(z) & (z * REMEASURE_CLOSER < self.zm[metric])
        self.X[metric[closer]], self.zm[metric[closer]] = X[closer], z[closer]

    def _replenish(self, i, img, cw):
        """New corners (this frame is their keyframe) when fewer than MIN_TRACKS are alive."""
        if len(self.px) >= MIN_TRACKS:
            return
        px = detect(img, MAX_TRACKS - len(self.px), self.px)
        X = self._metric_points(i, img, px, cw) if self.mode != "mono" else None
        if X is not None:
            has = ~np.isnan(X[:, 0])  # metric corners without depth are dropped: the depth pipeline stays metric
            px, X = px[has], X[has]
        self._add(px, cw, X)

    def _triangulate(self, cw):
        """(Re-)triangulate the corners without stereo or depth whose rays from their keyframe and now part by
        MIN_TRI_DEG: every frame again while tracked, as the baseline grows. Returns the mask of the tracks kept
        (those whose point comes out inconsistent with the two views are dropped)."""
        keep = np.ones(len(self.px), bool)
        todo = np.flatnonzero(self.tri)
        if len(todo):
            todo = todo[rays_deg(self.K, self.cw0[todo], self.px0[todo], cw, self.px[todo]) >= MIN_TRI_DEG]
        if len(todo) == 0:
            return keep
        X = triangulate(self.K, self.cw0[todo], self.px0[todo], cw, self.px[todo])
        uv1, z1 = project(self.K, cw, X)
        Xc0 = np.einsum("nij,nj->ni", self.cw0[todo, :3, :3], X) + self.cw0[todo, :3, 3]
        uv0 = Xc0 @ self.K.T
        uv0 = uv0[:, :2] / uv0[:, 2:3]
        good = (z1 > 0) & (Xc0[:, 2] > 0) & (np.linalg.norm(uv1 - self.px[todo], axis=1) < TRI_REPROJ_PX) \
            & (np.linalg.norm(uv0 - self.px0[todo], axis=1) < TRI_REPROJ_PX)
        self.X[todo[good]] = X[good]
        keep[todo[~good]] = False  # parallax enough yet no consistent point: a bad track
        self._keep(keep)
        return keep

    # ---- pose ---------------------------------------------------------------------------------------------
    def _pnp(self, cw_guess):
        """Camera-from-world of the current frame from the mapped tracks, or None; drops the outlier tracks."""
        known = np.flatnonzero(~np.isnan(self.X[:, 0]))
        if len(known) < MIN_PNP_POINTS:
            return None
        order = self.rng.permutation(len(known))  # the seed decides RANSAC's draws through the order of the points
        known = known[order]
        X, px = self.X[known], self.px[known].astype(float)
        rv0, _ = cv2.Rodrigues(cw_guess[:3, :3])
        good, rv, tv, inl = cv2.solvePnPRansac(X, px, self.K, None, rv0.copy(), cw_guess[:3, 3].reshape(3, 1).copy(),
                                               True, PNP_ITERS, PNP_REPROJ_PX, PNP_CONFIDENCE,
                                               flags=cv2.SOLVEPNP_ITERATIVE)
        if not good or inl is None or len(inl) < MIN_PNP_POINTS:
            return None
        inl = inl.ravel()
        rv, tv = cv2.solvePnPRefineLM(X[inl], px[inl], self.K, None, rv, tv)
        cw = pose_matrix(rv, tv)
        uv, z = project(self.K, cw, X)
        ok = (z > 0) & (np.linalg.norm(uv - px, axis=1) < PNP_REPROJ_PX)
        if ok.sum() < MIN_PNP_POINTS:
            return None
        keep = np.ones(len(self.px), bool)
        keep[known[~ok]] = False
        self._keep(keep)
        return cw

    def _relocalise(self, img):
        """Pose by ORB matching against the last posed frame's mapped corners, or None; the matches become the
        tracks (their points fixed from now on, since their keyframe is no longer tracked)."""
        last_img, last_px, last_X = self.last
        if len(last_px) < MIN_PNP_POINTS:
            return None
        orb = cv2.ORB_create(ORB_FEATURES)
        k0, d0 = orb.detectAndCompute(last_img, None)
        k1, d1 = orb.detectAndCompute(img, None)
        if d0 is None or d1 is None or len(k1) < 2:
            return None
        p0 = np.array([k.pt for k in k0])
        dist = np.linalg.norm(p0[:, None] - last_px[None], axis=2)
        near = dist.argmin(1)
        tied = dist[np.arange(len(p0)), near] < ORB_TIE_PX
        pairs = [m[0] for m in cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d0, d1, k=2)
                 if len(m) == 2 and m[0].distance < ORB_RATIO * m[1].distance and tied[m[0].queryIdx]]
        if len(pairs) < MIN_PNP_POINTS:
            return None
        X = last_X[near[[m.queryIdx for m in pairs]]]
        px = np.array([k1[m.trainIdx].pt for m in pairs], np.float32)
        good, rv, tv, inl = cv2.solvePnPRansac(X, px.astype(float), self.K, None, iterationsCount=PNP_ITERS,
                                               reprojectionError=PNP_REPROJ_PX, confidence=PNP_CONFIDENCE,
                                               flags=cv2.SOLVEPNP_SQPNP)
        if not good or inl is None or len(inl) < MIN_PNP_POINTS:
            return None
        inl = inl.ravel()
        rv, tv = cv2.solvePnPRefineLM(X[inl], px[inl].astype(float), self.K, None, rv, tv)
        cw = pose_matrix(rv, tv)
        self._keep(np.zeros(len(self.px), bool))
        self._add(px[inl], cw, X[inl])
        return cw

    # ---- start --------------------------------------------------------------------------------------------
    def _start_mono(self):
        """Two-view start: corners of frame 0 followed until their median flow passes INIT_FLOW_PX.

        Returns (index of the second view, its image, its camera-from-world, poses of the frames between)."""
        ds = self.ds
        img0 = ds.image(0)
        p0 = detect(img0, MAX_TRACKS)
        p, keep, prev, seen = p0.copy(), np.ones(len(p0), bool), img0, []
        for k in range(1, len(ds)):
            img = ds.image(k)
            q, ok = klt(prev, img, p, fb_px=self.fb_px)
            keep &= ok
            p, prev = q, img
            seen.append(q.copy())
            if np.median(np.linalg.norm(p[keep] - p0[keep], axis=1)) > INIT_FLOW_PX:
                break
        idx = np.flatnonzero(keep)
        idx = idx[self.rng.permutation(len(idx))]  # the seed decides RANSAC's draws through the order of the points
        a, b = p0[idx], p[idx]
        E, inl = cv2.findEssentialMat(a, b, self.K, E_METHOD, PNP_CONFIDENCE, E_THRESH_PX)
        _, R, t, inl = cv2.recoverPose(E, a, b, self.K, mask=inl)
        cw = np.eye(4)
        cw[:3, :3], cw[:3, 3] = R, t.ravel()
        inl = inl.ravel() > 0
        self._add(a[inl], np.eye(4))
        self.px = b[inl].astype(np.float32)
        idx = idx[inl][self._triangulate(cw)]
        # the frames between the two views: PnP against the start map from the pixels seen there
        known = ~np.isnan(self.X[:, 0])
        between = []
        for j, q in enumerate(seen[:-1], start=1):
            if known.sum() >= MIN_PNP_POINTS:
                ok, rv, tv = cv2.solvePnP(self.X[known], q[idx][known].astype(float), self.K, None,
                                          flags=cv2.SOLVEPNP_SQPNP)
                if ok:
                    between.append((j, pose_matrix(rv, tv)))
        return k, img, cw, between

    def run(self):
        """(frames with a pose, their world-from-camera poses)."""
        ds = self.ds
        frames, poses = [0], [np.eye(4)]
        if self.mode == "mono":
            start, prev, cw, between = self._start_mono()
            for j, c in between:
                frames.append(j)
                poses.append(np.linalg.inv(c))
            frames.append(start)
            poses.append(np.linalg.inv(cw))
            self._replenish(start, prev, cw)
        else:
            start, prev, cw = 0, ds.image(0), np.eye(4)
            self._replenish(0, prev, cw)
            if self.mode == "depth" and len(self.px) == 0:
                raise ValueError(f"{ds.root}: the depth peer needs a depth image for frame 0")
        cw_prev = cw.copy()
        known = ~np.isnan(self.X[:, 0])
        self.last = (prev, self.px[known].copy(), self.X[known].copy())
        for i in range(start + 1, len(ds)):
            img = ds.image(i)
            guess = cw @ np.linalg.inv(cw_prev) @ cw  # constant velocity
            self._follow(prev, img, guess)
            prev = img
            new = self._pnp(guess)
            if new is None:
                new = self._relocalise(img)
            if new is None:
                continue
            cw_prev, cw = cw, new
            frames.append(i)
            poses.append(np.linalg.inv(cw))
            known = ~np.isnan(self.X[:, 0])
            self.last = (img, self.px[known].copy(), self.X[known].copy())
            self._triangulate(cw)
            if self.mode != "mono":
                self._remeasure(i, img, cw)
            self._replenish(i, img, cw)
        return frames, np.array(poses)
