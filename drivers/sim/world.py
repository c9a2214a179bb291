"""The simulated world: textured planar quads (floor, walls, ceiling, boxes).

Coordinates follow vision/geometry.py: x right, y down, z forward, floor at
y = 0, points above the floor have y < 0. Every surface is a rectangle
(``Quad``) with its own procedural texture, generated from a seed so the same
world renders byte-for-byte the same image in every run.

Textures are rich in corners at several scales (large shaded blobs, random
rectangles / ellipses / triangles / bars of 2-60 cm, fine grain) and never
repeat: each surface draws from its own seed, so descriptor matching against
a keyframe is not fooled by copies.

Typical use::

    world = World.room(seed=0)                 # 10 m x 8 m room with boxes
    world.move_box("box_a", (0.5, 1.0))        # "two boxes moved" scenario
    world.add_box("obstacle", (0.0, 3.0), (0.3, 0.02, 0.3))   # a 2 cm box
    ids, depth = world.label_image(camera, R_wc, t_wc)        # ground truth
    height = -world.surface_points(camera, R_wc, t_wc)[..., 1]  # m above the floor

Worlds: ``World.room(seed, boxes=True)``, ``World.corridor(seed, ...)``,
``World.corridor_with_step(seed, step_at=3.0, step_depth=0.15)``,
``World.by_name(name, seed)`` for configuration (``sim.world``).

Polygon ids (``Quad.pid``) are stable for the life of the world (moving a box
keeps its ids); ``world.kind_image(ids)`` maps them to class names.
"""
from __future__ import annotations

import functools
import math
import zlib
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

# Texture resolution: texels per metre. 256 px/m (3.9 mm texels) keeps the
# floor in front of a 0.25 m high camera (nearest visible point ~0.4 m away,
# ~9 px per cm at fx = 400) only mildly magnified.
DEFAULT_PPM = 256.0
CEILING_PPM = 128.0      # seen from >= 2 m away: half the resolution suffices

KINDS = ("none", "floor", "wall", "ceiling", "box", "sheet", "step")


