"""Render a simulated World through a pinhole camera: image, true depth, ids.

Each visible quad is drawn with one homography (texture plane -> image) by
``cv2.warpPerspective`` into the bounding box of its projection, and merged by
a per-pixel depth test. The depth test needs no ray casting: for a plane
n . P = d (camera frame) the inverse depth at pixel (u, v) is

    1/z = (n . K^-1 (u, v, 1)) / d = A u + B v + C,

an affine function of the pixel (the same fact that makes the ground a plane
in (u, v, disparity) space, equation 11.7). So the z-buffer holds 1/z, true
depth is its inverse and true disparity for a baseline B is fx * B / z.

Quads are clipped against the view frustum (near plane z >= 5 cm and the four
image sides) before projection, so planes extending behind the camera (the
floor under the robot) project correctly. Large quads are split into tiles of
at most ``tile_m`` metres, and each tile picks a pre-filtered texture level per
texture axis (a rip-map) from its projected texel density, so distant and
grazing surfaces are anti-aliased and close ones stay sharp: KLT tracks stay
stable.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from vbnav.vision.camera_model import PinholeCamera

NEAR_Z = 0.05          # m, near clipping plane
FRUSTUM_MARGIN_PX = 2.0
MIP_BIAS = 0.5         # level = floor(log2(texels per pixel along a texture axis) + bias)


@dataclass
class RenderOutput:
    image: Optional[np.ndarray] = None     # HxW uint8 (or HxWx3 BGR)
    depth: Optional[np.ndarray] = None     # HxW float32 m, inf where no surface
    ids: Optional[np.ndarray] = None       # HxW int32 Quad.pid, 0 where no surface
    inv_depth: Optional[np.ndarray] = None  # HxW float32 1/z, 0 where no surface

    def disparity(self, fx: float, baseline: float) -> np.ndarray:
        """True disparity fx * B / z of a rectified pair with baseline B (m), float32, NaN where no surface."""
        w = self.inv_depth
        return np.where(w > 0, w * np.float32(fx * baseline), np.float32(np.nan)).astype(np.float32)


_BINOMIAL = np.array([1, 4, 6, 4, 1], np.float32) / 16.0   # cv2.pyrDown's kernel
_ONE = np.ones(1, np.float32)


class _RipMap:
    """Texture pre-filtered and halved independently along x and y (a "rip-map"), built lazily.

    Level (lx, ly) has texel (col, row) at level-0 texel (2^lx col, 2^ly row)
    (binomial filter, then every other sample, as cv2.pyrDown does). A floor seen
    at a grazing angle is squeezed along one texture axis only: halving just that
    axis removes the aliasing without blurring the other, which a plain
    mip-map cannot do.
    """

    MIN_SIZE = 4

    def __init__(self, texture: np.ndarray):
        self.levels = {(0, 0): np.ascontiguousarray(texture)}
        h, w = texture.shape[:2]
        self.max_lx = max(0, int(math.log2(max(w, 1) / self.MIN_SIZE)))
        self.max_ly = max(0, int(math.log2(max(h, 1) / self.MIN_SIZE)))

    def get(self, lx: int, ly: int) -> np.ndarray:
        key = (min(max(lx, 0), self.max_lx), min(max(ly, 0), self.max_ly))
        tex = self.levels.get(key)
        if tex is None:
            lx, ly = key
            if lx > 0:     # halve along x from the level one step finer in x
                src = self.get(lx - 1, ly)
                tex = cv2.sepFilter2D(src, -1, _BINOMIAL, _ONE, borderType=cv2.BORDER_REFLECT_101)[:, ::2]
            else:
                src = self.get(lx, ly - 1)
                tex = cv2.sepFilter2D(src, -1, _ONE, _BINOMIAL, borderType=cv2.BORDER_REFLECT_101)[::2]
            tex = self.levels[key] = np.ascontiguousarray(tex)
        return tex


class _Tiles:
    """The world's quads cut into tiles, as flat arrays for vectorised culling."""

    def __init__(self, world, tile_m: float, overlap_m: float = 0.02):
        corners, quad_of, rect = [], [], []
        self.quads = world.polygons
        for qi, q in enumerate(self.quads):
            na = max(1, math.ceil(q.width / tile_m - 1e-9))
            nb = max(1, math.ceil(q.height / tile_m - 1e-9))
            ea, eb = q.width / na, q.height / nb
            for i in range(na):
                for j in range(nb):
                    # Overlap inner seams slightly so rasterisation never leaves a gap.
                    a0 = max(0.0, i * ea - overlap_m)
                    a1 = min(q.width, (i + 1) * ea + overlap_m)
                    b0 = max(0.0, j * eb - overlap_m)
                    b1 = min(q.height, (j + 1) * eb + overlap_m)
                    corners.append([q.point(a0, b0), q.point(a1, b0), q.point(a1, b1), q.point(a0, b1)])
                    quad_of.append(qi)
                    rect.append((a0, a1, b0, b1))
        self.corners = np.array(corners, float).reshape(-1, 4, 3)
        self.quad_of = np.array(quad_of, int)
        self.normals = np.array([q.normal for q in self.quads], float).reshape(-1, 3)
        self.origins = np.array([q.origin for q in self.quads], float).reshape(-1, 3)
        self.two_sided = np.array([q.two_sided for q in self.quads], bool)


