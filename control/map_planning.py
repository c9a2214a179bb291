"""Planning on a saved line map: its traversability grid, a path around its walls and objects, and
that path in the goto controller's frame. Shared by ``vbnav goto --map`` and ``vbnav map view``."""
from __future__ import annotations

import collections
import math
import threading
from typing import Optional

EVENTS_KEPT = 100   # re-planner lines kept for the command to print (a weeks-long goto re-plans without end)
# How far the re-planner may move a goal that the grown map's noise put inside the planner's margin (no mapped
# obstacle on it): the line map's endpoint error acceptance, 95 % (docs/line_map.md, measured 2.5 cm).
GOAL_TOLERANCE_M = 0.05


def map_grid(lmap, meta: dict, robot_radius: float, extra_points=None):
    """The traversability grid (vision/nav_grid.py) of a loaded map: its verified segments and the object
    footprints abstracted from them or stored with the map; ``extra_points`` (N, 2) x, z lie inside it."""
    from vbnav.vision.line_abstraction import object_polygons

    return grid_of(lmap.P[lmap.verified], object_polygons(lmap.structure()), meta, robot_radius, extra_points)


def grid_of(verified, polygons, meta: dict, robot_radius: float, extra_points=None):
    """The grid of verified segments (K, 2, 3), object ``polygons`` (with ``footprint``) and the objects
    stored in a map file's ``meta``, grown by ``robot_radius``."""
    from vbnav.vision.nav_grid import build_grid

    return build_grid(verified, grid_params(robot_radius), extra_points=extra_points,
                      polygons=footprints(polygons, meta))


def grid_params(robot_radius: float):
    import dataclasses

    from vbnav.vision.nav_grid import GridParams

    return dataclasses.replace(GridParams(), robot_radius_m=robot_radius)


def footprints(polygons, meta: dict) -> list:
    """The footprints (N, 2) of object ``polygons`` and of the objects stored in a map file's ``meta``."""
    import numpy as np

    return [p.footprint for p in polygons] + [np.asarray(o["footprint"], float) for o in meta.get("objects", [])]


#: A robot this near its goal has no leg left to drive (its final turn on the spot is the controller's): the
#: re-planner does not re-plan its approach (it once sent a robot 1 cm from its goal off on a new one). The map's
#: own 95 % endpoint error, as for the goal (GOAL_TOLERANCE_M): nearer than that a leg says nothing.
ARRIVED_M = GOAL_TOLERANCE_M


def stop_approach(cfg):
    """The obstacle stop's band as the planner's ``Approach`` (vision/nav_grid.py), None when the obstacle stage
    is off: a route whose last leg faces a mapped obstacle nearer the goal than the stop's reach would be held
    short of the goal for good (docs/line_map.md, 'The approach to the goal')."""
    if not cfg.obstacles.enabled:
        return None
    from vbnav.control.controllers.goto import WAYPOINT_TOLERANCE_M
    from vbnav.control.stages.obstacles import stop_half_width, stop_reach
    from vbnav.vision.nav_grid import Approach

    zones = cfg.obstacles.zones
    return Approach(stop_reach(zones), stop_half_width(zones), tolerance_m=WAYPOINT_TOLERANCE_M)


def plan_on_map(path: str, start, goal, robot_radius: float):
    """Waypoints (x, z) in the map's frame from ``start`` to ``goal`` around the walls and objects of the map
    file ``path``."""
    from vbnav.control.line_map_file import load_map

    return plan_path(*load_map(path), start, goal, robot_radius)


def plan_path(lmap, meta: dict, start, goal, robot_radius: float, approach=None):
    """``plan_on_map`` on a loaded map; ``approach``: the obstacle stop's band (``stop_approach``)."""
    import numpy as np

    from vbnav.vision.nav_grid import plan

    grid = map_grid(lmap, meta, robot_radius, extra_points=np.array([[start.x, start.z], [goal.x, goal.z]]))
    return plan(grid, (start.x, start.z), (goal.x, goal.z), GOAL_TOLERANCE_M, approach)   # the re-planner's rules too