@dataclass(frozen=True)
class Quad:
    """A textured rectangle in the world.

    Points are ``origin + a * u + b * v`` for a in [0, width], b in [0, height]
    (metres). Texture row r / column c (texel centres) sit at
    ``a = (c + 0.5) / ppm``, ``b = (r + 0.5) / ppm`` (the texture's shape is
    (round(height * ppm), round(width * ppm))). ``normal`` = u x v points to the
    visible side; a quad seen from behind is not drawn unless ``two_sided``.
    """

    pid: int
    name: str
    kind: str
    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    width: float
    height: float
    texture: np.ndarray = field(repr=False)
    ppm: float = DEFAULT_PPM
    two_sided: bool = False
    tint: tuple = (1.0, 1.0, 1.0)   # BGR multipliers for colour rendering

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) world corners in order (0,0), (w,0), (w,h), (0,h)."""
        o, u, v = self.origin, self.u * self.width, self.v * self.height
        return np.array([o, o + u, o + u + v, o + v])

    @property
    def center(self) -> np.ndarray:
        return self.origin + 0.5 * (self.u * self.width + self.v * self.height)

    def point(self, a: float, b: float) -> np.ndarray:
        """World point at plane coordinates (a, b) metres."""
        return self.origin + a * self.u + b * self.v

    def texel_to_world(self, col: float, row: float) -> np.ndarray:
        """World point of texture position (col, row) (texel-centre convention above)."""
        return self.point((col + 0.5) * self.width / self.texture.shape[1],
                          (row + 0.5) * self.height / self.texture.shape[0])


def _seed_for(seed: int, name: str) -> int:
    """A per-surface seed: the same (seed, name) always gives the same texture."""
    return zlib.crc32(f"{int(seed)}:{name}".encode()) & 0x7FFFFFFF


@functools.lru_cache(maxsize=128)
def make_texture(seed: int, width_px: int, height_px: int, ppm: float) -> np.ndarray:
    """A procedural grey texture (uint8, read-only), deterministic for its arguments.

    Layers: smooth large-scale shading (1-2 m blobs), random filled shapes whose
    sizes are log-uniform in 2-60 cm (corners at every scale a camera sees from
    0.4 to 10 m), thin lines, and a fine grain that keeps close-up views
    textured. Cached, since tests build the same world many times.
    """
    rng = np.random.default_rng(seed)
    h, w = int(height_px), int(width_px)
    # Large-scale shading: bicubic upsampling of a coarse random grid (~1 m cells).
    cell = max(8, int(ppm))
    coarse = rng.uniform(50, 200, size=(h // cell + 3, w // cell + 3)).astype(np.float32)
    img = cv2.resize(coarse, ((w // cell + 3) * cell, (h // cell + 3) * cell),
                     interpolation=cv2.INTER_CUBIC)[cell:cell + h, cell:cell + w]
    img = np.ascontiguousarray(img)
    area_m2 = (w / ppm) * (h / ppm)
    _draw_shapes(img, rng, int(60 * area_m2) + 8, ppm)
    # Fine grain (sigma ~1 texel) for close views; low amplitude so the
    # shapes' corners stay the strongest features.
    grain = rng.standard_normal((h, w), dtype=np.float32)
    grain = cv2.GaussianBlur(grain, (0, 0), 1.0)
    img += 14.0 * grain
    out = np.clip(img, 0, 255).astype(np.uint8)
    out.flags.writeable = False
    return out


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, n: int, ppm: float) -> None:
    """Draw n random filled shapes (in place). Random numbers are drawn in bulk."""
    h, w = img.shape
    size = np.exp(rng.uniform(math.log(0.02), math.log(0.6), n)) * ppm   # texels
    aspect = np.exp(rng.uniform(-1.2, 1.2, n))
    cx, cy = rng.uniform(0, w, n), rng.uniform(0, h, n)
    angle = rng.uniform(0, 180, n)
    grey = rng.uniform(0, 255, n)
    kind = rng.integers(0, 10, n)
    shift = 4                                       # sub-texel precision for cv2 drawing
    sc = float(1 << shift)
    for i in range(n):
        g = float(grey[i])
        sx, sy = size[i] * math.sqrt(aspect[i]) / 2, size[i] / math.sqrt(aspect[i]) / 2
        if kind[i] < 5:        # rotated rectangle: 4 sharp corners
            pts = cv2.boxPoints(((cx[i], cy[i]), (2 * sx, 2 * sy), angle[i]))
            cv2.fillConvexPoly(img, np.round(pts * sc).astype(np.int32), g, cv2.LINE_8, shift)
        elif kind[i] < 7:      # ellipse: blob
            cv2.ellipse(img, (int(cx[i] * sc), int(cy[i] * sc)), (int(sx * sc), int(sy * sc)),
                        angle[i], 0, 360, g, -1, cv2.LINE_8, shift)
        elif kind[i] < 9:      # triangle
            a0 = math.radians(angle[i])
            t = np.array([[cx[i] + sx * math.cos(a0 + k * 2.1 + 0.3 * k * k),
                           cy[i] + sy * math.sin(a0 + k * 2.1 + 0.3 * k * k)] for k in range(3)])
            cv2.fillConvexPoly(img, np.round(t * sc).astype(np.int32), g, cv2.LINE_8, shift)
        else:                  # bar / line
            a0 = math.radians(angle[i])
            dx, dy = sx * 2 * math.cos(a0), sx * 2 * math.sin(a0)
            thick = max(1, int(sy * 0.3))
            cv2.line(img, (int((cx[i] - dx) * sc), int((cy[i] - dy) * sc)),
                     (int((cx[i] + dx) * sc), int((cy[i] + dy) * sc)), g, thick, cv2.LINE_8, shift)


def _tint(seed: int) -> tuple:
    """A random colour with unit luminance (grey of the colour image ~ the grey texture)."""
    rng = np.random.default_rng(seed ^ 0x5A5A)
    c = rng.uniform(0.6, 1.4, 3)
    lum = 0.114 * c[0] + 0.587 * c[1] + 0.299 * c[2]
    return tuple(float(x) for x in c / lum)


def _axes_facing(normal, up_hint) -> tuple[np.ndarray, np.ndarray]:
    """Unit (u, v) with u x v = normal, v (texture rows) along ``up_hint`` projected."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    v = np.asarray(up_hint, float)
    v = v - n * (v @ n)
    v = v / np.linalg.norm(v)
    u = np.cross(v, n)          # (v x n) x v = n for unit orthogonal v, n
    return u, v