class Renderer:
    """Renders one World for one PinholeCamera. Reuse it: it caches tiles and texture pyramids.

    The cache follows ``world.version``, so moving a box between frames is fine.
    """

    def __init__(self, world, camera: PinholeCamera, tile_m: float = 2.0):
        if not isinstance(camera, PinholeCamera):
            raise TypeError(f"the simulated renderer supports PinholeCamera models, got {type(camera).__name__}")
        self._distorted: Optional[_DistortionRemap] = None
        if camera.has_distortion:
            # Render an ideal pinhole image that covers the distorted view, then remap it.
            self._distorted = _DistortionRemap(camera)
            self._ideal = Renderer(world, self._distorted.ideal, tile_m)
            return
        self.world = world
        self.cam = camera
        self.tile_m = float(tile_m)
        self._version = None
        self._tiles: Optional[_Tiles] = None
        self._rips: dict[tuple, _RipMap] = {}
        W, H = camera.width, camera.height
        m = FRUSTUM_MARGIN_PX
        xl, xr = (-0.5 - m - camera.cx) / camera.fx, (W - 0.5 + m - camera.cx) / camera.fx
        yt, yb = (-0.5 - m - camera.cy) / camera.fy, (H - 0.5 + m - camera.cy) / camera.fy
        # Half-spaces n . P >= off, camera frame: near, left, right, top, bottom.
        self._planes = np.array([[0, 0, 1], [1, 0, -xl], [-1, 0, xr], [0, 1, -yt], [0, -1, yb]], float)
        self._offsets = np.array([NEAR_Z, 0, 0, 0, 0], float)
        self._plane_list = list(zip(self._planes.tolist(), self._offsets.tolist()))
        self._xs = np.arange(W, dtype=np.float32)
        self._ys = np.arange(H, dtype=np.float32)

    # --------------------------------------------------------------- caching
    def _sync(self) -> _Tiles:
        if self._version != self.world.version or self._tiles is None:
            self._tiles = _Tiles(self.world, self.tile_m)
            self._version = self.world.version
            live = {(id(q.texture), c) for q in self._tiles.quads for c in (False, True)}
            self._rips = {k: v for k, v in self._rips.items() if k in live}
        return self._tiles

    def _ripmap(self, quad, color: bool) -> _RipMap:
        key = (id(quad.texture), color)
        rip = self._rips.get(key)
        if rip is None:
            tex = quad.texture
            if color:
                tint = np.asarray(quad.tint, np.float32)
                tex = np.clip(tex[..., None].astype(np.float32) * tint, 0, 255).astype(np.uint8)
            rip = self._rips[key] = _RipMap(tex)
        return rip

    # ------------------------------------------------------------- rendering
    def render(self, R_wc: np.ndarray, t_wc: np.ndarray, *, image: bool = True, depth: bool = False,
               ids: bool = False, color: bool = False) -> RenderOutput:
        """Draw the world seen from world-from-camera pose (R_wc, t_wc)."""
        if self._distorted is not None:
            out = self._ideal.render(R_wc, t_wc, image=image, depth=depth, ids=ids, color=color)
            return self._distorted.apply(out)
        cam = self.cam
        H, W = cam.height, cam.width
        tiles = self._sync()
        R_wc = np.asarray(R_wc, float)
        c = np.asarray(t_wc, float).reshape(3)
        zbuf = np.zeros((H, W), np.float32)      # inverse depth, 0 = nothing
        img = None
        if image:
            img = np.full((H, W, 3) if color else (H, W), self.world.background, np.uint8)
        idimg = np.zeros((H, W), np.int32) if ids else None
        if len(tiles.corners) == 0:
            return self._output(img, zbuf, idimg, depth)

        # Everything in the camera frame: P_c = R_cw (P_w - c) = (P_w - c) @ R_wc.
        Pc = (tiles.corners - c) @ R_wc                               # (T, 4, 3)
        n_c = tiles.normals @ R_wc                                    # (Q, 3)
        d_c = np.einsum("qi,qi->q", n_c, (tiles.origins - c) @ R_wc)  # plane n . P = d
        facing = (d_c < -1e-9) | (tiles.two_sided & (np.abs(d_c) > 1e-9))
        dist = Pc @ self._planes.T - self._offsets                   # (T, 4, 5)
        inside = dist >= 0
        out_of_view = (~inside).all(axis=1).any(axis=1)
        needs_clip = ~inside.all(axis=(1, 2))
        todo = np.nonzero(~out_of_view & facing[tiles.quad_of])[0]

        fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
        K = cam.K
        for t in todo:
            poly = Pc[t]
            if needs_clip[t]:
                poly = self._clip(poly)
                if poly is None:
                    continue
            z = poly[:, 2]
            px = np.column_stack((fx * poly[:, 0] / z + cx, fy * poly[:, 1] / z + cy))
            x0 = max(0, int(math.floor(px[:, 0].min())))
            x1 = min(W, int(math.ceil(px[:, 0].max())) + 1)
            y0 = max(0, int(math.floor(px[:, 1].min())))
            y1 = min(H, int(math.ceil(px[:, 1].max())) + 1)
            if x1 <= x0 or y1 <= y0:
                continue
            bw, bh = x1 - x0, y1 - y0
            mask = np.zeros((bh, bw), np.uint8)
            pts = np.round((px - (x0, y0)) * 16.0).astype(np.int32)
            cv2.fillConvexPoly(mask, pts, 1, cv2.LINE_8, 4)
            qi = tiles.quad_of[t]
            n, d = n_c[qi], d_c[qi]
            # 1/z = (n . ((u - cx)/fx, (v - cy)/fy, 1)) / d, affine in (u, v).
            A, B = n[0] / (fx * d), n[1] / (fy * d)
            C = (n[2] - n[0] * cx / fx - n[1] * cy / fy) / d
            w = (self._ys[y0:y1, None] * np.float32(B) + np.float32(C)) + self._xs[None, x0:x1] * np.float32(A)
            zb = zbuf[y0:y1, x0:x1]
            upd = w > zb
            upd &= mask.view(bool)
            if not upd.any():
                continue
            np.copyto(zb, w, where=upd)
            if idimg is not None:
                np.copyto(idimg[y0:y1, x0:x1], np.int32(tiles.quads[qi].pid), where=upd)
            if img is not None:
                quad = tiles.quads[qi]
                # Filter levels are chosen where the tile's projected vertices' mean hits the plane.
                pu, pv = float(px[:, 0].mean()), float(px[:, 1].mean())
                inv_z = A * pu + B * pv + C
                pm = np.array([(pu - cx) / fx, (pv - cy) / fy, 1.0]) / inv_z if inv_z > 0 else poly.mean(axis=0)
                warped = self._warp_tile(quad, pm, K, R_wc, c, x0, y0, bw, bh, color)
                region = img[y0:y1, x0:x1]
                np.copyto(region, warped, where=upd[..., None] if color else upd)
        return self._output(img, zbuf, idimg, depth)

    def _output(self, img, zbuf, idimg, want_depth) -> RenderOutput:
        out = RenderOutput(image=img, ids=idimg, inv_depth=zbuf)
        if want_depth:
            with np.errstate(divide="ignore"):
                out.depth = np.where(zbuf > 0, 1.0 / zbuf, np.inf).astype(np.float32)
        return out

    def _clip(self, poly: np.ndarray) -> Optional[np.ndarray]:
        """Sutherland-Hodgman clipping of a convex 3D polygon against the frustum half-spaces.

        Plain Python on <= 9 vertices: several times cheaper than numpy per call.
        """
        pts = poly.tolist()
        for (nx, ny, nz), off in self._plane_list:
            s = [nx * p[0] + ny * p[1] + nz * p[2] - off for p in pts]
            if min(s) >= 0:
                continue
            if max(s) < 0:
                return None
            out = []
            k = len(pts)
            for i in range(k):
                j = (i + 1) % k
                if s[i] >= 0:
                    out.append(pts[i])
                if (s[i] >= 0) != (s[j] >= 0):
                    a = s[i] / (s[i] - s[j])
                    pi, pj = pts[i], pts[j]
                    out.append([pi[0] + a * (pj[0] - pi[0]), pi[1] + a * (pj[1] - pi[1]), pi[2] + a * (pj[2] - pi[2])])
            if len(out) < 3:
                return None
            pts = out
        return np.array(pts)

    def _warp_tile(self, quad, pm, K, R_wc, c, x0, y0, bw, bh, color):
        rip = self._ripmap(quad, color)
        th, tw = quad.texture.shape[:2]
        sa, sb = quad.width / tw, quad.height / th          # metres per level-0 texel
        # Level-0 texel (col, row) is the plane point a = (col + 0.5) sa, b = (row + 0.5) sb.
        Ru, Rv = R_wc.T @ quad.u, R_wc.T @ quad.v
        o = R_wc.T @ (quad.origin - c) + 0.5 * sa * Ru + 0.5 * sb * Rv
        M = K @ np.column_stack((Ru * sa, Rv * sb, o))      # level-0 texture -> image
        lx, ly = _filter_levels(M, pm, o, Ru, Rv, sa, sb)
        # Level (lx, ly) texel (col, row) is level-0 texel (2^lx col, 2^ly row).
        M[:, 0] *= float(1 << lx)
        M[:, 1] *= float(1 << ly)
        M[0] -= x0 * M[2]
        M[1] -= y0 * M[2]
        return cv2.warpPerspective(rip.get(lx, ly), M, (bw, bh), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE)