def goal_moved_note(goal, moved: float, margin: str, what: str = "the goal") -> str:
    """What the planner did with a goal in its margin, ``moved`` m from the path's end (the start plan and the
    re-planner say it alike)."""
    return (f"{what} ({goal.x:+.2f}, {goal.z:+.2f}) lies within {margin} (no mapped obstacle on it); the route "
            f"ends at the nearest free point, {moved:.3f} m from it (tolerance {GOAL_TOLERANCE_M:.2f} m)")


def no_path_reason(lmap, meta: dict, start, goal, robot_radius: float) -> str:
    """Why ``plan_path`` found no path: the start on a wall or in an object, the goal too near one, or the
    goal walled off."""
    import numpy as np

    from vbnav.vision.nav_grid import goal_cells

    grid = map_grid(lmap, meta, robot_radius, extra_points=np.array([[start.x, start.z], [goal.x, goal.z]]))
    keep = (f"{grid.grown_m:.2f} m (--robot-radius {robot_radius:g} m + {grid.grown_m - robot_radius:.2f} m "
            f"clearance)")
    if grid.occupied[grid.cell(start.x, start.z)]:
        return (f"the --start ({start.x:+.2f}, {start.z:+.2f}) lies on a mapped wall or inside a mapped object: "
                f"give the robot's pose in the map")
    if not goal_cells(grid, (goal.x, goal.z), GOAL_TOLERANCE_M):
        return (f"the --goal ({goal.x:+.2f}, {goal.z:+.2f}) lies within {keep} of a mapped wall or object, more "
                f"than {GOAL_TOLERANCE_M:.2f} m inside that margin (or on the wall): give a goal farther from it")
    return (f"no path from ({start.x:+.2f}, {start.z:+.2f}) to the --goal ({goal.x:+.2f}, {goal.z:+.2f}) keeps "
            f"{keep} from the mapped walls and objects: walls stand between them, or the way is too narrow")


def map_route_in_reference_frame(planned, start, goal):
    """The planned path's intermediate waypoints and its end with the goal's heading (the goal itself, or the
    nearest free point of a goal in the planner's margin), moved from the map's frame into the goto
    controller's reference frame (the robot's pose at the start, ``start`` in the map)."""
    from vbnav.vision.geometry import Pose2

    ref = [start.between(Pose2(x, z, 0.0)) for x, z in planned[1:-1]]
    return [(p.x, p.z) for p in ref], start.between(Pose2(*planned[-1], goal.theta))


def sim_start_problem(cfg, meta: dict, map_path: str, start) -> str:
    """On the simulated robot, why ``start`` (--start) is not its pose in the map's frame, with what to give; ""
    when it is, or when the map does not say where its frame lies in the simulated world (``meta.sim_start_pose``,
    the robot's world pose when ``vbnav map build`` started; a map from elsewhere). Planning from a wrong start
    drives the wrong way, and the simulator's ground truth, taken from the robot's own start, does not show it."""
    import math

    from vbnav.vision.geometry import Pose2

    if cfg.drive.driver != "sim" or "sim_start_pose" not in meta:
        return ""
    x, z, th = meta["sim_start_pose"]
    true = Pose2(x, z, math.radians(th)).between(cfg.sim.start())
    off = math.degrees(abs(math.remainder(true.theta - start.theta, math.tau)))
    if math.hypot(true.x - start.x, true.z - start.z) <= 0.01 and off <= 0.5:
        return ""
    return (f"--start ({start.x:+.2f}, {start.z:+.2f}, {math.degrees(start.theta):+.1f} deg) is not where the "
            f"simulated robot stands in the map's frame: {cfg.source}: sim.start_pose {list(cfg.sim.start_pose)} in "
            f"the world, and {map_path} was built from meta.sim_start_pose {list(meta['sim_start_pose'])}: give "
            f"--start {true.x:.3f} {true.z:.3f} {math.degrees(true.theta):.1f}")