@dataclass
class _Box:
    name: str
    center_xz: tuple
    size_xyz: tuple
    yaw: float
    seed: int
    pids: list = field(default_factory=list)


class World:
    """A set of textured quads plus named groups (boxes, sheets) that can be moved or removed.

    ``version`` increases on every change, so renderers know when to rebuild.
    """

    def __init__(self, seed: int = 0, ppm: float = DEFAULT_PPM, background: int = 100):
        self.seed = int(seed)
        self.ppm = float(ppm)
        self.background = int(background)   # grey level where no surface is seen
        self._quads: dict[int, Quad] = {}
        self._groups: dict[str, list[int]] = {}
        self._boxes: dict[str, _Box] = {}
        self._next_pid = 1                   # 0 means "no surface" in label images
        self.version = 0
        self.bounds: Optional[tuple] = None  # (xmin, xmax, zmin, zmax) of the walls, if any

    # ------------------------------------------------------------------ access
    @property
    def polygons(self) -> list[Quad]:
        return list(self._quads.values())

    @property
    def quads(self) -> list[Quad]:
        """Same as ``polygons``."""
        return self.polygons

    def polygon(self, pid: int) -> Quad:
        return self._quads[pid]

    def group(self, name: str) -> list[Quad]:
        """The quads added under ``name`` (a box's faces, a wall, ...)."""
        if name not in self._groups:
            raise KeyError(f"world has no object named {name!r}; it has {sorted(self._groups)}")
        return [self._quads[p] for p in self._groups[name]]

    def names(self) -> list[str]:
        return list(self._groups)

    def kind_image(self, ids: np.ndarray) -> np.ndarray:
        """uint8 class labels (index into KINDS) for an id image from label_image."""
        lut = np.zeros(self._next_pid, np.uint8)
        for q in self._quads.values():
            lut[q.pid] = KINDS.index(q.kind)
        return lut[ids]

    def label_image(self, camera, R_wc: np.ndarray, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ground truth for one view: (ids int32 HxW, 0 = no surface; depth float32 m, inf = none).

        Depth is the camera-frame z of the surface seen at each pixel centre.
        Uses the same rasterisation as the renderer, so masks match images.
        """
        from vbnav.drivers.sim.render import Renderer
        out = Renderer(self, camera).render(R_wc, t_wc, image=False, depth=True, ids=True)
        return out.ids, out.depth

    def surface_points(self, camera, R_wc: np.ndarray, t_wc: np.ndarray) -> np.ndarray:
        """World point (x, y, z) seen at every pixel centre, (H, W, 3) float32, NaN where none.

        Height above the floor is ``-points[..., 1]`` (e.g. the ground truth of
        an obstacle mask: pixels more than 1 cm above the floor).
        """
        _, depth = self.label_image(camera, R_wc, t_wc)
        H, W = depth.shape
        v, u = np.mgrid[0:H, 0:W]
        uv = camera.normalized(np.column_stack((u.ravel(), v.ravel())).astype(np.float64))
        z = depth.reshape(-1).astype(np.float64)
        z = np.where(np.isfinite(z), z, np.nan)
        pc = np.column_stack((uv * z[:, None], z))
        pw = pc @ np.asarray(R_wc, float).T + np.asarray(t_wc, float).reshape(1, 3)
        return pw.reshape(H, W, 3).astype(np.float32)

    # ---------------------------------------------------------------- building
    def add_quad(self, name: str, kind: str, origin, u, v, width: float, height: float, *,
                 seed: Optional[int] = None, ppm: Optional[float] = None, two_sided: bool = False,
                 texture: Optional[np.ndarray] = None, _pid: Optional[int] = None) -> Quad:
        """Add one textured rectangle to the group ``name`` (created if new)."""
        if kind not in KINDS[1:]:
            raise ValueError(f"quad kind must be one of {KINDS[1:]}, got {kind!r}")
        if not (width > 0 and height > 0):
            raise ValueError(f"quad {name!r}: width and height must be > 0 m, got {width}, {height}")
        ppm = self.ppm if ppm is None else float(ppm)
        pid = self._next_pid if _pid is None else int(_pid)
        tex_seed = _seed_for(self.seed if seed is None else seed, f"{name}/{len(self._groups.get(name, []))}")
        if texture is None:
            texture = make_texture(tex_seed, max(2, round(width * ppm)), max(2, round(height * ppm)), ppm)
        q = Quad(pid, name, kind, np.asarray(origin, float), np.asarray(u, float), np.asarray(v, float),
                 float(width), float(height), texture, ppm, two_sided, _tint(tex_seed))
        self._quads[pid] = q
        self._groups.setdefault(name, []).append(pid)
        if _pid is None:
            self._next_pid += 1
        self.version += 1
        return q

    def add_rect(self, name: str, kind: str, center, normal, up_hint, width: float, height: float,
                 **kw) -> Quad:
        """A rectangle centred at ``center`` facing ``normal``; its height runs along ``up_hint``."""
        u, v = _axes_facing(normal, up_hint)
        origin = np.asarray(center, float) - 0.5 * (u * width + v * height)
        return self.add_quad(name, kind, origin, u, v, width, height, **kw)

    def add_floor(self, x0: float, x1: float, z0: float, z1: float, y: float = 0.0,
                  name: str = "floor", kind: str = "floor", **kw) -> Quad:
        """Horizontal rectangle at height y (facing up, i.e. toward -y)."""
        return self.add_quad(name, kind, (x0, y, z0), (1, 0, 0), (0, 0, 1), x1 - x0, z1 - z0, **kw)

    def add_wall(self, name: str, p0_xz, p1_xz, height: float, y_bottom: float = 0.0,
                 kind: str = "wall", **kw) -> Quad:
        """Vertical rectangle from floor point p0 to p1, visible from the LEFT of p0->p1
        seen from above with +z up the page and +x to the right (i.e. the side
        that a counter-clockwise loop of walls encloses)."""
        p0, p1 = np.asarray(p0_xz, float), np.asarray(p1_xz, float)
        d = p1 - p0
        length = float(np.hypot(*d))
        u = np.array([d[0], 0.0, d[1]]) / length
        v = np.array([0.0, 1.0, 0.0])       # texture rows run downward
        origin = np.array([p0[0], y_bottom - height, p0[1]])
        return self.add_quad(name, kind, origin, u, v, length, height, **kw)

    def add_box(self, name: str, center_xz, size_xyz, seed: Optional[int] = None, yaw: float = 0.0) -> list[Quad]:
        """A box standing on the floor: 4 side faces and the top, each textured.

        size_xyz = (width along x, height, depth along z) in metres before ``yaw``
        (rad, rotation about the vertical axis, positive turning +z toward +x).
        """
        if name in self._groups:
            raise ValueError(f"world already has an object named {name!r}")
        sx, sy, sz = (float(s) for s in size_xyz)
        if min(sx, sy, sz) <= 0:
            raise ValueError(f"box {name!r}: size_xyz must be > 0 m, got {size_xyz}")
        box = _Box(name, tuple(float(c) for c in center_xz), (sx, sy, sz), float(yaw),
                   self.seed if seed is None else int(seed))
        self._boxes[name] = box
        self._build_box(box, textures=None)
        return self.group(name)

    def _build_box(self, box: _Box, textures: Optional[list], pids: Optional[list] = None) -> None:
        sx, sy, sz = box.size_xyz
        c, s = math.cos(box.yaw), math.sin(box.yaw)
        ex = np.array([c, 0.0, -s])      # box x axis in the world (rot_y(yaw))
        ez = np.array([s, 0.0, c])
        up = np.array([0.0, -1.0, 0.0])
        ctr = np.array([box.center_xz[0], -sy / 2, box.center_xz[1]])
        faces = [  # (center, outward normal, texture-up hint, width, height)
            (ctr + ez * sz / 2, ez, -up, sx, sy),
            (ctr - ez * sz / 2, -ez, -up, sx, sy),
            (ctr + ex * sx / 2, ex, -up, sz, sy),
            (ctr - ex * sx / 2, -ex, -up, sz, sy),
            (ctr + up * sy / 2, up, ez, sx, sz),
        ]
        for i, (cen, nrm, hint, w, h) in enumerate(faces):
            tex = None if textures is None else textures[i]
            self.add_rect(box.name, "box", cen, nrm, hint, w, h, seed=box.seed, texture=tex,
                          _pid=None if pids is None else pids[i])

    def move_box(self, name: str, new_center_xz, yaw: Optional[float] = None) -> None:
        """Move a box (same textures, same size) to a new floor position."""
        box = self._boxes.get(name)
        if box is None:
            raise KeyError(f"world has no box named {name!r}; boxes: {sorted(self._boxes)}")
        faces = self.group(name)
        textures, pids = [q.texture for q in faces], [q.pid for q in faces]
        self._drop_group(name)
        box.center_xz = tuple(float(c) for c in new_center_xz)
        if yaw is not None:
            box.yaw = float(yaw)
        self._build_box(box, textures, pids)

    def remove(self, name: str) -> None:
        """Remove a named object (box, sheet, wall...)."""
        self._drop_group(name)
        self._boxes.pop(name, None)

    def _drop_group(self, name: str) -> None:
        if name not in self._groups:
            raise KeyError(f"world has no object named {name!r}; it has {sorted(self._groups)}")
        for pid in self._groups.pop(name):
            del self._quads[pid]
        self.version += 1

    def add_floor_sheet(self, name: str, center_xz, size_xz, thickness: float = 0.001,
                        seed: Optional[int] = None, yaw: float = 0.0) -> Quad:
        """A flat textured sheet (paper, mat) lying on the floor: not an obstacle.

        Only its top is modelled, ``thickness`` above the floor.
        """
        c, s = math.cos(yaw), math.sin(yaw)
        ez = np.array([s, 0.0, c])
        center = np.array([center_xz[0], -float(thickness), center_xz[1]])
        return self.add_rect(name, "sheet", center, (0, -1, 0), ez, float(size_xz[0]), float(size_xz[1]),
                             seed=seed)

    def boxes(self) -> dict[str, tuple]:
        """name -> (center_xz, size_xyz, yaw) of every box."""
        return {b.name: (b.center_xz, b.size_xyz, b.yaw) for b in self._boxes.values()}

    def footprints(self) -> list[tuple[str, str, np.ndarray]]:
        """Plan view for plots: (name, kind, (N, 2) array of (x, z)) per object.

        Walls and risers are 2-point segments; boxes and sheets closed outlines
        (their top quad's corners); floors and ceilings are left out.
        """
        out = []
        for name, pids in self._groups.items():
            quads = [self._quads[p] for p in pids]
            kinds = {q.kind for q in quads}
            if kinds & {"floor", "ceiling"} or (kinds == {"step"} and abs(quads[0].normal[1]) > 0.5):
                continue
            if kinds <= {"wall", "step"}:
                for q in quads:
                    c = q.corners
                    out.append((name, q.kind, c[[0, 1]][:, [0, 2]]))
                continue
            top = min(quads, key=lambda q: q.center[1])   # highest face: the box top / the sheet
            out.append((name, top.kind, top.corners[:, [0, 2]]))
        return out

    def clearance(self, x: float, z: float) -> float:
        """Plan-view distance (m) from (x, z) to the nearest wall or box footprint (< 0 inside a box)."""
        best = math.inf
        if self.bounds is not None:
            x0, x1, z0, z1 = self.bounds
            best = min(x - x0, x1 - x, z - z0, z1 - z)
        for b in self._boxes.values():
            c, s = math.cos(b.yaw), math.sin(b.yaw)
            dx, dz = x - b.center_xz[0], z - b.center_xz[1]
            lx, lz = c * dx - s * dz, s * dx + c * dz     # into the box frame (inverse of rot_y(yaw))
            qx, qz = abs(lx) - b.size_xyz[0] / 2, abs(lz) - b.size_xyz[2] / 2
            outside = math.hypot(max(qx, 0.0), max(qz, 0.0))
            best = min(best, outside if outside > 0 else max(qx, qz))
        return best

    # ------------------------------------------------------------------ worlds
    @classmethod
    def room(cls, seed: int = 0, boxes: bool = True, size_xz=(10.0, 8.0), wall_height: float = 2.5,
             ceiling: bool = True) -> "World":
        """A closed room centred on the origin: x in [-5, 5], z in [-4, 4] by default.

        The rectangle route of ``suggested_route()`` (7 m x 4 m, 22 m) keeps
        >= 1 m from walls and boxes. Boxes (if ``boxes``): "box_a" and "box_b"
        inside the route's loop, "box_c" .. "box_e" between route and walls.
        """
        w = cls(seed)
        hx, hz = size_xz[0] / 2, size_xz[1] / 2
        w.bounds = (-hx, hx, -hz, hz)
        w.add_floor(-hx, hx, -hz, hz)
        if ceiling:
            w.add_quad("ceiling", "ceiling", (-hx, -wall_height, hz), (1, 0, 0), (0, 0, -1),
                       2 * hx, 2 * hz, ppm=CEILING_PPM)
        # Counter-clockwise seen from above (x right, z up the page): inside is on the left.
        corners = [(-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz)]
        for i, name in enumerate(("wall_south", "wall_east", "wall_north", "wall_west")):
            w.add_wall(name, corners[i], corners[(i + 1) % 4], wall_height)
        if boxes:
            w.add_box("box_a", (-1.3, 0.3), (0.8, 0.9, 0.6), yaw=0.3)
            w.add_box("box_b", (1.4, -0.2), (0.6, 0.5, 0.9), yaw=-0.2)
            w.add_box("box_c", (4.4, 3.4), (0.6, 1.2, 0.6), yaw=0.1)
            w.add_box("box_d", (-4.4, -3.3), (0.7, 0.7, 0.7), yaw=0.5)
            w.add_box("box_e", (0.5, 3.55), (1.2, 0.6, 0.5))
        return w

    @staticmethod
    def suggested_route() -> list[tuple[float, float]]:
        """Corners (x, z) of a closed 22 m rectangle inside ``room()`` with >= 1 m clearance."""
        return [(-3.5, -2.0), (3.5, -2.0), (3.5, 2.0), (-3.5, 2.0)]

    @classmethod
    def corridor(cls, seed: int = 0, width: float = 3.0, length: float = 12.0, wall_height: float = 2.5,
                 step_at: Optional[float] = None, step_depth: float = 0.15) -> "World":
        """A straight corridor along +z from z = -1 to z = length, x in [-width/2, width/2].

        With ``step_at`` the floor drops by ``step_depth`` metres for z > step_at
        (a negative obstacle); the drop's riser faces away from a robot at z < step_at.
        """
        w = cls(seed)
        hx = width / 2
        z0, z1 = -1.0, float(length)
        w.bounds = (-hx, hx, z0, z1)
        if step_at is None:
            w.add_floor(-hx, hx, z0, z1)
        else:
            w.add_floor(-hx, hx, z0, step_at)
            w.add_floor(-hx, hx, step_at, z1, y=step_depth, name="floor_low", kind="step")
            w.add_quad("riser", "step", (-hx, 0.0, step_at), (1, 0, 0), (0, 1, 0), width, step_depth,
                       two_sided=True)
        drop = 0.0 if step_at is None else step_depth
        corners = [(-hx, z0), (hx, z0), (hx, z1), (-hx, z1)]
        for i, name in enumerate(("wall_south", "wall_east", "wall_north", "wall_west")):
            w.add_wall(name, corners[i], corners[(i + 1) % 4], wall_height + drop, y_bottom=drop)
        return w

    @classmethod
    def corridor_with_step(cls, seed: int = 0, step_at: float = 3.0, step_depth: float = 0.15,
                           **kw) -> "World":
        """A corridor whose floor drops by ``step_depth`` m beyond z = ``step_at``."""
        return cls.corridor(seed, step_at=step_at, step_depth=step_depth, **kw)

    @classmethod
    def by_name(cls, name: str, seed: int = 0) -> "World":
        """Worlds selectable from configuration (``sim.world``)."""
        makers = {
            "room": lambda: cls.room(seed),
            "empty_room": lambda: cls.room(seed, boxes=False),
            "corridor": lambda: cls.corridor(seed),
            "corridor_step": lambda: cls.corridor_with_step(seed),
        }
        if name not in makers:
            raise ValueError(f"unknown simulated world {name!r}; expected one of {', '.join(makers)}")
        return makers[name]()

    def __repr__(self) -> str:
        return f"World(seed={self.seed}, quads={len(self._quads)}, objects={self.names()})"
