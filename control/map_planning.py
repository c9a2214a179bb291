"""Planning on a saved line map: its traversability grid, a path around its walls and objects, and
that path in the goto controller's frame. Shared by ``vbnav goto --map`` and ``vbnav map view``."""
from __future__ import annotations


def map_grid(lmap, meta: dict, robot_radius: float, extra_points=None):
    """The traversability grid (vision/nav_grid.py) of a loaded map: its verified segments and the object
    footprints abstracted from them or stored with the map; ``extra_points`` (N, 2) x, z lie inside it."""
    import dataclasses

    import numpy as np

    from vbnav.vision.line_abstraction import object_polygons
    from vbnav.vision.nav_grid import GridParams, build_grid

    V = lmap.P[lmap.verified]
    polys = [p.footprint for p in object_polygons(V)]
    polys += [np.asarray(o["footprint"], float) for o in meta.get("objects", [])]
    params = dataclasses.replace(GridParams(), robot_radius_m=robot_radius)
    return build_grid(V, params, extra_points=extra_points, polygons=polys)


def plan_on_map(path: str, start, goal, robot_radius: float):
    """Waypoints (x, z) in the map's frame from ``start`` to ``goal`` around the walls and objects of the map
    file ``path``."""
    from vbnav.control.line_map_file import load_map

    return plan_path(*load_map(path), start, goal, robot_radius)


def plan_path(lmap, meta: dict, start, goal, robot_radius: float):
    """``plan_on_map`` on a loaded map."""
    import numpy as np

    from vbnav.vision.nav_grid import plan

    grid = map_grid(lmap, meta, robot_radius, extra_points=np.array([[start.x, start.z], [goal.x, goal.z]]))
    return plan(grid, (start.x, start.z), (goal.x, goal.z))


def map_route_in_reference_frame(planned, start, goal):
    """The planned path's intermediate waypoints and the goal, moved from the map's frame into the goto
    controller's reference frame (the robot's pose at the start, ``start`` in the map)."""
    from vbnav.vision.geometry import Pose2

    ref = [start.between(Pose2(x, z, 0.0)) for x, z in planned[1:-1]]
    return [(p.x, p.z) for p in ref], start.between(goal)


def localise_start(cfg, camera, lmap, map_path: str, guess, timeout_s: float = 3.0):
    """The robot's pose in the frame of the loaded map ``lmap`` (from ``map_path``) from one stereo frame of
    ``camera`` (vision/line_localise.py), searched around ``guess``: (Localisation, message). The camera is
    opened and closed again here (the run opens it for itself)."""
    from vbnav.vision.line_localise import View, localise
    from vbnav.vision.line_segments import detect_segments

    baseline = cfg.camera.stereo_baseline()
    if not baseline:
        return None, f"{cfg.source}: camera: localising against a line map needs a stereo camera (a baseline)"
    camera.connect()
    try:
        frame = camera.read(timeout_s)
    finally:
        camera.disconnect()
    if frame is None:
        return None, f"camera: no frame within {timeout_s:.0f} s to localise against {map_path}"
    model = cfg.camera.to_model()
    view = View(model.fx, model.fy, model.cx, model.cy, model.width, model.height, baseline,
                cfg.camera.mount.to_mount())
    r = localise(lmap, detect_segments(frame.image), view, guess)
    say = (f"{map_path}: {r.matches} of the {r.predicted} map segments predicted in view found, "
           f"{r.rms_px:.2f} px rms")
    return r, say