#: What to do instead when the camera cannot localise the start against a map.
INSTEAD = "or leave out --localise and give the robot's pose in the map with --start"


def localise_problem(cfg) -> str:
    """Why the configured camera cannot localise against a line map, with what to do; "" when it can. The
    localisation reads a rectified stereo pair, as the line map does."""
    if not cfg.camera.stereo_baseline():
        return (f"{cfg.source}: camera: localising against a line map needs a stereo camera, and neither "
                f"camera.calibration_file nor camera.options.stereo_baseline gives a baseline: set one, {INSTEAD}")
    refusal = cfg.camera.rectified_refusal("localising against a line map",
                                           f"rectify the pair with a stereo calibration file, {INSTEAD}")
    return f"{cfg.source}: {refusal}" if refusal else ""


def localise_start(cfg, camera, lmap, map_path: str, guess, timeout_s: float = 3.0):
    """The robot's pose in the frame of the loaded map ``lmap`` (from ``map_path``) from one stereo frame of
    ``camera`` (vision/line_localise.py), searched around ``guess``: (Localisation, message); (None, why and
    what to do) when it cannot localise at all. The camera is opened and closed again here (the run opens it
    for itself)."""
    from vbnav.vision.line_localise import LocaliseParams, View, localise
    from vbnav.vision.line_segments import detect_segments

    problem = localise_problem(cfg)
    if problem:
        return None, problem
    baseline = cfg.camera.stereo_baseline()
    camera.connect()
    try:
        frame = camera.read(timeout_s)
    finally:
        camera.disconnect()
    if frame is None:
        return None, (f"camera: no frame within {timeout_s:.0f} s to localise against {map_path}: check the camera "
                      f"('vbnav doctor -c CONFIG'), {INSTEAD}")
    model = cfg.camera.to_model()
    view = View(model.fx, model.fy, model.cx, model.cy, model.width, model.height, baseline,
                cfg.camera.mount.to_mount())
    r = localise(lmap, detect_segments(frame.image), view, guess)
    lp = LocaliseParams()
    if r.predicted == 0:        # "0 of the 0 ... inf px rms" said nothing of why
        say = (f"{map_path}: no map segment would be in view from the poses searched around --start "
               f"({lp.search_m:g} m / {lp.search_deg:g} deg): the start is far from where the map was built, or "
               f"looks away from what it holds")
    else:
        say = f"{map_path}: {r.matches} of the {r.predicted} map segments predicted in view found"
        if r.matches < lp.min_matches:
            say += f", fewer than the {lp.min_matches} a pose needs"
        elif r.matches < lp.min_explained * r.predicted:
            say += f", under the {lp.min_explained:.0%} a true pose explains"
        if math.isfinite(r.rms_px):
            say += f", {r.rms_px:.2f} px rms"
    return r, say


def sighting_squares(points, size: float) -> list:
    """The obstacle stop's sighting (``(N, 2)`` x, z or None) as one small square footprint per point."""
    if points is None or not len(points):
        return []
    h = size / 2
    corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
    return [[(float(x) + dx, float(z) + dz) for dx, dz in corners] for x, z in points]


def route_is_clear(grid, here, route, skip_m: float) -> bool:
    """True when the polyline from ``here`` (x, z) through ``route`` [(x, z), ...] crosses no blocked cell of
    ``grid``, sampled every half cell. Blocked samples within ``skip_m`` of ``here`` at the very start are
    not counted: a robot passing close to a wall stands in the grown margin itself (the planner leaves a
    blocked start cell too)."""
    import numpy as np

    pts = [np.asarray(here, float)] + [np.asarray(p, float) for p in route]
    step = grid.res / 2
    leaving = True
    for a, b in zip(pts, pts[1:]):
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
        for p in np.linspace(a, b, n):
            cell = grid.cell(float(p[0]), float(p[1]))
            blocked = grid.inside(*cell) and bool(grid.blocked[cell])
            if leaving and (not blocked or np.linalg.norm(p - pts[0]) >= skip_m):
                leaving = False
            if blocked and not leaving:
                return False
    return True


