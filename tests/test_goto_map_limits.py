"""vbnav goto --map and vbnav map view against hostile input: goals, starts and maps whose planning grid
would not fit in memory are refused with a clear error, before the robot moves."""
from __future__ import annotations

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