def _filter_levels(M: np.ndarray, pm: np.ndarray, o, Ru, Rv, sa: float, sb: float) -> tuple[int, int]:
    """Rip-map levels for the texture -> image homography M around camera-frame point pm.

    pm (on the plane) is texel (col, row) with pm = o + col sa Ru + row sb Rv.
    The inverse of the homography's Jacobian there says how many texels along
    each texture axis one pixel step covers; each axis is halved until that is ~1.
    """
    d = pm - o
    col, row = float(d @ Ru) / sa, float(d @ Rv) / sb
    x = M @ np.array([col, row, 1.0])
    w = x[2]
    if w <= 1e-9:
        return 0, 0
    px, py = x[0] / w, x[1] / w
    j00, j01 = (M[0, 0] - px * M[2, 0]) / w, (M[0, 1] - px * M[2, 1]) / w   # d(pixel) / d(texel)
    j10, j11 = (M[1, 0] - py * M[2, 0]) / w, (M[1, 1] - py * M[2, 1]) / w
    det = abs(j00 * j11 - j01 * j10)
    if det < 1e-18:
        return 0, 0
    # Rows of the inverse Jacobian: texels along col / row per pixel step.
    levels = []
    for s in (math.hypot(j11, j01) / det, math.hypot(j10, j00) / det):
        levels.append(max(0, int(math.floor(math.log2(s) + MIP_BIAS))) if s > 1e-12 else 0)
    return levels[0], levels[1]