class Replanner:
    """The mission loop on a map that grows while the robot drives (section 11.2.1.1: the DLM is the
    centre of navigation). Each ``step`` (its own thread, every ``period_s``; or inline on a simulated
    clock) looks at the line map only when it changed since the last look: it brings the traversability
    grid up to date with the map as it is now (verified segments, the slow loop's object polygons and those
    stored with the map file; only what changed is redrawn, ``nav_grid.IncrementalGrid``), checks that the route still ahead of the robot is clear, and when the grown map
    blocks it plans again from the robot's pose and hands the controller the new waypoints. With no path
    at all the controller holds (stopped) until the map opens one again; the obstacle stop stays in force
    whatever the plan says.

    ``stage``: the LineMapStage updating the map (its ``revision``, ``verified_snapshot`` and abstraction);
    ``start``: the robot's start pose in the map's frame (the controller's reference frame origin);
    ``goal``: in the map's frame; ``robot_pose``: () -> the robot's pose in the reference frame, or None."""

    def __init__(self, stage, meta: dict, start, goal, robot_radius: float, controller, robot_pose,
                 period_s: float = 0.5, approach=None, sightings=None):
        from vbnav.vision.nav_grid import GridParams, IncrementalGrid

        self.stage, self.meta = stage, meta
        self.start, self.goal = start, goal
        self.robot_radius = float(robot_radius)
        self.approach = approach        # the obstacle stop's band: a last leg facing a mapped obstacle is re-planned
        # () -> (N, 2) x, z in the map's frame of what the obstacle stop sees holding the robot, or None: drawn
        # into the grid as obstacles while it holds (the map may lack the part of a box the stop faces)
        self.sightings = sightings
        self._seen_key = None
        # Blocked samples this near the robot at the start of its route are its own grown margin.
        self.skip_m = self.robot_radius + GridParams().clearance_m
        self.controller, self.robot_pose = controller, robot_pose
        self.period_s = float(period_s)
        self.grid = IncrementalGrid(grid_params(self.robot_radius))   # redrawn where the map changed
        self.looked_at = -1            # map revision of the last check
        self.checks = 0
        self.replans = 0
        # what the re-planner did, in order (printed by the command): the newest EVENTS_KEPT, and how many in all
        self.events: collections.deque[str] = collections.deque(maxlen=EVENTS_KEPT)
        self.said = 0
        self._events_lock = threading.Lock()
        self._held = False
        self.goal_moved_m: Optional[float] = None   # how far the current plan ends from the goal (None: at it)
        self._stop = None
        self._thread = None

    def step(self) -> Optional[str]:
        """One look at the map; returns what it did (a message) or None when nothing changed."""
        import numpy as np

        from vbnav.vision.geometry import Pose2
        from vbnav.vision.nav_grid import goal_cells, plan

        revision = self.stage.revision
        pose_ref = self.robot_pose()
        seen = self.sightings() if self.sightings is not None else None
        seen_key = None if seen is None or not len(seen) else np.round(seen, 3).tobytes()
        if (revision == self.looked_at and seen_key == self._seen_key) or pose_ref is None:
            return None
        self.looked_at, self._seen_key = revision, seen_key
        self.checks += 1
        here = self.start.compose(pose_ref)
        route = [self.start.compose(Pose2(x, z, 0.0)) for x, z in self.controller.route()]
        route = [(p.x, p.z) for p in route]
        ab = self.stage.abstraction       # its last pass's polygons: abstracting again here would repeat it
        grid = self.grid.update(self.stage.verified_snapshot(), np.array([(here.x, here.z)] + route),
                                footprints(ab.polygons if ab is not None else [], self.meta)
                                + sighting_squares(seen, self.grid.params.resolution_m))
        goal_free = grid.is_free(self.goal.x, self.goal.z)
        back_to_goal = self.goal_moved_m is not None and goal_free
        faced = self._faces_an_obstacle(grid, (here.x, here.z), route)
        clear = route_is_clear(grid, (here.x, here.z), route, self.skip_m)
        if not self._held and not back_to_goal and not faced and clear:
            return None
        path = plan(grid, (here.x, here.z), (self.goal.x, self.goal.z), GOAL_TOLERANCE_M, self.approach)
        if (not self._held and not back_to_goal and clear and path is not None
                and self._faces_an_obstacle(grid, (here.x, here.z), path[1:])):
            return None     # only the approach was wrong, and no other clears it: keep the route (no churn)
        at = f"map revision {revision}, robot at ({here.x:+.2f}, {here.z:+.2f})"
        goal = f"the goal ({self.goal.x:+.2f}, {self.goal.z:+.2f})"
        margin = f"{grid.grown_m:.2f} m (robot radius + clearance) of what the map holds"
        if path is None:
            self.controller.hold("no path")
            self.goal_moved_m = None        # no route: none ends near the goal
            if self._held:
                return None
            self._held = True
            if not goal_cells(grid, (self.goal.x, self.goal.z), GOAL_TOLERANCE_M):
                return self._say(f"{at}: {goal} now lies within {margin}, more than {GOAL_TOLERANCE_M:.2f} m "
                                 f"inside it or on it; holding until the map frees it")
            near = "" if goal_free else f" and to the free points within {GOAL_TOLERANCE_M:.2f} m of it"
            return self._say(f"{at}: the map closes every path to {goal}{near}; holding until it opens one")
        end = self.start.between(Pose2(*path[-1], 0.0))
        waypoints = [self.start.between(Pose2(x, z, 0.0)) for x, z in path[1:-1]]
        self.controller.replace_route([(w.x, w.z) for w in waypoints], (end.x, end.z))
        self.controller.hold(None)
        self._held = False
        self.replans += 1
        moved = math.hypot(path[-1][0] - self.goal.x, path[-1][1] - self.goal.z)
        self.goal_moved_m = moved if moved > 0.0 else None
        holds = "what the map now holds" + (" and the obstacle stop sees" if seen_key is not None else "")
        why = (f"the map frees {goal} again" if back_to_goal else
               f"the route's last leg faces {holds} within the obstacle stop's reach of the goal" if faced and clear
               else f"the route ahead crosses {holds}")
        if self.goal_moved_m is not None:
            why = goal_moved_note(self.goal, moved, margin).replace(" lies within", " now lies within", 1)
        return self._say(f"{at}: {why}; re-planned: " + " -> ".join(f"({x:+.2f}, {z:+.2f})" for x, z in path))

    def _faces_an_obstacle(self, grid, here, route) -> bool:
        """The route's last leg has a mapped obstacle in the obstacle stop's band (``nav_grid.band_clear``). A
        robot already on its last leg drives it from where it is (no waypoint to pass: no turn of the leg), and
        one at the goal (within ``ARRIVED_M``) has no leg left: its turn there is the controller's."""
        if self.approach is None or not route:
            return False
        from vbnav.vision.nav_grid import band_clear

        if len(route) > 1:
            return not band_clear(grid, route[-2], route[-1], self.approach)
        if math.hypot(route[-1][0] - here[0], route[-1][1] - here[1]) <= ARRIVED_M:
            return False
        return not band_clear(grid, here, route[-1], self.approach, turned=False)

    def _say(self, msg: str) -> str:
        with self._events_lock:
            self.events.append(msg)
            self.said += 1
        return msg

    def events_since(self, n: int) -> tuple[list[str], int]:
        """(the events after the first ``n`` said, as far as they are kept; how many have been said)."""
        with self._events_lock:
            new = min(self.said - n, len(self.events))
            return (list(self.events)[len(self.events) - new:] if new > 0 else []), self.said

    def start_thread(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="vbnav-replanner", daemon=True)
        self._thread.start()

    def stop_thread(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.step()
            except Exception as exc:   # a planner that cannot plan must not leave the robot on a stale route
                self.controller.hold("re-planner failed")
                self._say(f"re-planner failed ({exc!r}); the robot holds")
                return
