"""A map file read back that is not what it claims is refused naming the file, the segment and what was expected."""
import json

import numpy as np
import pytest

from vbnav.control.line_map_file import MapFileError, load_map, save_map
from vbnav.vision.line_map import LineMap, MapParams


def _saved(tmp_path):
    m = LineMap(MapParams())
    P = np.array([[[0, -1, 2], [1, -1, 2]], [[0, -1, 3], [0, -0.2, 3]]], float)
    C = np.tile(np.eye(3) * 1e-4, (2, 2, 1, 1))
    m._insert(P, C, np.array([0, 1]), np.array([0, 0, 0, 0.0]))
    path = tmp_path / "map.json"
    save_map(m, path)
    return path


def _edit(path, change):
    data = json.loads(path.read_text())
    change(data["segments"])
    path.write_text(json.dumps(data))


def test_saved_map_loads(tmp_path):
    lmap, _ = load_map(_saved(tmp_path))
    assert len(lmap) == 2


def test_zero_length_segment_is_refused(tmp_path):
    path = _saved(tmp_path)
    _edit(path, lambda s: s[1].__setitem__("p1", s[1]["p0"]))
    with pytest.raises(MapFileError, match=r"map\.json: segments\[1\]: .*zero length"):
        load_map(path)


def test_duplicate_segment_ids_are_refused(tmp_path):
    path = _saved(tmp_path)
    _edit(path, lambda s: s[1].__setitem__("id", s[0]["id"]))
    with pytest.raises(MapFileError, match=r"map\.json: segments\[1\]: id .* also segments\[0\]"):
        load_map(path)


@pytest.mark.parametrize("cov", [[[1e-4, 0, 0], [0, -1e-4, 0], [0, 0, 1e-4]],
                                 [[1e-4, 1e-5, 0], [0, 1e-4, 0], [0, 0, 1e-4]]])
def test_covariance_not_symmetric_positive_definite_is_refused(tmp_path, cov):
    path = _saved(tmp_path)
    _edit(path, lambda s: s[0].__setitem__("cov1", cov))
    with pytest.raises(MapFileError, match=r"map\.json: segments\[0\]: cov1 .*symmetric positive definite"):
        load_map(path)
