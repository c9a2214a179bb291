"""vbnav goto --map and vbnav map view against hostile input: goals, starts and maps whose planning grid
would not fit in memory are refused with a clear error, before the robot moves."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from vbnav.control.line_map_file import save_map
from vbnav.vision.line_map import LineMap
from vbnav.vision.nav_grid import MAX_CELLS, build_grid


def test_a_grid_too_large_to_plan_on_is_refused_not_allocated():
    """A goal 10 000 km away asked for a 2e8 x 2e8 cell grid (35 PiB): numpy's MemoryError, a traceback."""
    with pytest.raises(ValueError, match=r"planning grid .* cells"):
        build_grid(np.zeros((0, 2, 3)), extra_points=np.array([[0.0, 0.0], [1e7, 1e7]]))
    g = build_grid(np.zeros((0, 2, 3)), extra_points=np.array([[0.0, 0.0], [50.0, 50.0]]))
    assert g.blocked.size <= MAX_CELLS                  # a 50 m goal still plans


def test_goto_map_refuses_a_goal_too_far_for_the_grid(tmp_path, capsys):
    from vbnav.control.cli import main

    save_map(LineMap(), tmp_path / "empty.json")
    code = main(["goto", "--map", str(tmp_path / "empty.json"), "--static-map", "--goal", "1e7", "1e7", "0",
                 "--duration", "1"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "--goal" in err and "cells" in err and "bug" not in err and "Traceback" not in err


def test_map_view_refuses_a_map_too_large_for_its_planning_grid(tmp_path, capsys):
    """Two objects 100 km apart: the grid shown beside the segments would not fit; a traceback before."""
    from vbnav.control.cli import main

    box = [[0, 0], [0.5, 0], [0.5, 0.5]]
    far = [[x + 1e5, z] for x, z in box]
    save_map(LineMap(), tmp_path / "wide.json",
             {"objects": [{"footprint": box, "height": 0.5}, {"footprint": far, "height": 0.5}]})
    code = main(["map", "view", str(tmp_path / "wide.json"), "--port", "0", "--duration", "0.1"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "wide.json" in err and "cells" in err and "bug" not in err and "Traceback" not in err


@pytest.mark.parametrize("gap", [0.27, 0.2, 0.15, 0.1, 0.05])
def test_a_start_deep_in_the_grown_margin_of_a_wall_still_plans_out_of_it(gap):
    """The robot's centre ``gap`` m from a mapped wall (inside the radius + clearance band, 0.28 m): the
    search left a blocked start only into a free neighbour, so from 0.15 m on there was no path at all
    (goto --map exit 1, the re-planner holding the robot by the wall for good)."""
    from vbnav.vision.nav_grid import plan

    wall = np.array([[[-2.0, -0.3, 1.0], [2.0, -0.3, 1.0]]])         # along x at z = 1, 0.3 m high
    start, goal = (0.0, 1.0 - gap), (0.0, -2.0)
    grid = build_grid(wall, extra_points=np.array([start, goal]))
    path = plan(grid, start, goal)
    assert path is not None and path[0] == start and path[-1] == goal
    assert all(z < 1.0 for _, z in path)                               # never through the wall
    # a start beside a wall of a closed box is not a way into the box: walled in stays no path
    box = np.array([[[-1, -0.3, -1], [1, -0.3, -1]], [[1, -0.3, -1], [1, -0.3, 1]],
                    [[1, -0.3, 1], [-1, -0.3, 1]], [[-1, -0.3, 1], [-1, -0.3, -1]]], float)
    grid = build_grid(box, extra_points=np.array([(0.0, 1.0 - gap), (0.0, 3.0)]))
    assert plan(grid, (0.0, 1.0 - gap), (0.0, 3.0)) is None


def _wall_map(path):
    lmap = LineMap()
    P = np.array([[[-2.0, -0.3, 1.0], [2.0, -0.3, 1.0]]])
    lmap._insert(P, np.broadcast_to(1e-4 * np.eye(3), (1, 2, 3, 3)).copy(), np.full(1, -1), np.zeros(4))
    lmap.verified[:] = True
    save_map(lmap, path)
    return path


def test_goto_map_says_when_the_goal_itself_is_too_near_a_wall(tmp_path, capsys):
    """A goal 0.15 m from a mapped wall with --robot-radius 0.2: refused as 'no path ... clear of the mapped
    walls and objects by 0.2 m', untrue (it is 0.15 m clear) and silent on what to change. Now the goal is
    named, with the distance the planner keeps (radius + clearance) and how far it may move a goal."""
    from vbnav.control.cli import main

    path = _wall_map(tmp_path / "wall.json")
    code = main(["goto", "--map", str(path), "--static-map", "--goal", "0", "0.85", "0"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "--goal" in err and "within 0.28 m" in err and "--robot-radius" in err, err
    assert "more than 0.05 m inside" in err, err


def test_goto_map_plans_with_the_configured_footprint_radius_unless_robot_radius_is_given(tmp_path, capsys):
    """robot.footprint_radius (a round robot) is the planning radius of goto --map when --robot-radius is not
    given: the same goal 0.35 m from the wall, free for a 0.2 m robot, is refused for a 0.4 m one."""
    import yaml
    from vbnav.control.cli import main
    from vbnav.control.config import CONFIG_DIR

    path = _wall_map(tmp_path / "wall.json")
    cfg = yaml.safe_load((CONFIG_DIR / "sim_stereo.yaml").read_text())
    cfg["robot"]["footprint_radius"] = 0.4
    (tmp_path / "round.yaml").write_text(yaml.safe_dump(cfg))
    args = ["goto", "--map", str(path), "--static-map", "--goal", "0", "0.65", "0", "--duration", "0.1"]
    code = main(args + ["-c", str(tmp_path / "round.yaml")])
    out = "".join(capsys.readouterr())
    assert code == 1 and "within 0.48 m" in out and "planned path" not in out, out   # 0.4 m + 0.08 m clearance
    main(args + ["-c", str(tmp_path / "round.yaml"), "--robot-radius", "0.2"])
    out = "".join(capsys.readouterr())
    assert "planned path" in out and "within 0.48 m" not in out, out


def test_goto_map_start_plan_moves_a_goal_just_inside_the_margin_as_the_replanner_does(tmp_path, capsys):
    """A goal 0.25 m from a mapped wall, 3 cm inside the 0.28 m margin: the start plan refused it (exit 1) while
    the re-planner moves such a goal to the nearest free cell within GOAL_TOLERANCE_M. One rule for both: the
    start plan ends at that cell, says so and by how much, and the controller drives there."""
    from vbnav.control.cli import main
    from vbnav.control.map_planning import GOAL_TOLERANCE_M, map_grid, plan_path
    from vbnav.control.line_map_file import load_map
    from vbnav.vision.geometry import Pose2

    path = _wall_map(tmp_path / "wall.json")
    lmap, meta = load_map(path)
    planned = plan_path(lmap, meta, Pose2(0.0, 0.0, 0.0), Pose2(0.0, 0.75, 0.0), 0.2)
    assert planned is not None
    moved = math.hypot(planned[-1][0], planned[-1][1] - 0.75)
    assert 0.0 < moved <= GOAL_TOLERANCE_M + 0.05 * math.sqrt(0.5)
    grid = map_grid(lmap, meta, 0.2, extra_points=np.array([[0.0, 0.0], [0.0, 0.75]]))
    assert not grid.is_free(0.0, 0.75) and grid.is_free(*planned[-1])      # the end keeps the margin
    code = main(["goto", "--map", str(path), "--static-map", "--goal", "0", "0.75", "0", "--duration", "20"])
    out, err = capsys.readouterr()
    assert "no path" not in err and "within 0.28 m" in out, (out, err)
    assert f"ends at the nearest free point, {moved:.3f} m from it (tolerance 0.05 m)" in out, out
    assert f"({planned[-1][0]:+.2f}, {planned[-1][1]:+.2f})" in out.split("planned path")[1].splitlines()[0], out
    assert code == 0 and "goto ended: finished" in out, out     # driven to the path's end, not held
    m = re.search(r"simulator ground truth: x=([-+0-9.]+) z=([-+0-9.]+)", out)
    end = math.hypot(float(m.group(1)) - planned[-1][0], float(m.group(2)) - planned[-1][1])
    assert end < 0.02 and end < math.hypot(float(m.group(1)), float(m.group(2)) - 0.75), out


def test_goto_map_says_when_the_start_is_inside_a_mapped_object(tmp_path, capsys):
    """--start inside a stored box footprint: 'the goal is walled off' blamed the goal."""
    from vbnav.control.cli import main

    box = [[-0.5, 1.5], [0.5, 1.5], [0.5, 2.5], [-0.5, 2.5]]
    save_map(LineMap(), tmp_path / "box.json", {"objects": [{"footprint": box, "height": 0.5}]})
    code = main(["goto", "--map", str(tmp_path / "box.json"), "--static-map", "--start", "0", "2", "0",
                 "--goal", "0", "4", "0"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "--start (+0.00, +2.00) lies on a mapped wall or inside a mapped object" in err, err


def test_goto_map_on_the_simulator_refuses_a_start_that_disagrees_with_sim_start_pose(tmp_path, capsys):
    """The map's frame is the simulated robot's start when the map was built (recorded by `map build` as
    meta.sim_start_pose): a --start (default 0 0 0) that is not sim.start_pose seen from there planned from the
    wrong place, and the ground-truth error, measured from the robot's own start, did not show it."""
    import yaml

    from vbnav.control.cli import main
    from vbnav.control.config import CONFIG_DIR

    path = tmp_path / "m.json"
    save_map(LineMap(), path, {"sim_start_pose": [0.5, 0.0, 0.0]})
    cfg = yaml.safe_load((CONFIG_DIR / "sim_stereo.yaml").read_text())
    cfg["sim"] = dict(cfg.get("sim", {}), start_pose=[1.5, 0.5, 30.0])
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    rc = main(["goto", "-c", str(tmp_path / "robot.yaml"), "--map", str(path), "--goal", "0", "2", "0"])
    err = capsys.readouterr().err
    assert rc == 2 and "--start (+0.00, +0.00, +0.0 deg)" in err and "sim.start_pose [1.5, 0.5, 30.0]" in err, err
    assert "meta.sim_start_pose [0.5, 0.0, 0.0]" in err and "--start 1.000 0.500 30.0" in err, err
    from vbnav.control.config import load_config
    from vbnav.control.map_planning import sim_start_problem
    from vbnav.vision.geometry import Pose2
    meta = {"sim_start_pose": [0.5, 0.0, 0.0]}
    assert sim_start_problem(load_config(str(tmp_path / "robot.yaml")), meta, "m.json",
                             Pose2(1.0, 0.5, math.radians(30.0))) == ""
    assert sim_start_problem(load_config(str(tmp_path / "robot.yaml")), {}, "m.json", Pose2()) == ""   # not known
    data = json.loads(path.read_text())
    data["meta"]["sim_start_pose"] = [0.5, "x", 0.0]
    path.write_text(json.dumps(data))
    assert main(["goto", "-c", str(tmp_path / "robot.yaml"), "--map", str(path), "--goal", "0", "2", "0"]) == 2
    assert "meta.sim_start_pose" in capsys.readouterr().err


def test_a_goal_just_before_an_obstacle_is_approached_from_a_side_the_stop_band_leaves_clear():
    """A goal 0.5 m before a mapped box face, straight ahead of the start: the shortest route's last leg faces
    the box, which the obstacle stop's 0.8 m band reaches from 0.3 m short of the goal on (held there for good).
    With the stop's band (``Approach``) the route comes in along a straight 0.6 m leg whose band is clear, at
    little extra length; without it the route is the straight one."""
    import math

    from vbnav.vision.nav_grid import Approach, band_clear, path_length, plan

    def outline(x0, z0, x1, z1):        # a box's four top edges, 0.3 m above the floor (y down)
        c = [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]
        return [[[x, -0.3, z], [xx, -0.3, zz]] for (x, z), (xx, zz) in zip(c, c[1:] + c[:1])]

    box = outline(-0.5, 2.5, 0.5, 3.0)
    grid = build_grid(np.array(box, float), extra_points=np.array([(0.0, 0.0), (0.0, 2.0)]))
    band = Approach(reach_m=0.8, half_width_m=0.25)
    start, goal = (0.0, 0.0), (0.0, 2.0)
    straight = plan(grid, start, goal)
    assert len(straight) == 2 and not band_clear(grid, straight[-2], straight[-1], band)
    path = plan(grid, start, goal, approach=band)
    assert path[0] == start and path[-1] == goal
    last = math.hypot(path[-1][0] - path[-2][0], path[-1][1] - path[-2][1])
    assert last == pytest.approx(0.6, abs=0.05) and band_clear(grid, path[-2], path[-1], band)
    heading = math.degrees(math.atan2(path[-1][0] - path[-2][0], path[-1][1] - path[-2][1]))
    assert 45.0 <= abs(heading) <= 135.0, heading                  # from a side, not toward the box
    assert path_length(path) < path_length(straight) + 0.8, path_length(path)
    # no clear approach at all (walls 1.2 m either side: a 2 m band reaches one from every side): the route
    # stays the straight one
    walled = build_grid(np.array(box + outline(-1.3, -1.0, -1.2, 4.0) + outline(1.2, -1.0, 1.3, 4.0), float),
                        extra_points=np.array([(0.0, 0.0), (0.0, 2.0)]))
    assert plan(walled, start, goal, approach=Approach(reach_m=2.0, half_width_m=0.25)) == plan(walled, start, goal)