class _DistortionRemap:
    """Maps an ideal pinhole rendering onto the pixel grid of a camera with OpenCV distortion.

    For every output pixel, its undistorted normalised coordinates (the camera
    model's own ``normalized``) give a position in an ideal pinhole image with the
    same focal lengths, large enough to hold them all. Images are resampled
    bilinearly; ids and depth take the nearest ideal pixel (within 0.5 px).
    """

    MAX_SCALE = 3.0     # refuse ideal canvases larger than 3x the image per side

    def __init__(self, camera: PinholeCamera):
        W, H = camera.width, camera.height
        v, u = np.mgrid[0:H, 0:W]
        xy = camera.normalized(np.column_stack((u.ravel(), v.ravel())).astype(np.float64))
        if not np.isfinite(xy).all():
            raise ValueError(f"camera distortion {camera.dist} cannot be inverted over the whole image")
        xmin, ymin = xy.min(axis=0)
        xmax, ymax = xy.max(axis=0)
        iw = int(math.ceil((xmax - xmin) * camera.fx)) + 4
        ih = int(math.ceil((ymax - ymin) * camera.fy)) + 4
        if iw > self.MAX_SCALE * W or ih > self.MAX_SCALE * H:
            raise ValueError(f"camera distortion {camera.dist} is too strong for the pinhole renderer "
                             f"(ideal image {iw}x{ih} for {W}x{H}); use a smaller field of view")
        cx, cy = -xmin * camera.fx + 2.0, -ymin * camera.fy + 2.0
        self.ideal = PinholeCamera(iw, ih, camera.fx, camera.fy, cx, cy)
        self.map_x = (xy[:, 0] * camera.fx + cx).reshape(H, W).astype(np.float32)
        self.map_y = (xy[:, 1] * camera.fy + cy).reshape(H, W).astype(np.float32)
        # Ideal-camera z equals the real camera's z (same optical axis), so depth maps over unchanged.

    def apply(self, out: RenderOutput) -> RenderOutput:
        def remap(a, interp):
            return None if a is None else cv2.remap(a, self.map_x, self.map_y, interp,
                                                    borderMode=cv2.BORDER_REPLICATE)
        ids = out.ids
        if ids is not None:   # cv2.remap has no int32 nearest path on every build: go through float32 ids
            ids = remap(ids.astype(np.float32), cv2.INTER_NEAREST).astype(np.int32)
        return RenderOutput(image=remap(out.image, cv2.INTER_LINEAR), depth=remap(out.depth, cv2.INTER_NEAREST),
                            ids=ids, inv_depth=remap(out.inv_depth, cv2.INTER_NEAREST))
