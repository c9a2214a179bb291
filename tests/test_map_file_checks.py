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


def test_rival_flag_round_trips_and_an_older_map_keeps_three_viewpoints(tmp_path):
    """A candidate that was one of several rival matches is never verified from two viewpoints (vision/line_map.py
    separating_views): the flag is saved; a map written before it had none, so its candidates keep the rule
    they were built under (three viewpoints), and a flag that is not true/false is refused."""
    m = LineMap(MapParams())
    P = np.array([[[0, -1, 2], [1, -1, 2]], [[0, -1, 3], [0, -0.2, 3]]], float)
    m._insert(P, np.tile(np.eye(3) * 1e-4, (2, 2, 1, 1)), np.array([4, -1]), np.array([0, 0, 0, 0.0]))
    assert m.ambiguous.tolist() == [True, False]
    path = tmp_path / "map.json"
    save_map(m, path)
    assert load_map(path)[0].ambiguous.tolist() == [True, False]
    _edit(path, lambda segs: [s.pop("ambiguous") for s in segs])
    assert load_map(path)[0].ambiguous.tolist() == [True, True]
    _edit(path, lambda segs: segs[1].__setitem__("ambiguous", "no"))
    with pytest.raises(MapFileError, match=r"map\.json: segments\[1\]\.ambiguous: expected true or false, got 'no'"):
        load_map(path)


def test_stance_votes_round_trip_and_an_older_map_has_none(tmp_path):
    """What stood on a floor line (``LineMap.stance_votes``) is saved: a loaded map keeps a flat texture line
    out of the objects its abstraction makes (``LineMap.structure``). A map written before it had none; a
    count that is not one is refused, naming the segment."""
    m = LineMap(MapParams())
    P = np.array([[[0, 0, 2], [1, 0, 2]], [[0, 0, 3], [1, 0, 3]]], float)
    m._insert(P, np.tile(np.eye(3) * 1e-4, (2, 2, 1, 1)), np.array([-1, -1]), np.array([0, 0, 0, 0.0]),
              stance=np.array([1, -1], np.int8))
    m.verified[:] = True
    m.stance_votes[1] += [1, 4]
    path = tmp_path / "map.json"
    save_map(m, path)
    back = load_map(path)[0]
    assert back.stance_votes.tolist() == [[1, 0], [1, 5]] and back.structure().tolist() == [P[0].tolist()]
    _edit(path, lambda segs: [s.pop("stance") for s in segs])
    assert load_map(path)[0].stance_votes.tolist() == [[0, 0], [0, 0]]
    for bad, why in (([1], r": expected \[standing, flat\] counts, got \[1\]"),
                     ([1, -2], r"\[1\] \(flat\): expected an integer >= 0, got -2")):
        _edit(path, lambda segs: segs[1].__setitem__("stance", bad))
        with pytest.raises(MapFileError, match=r"map\.json: segments\[1\]\.stance" + why):
            load_map(path)


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


def _map(P, C, views=None):
    m = LineMap(MapParams())
    m._insert(np.asarray(P, float), np.asarray(C, float), np.arange(len(P)), np.array([0, 0, 0, 0.0]))
    if views is not None:
        m.views = views
    return m


GOOD_P = [[[0, -1, 2], [1, -1, 2]]]
GOOD_C = [[np.eye(3) * 1e-4] * 2]


@pytest.mark.parametrize("lmap, meta, why", [
    # rounded to 10 decimals on writing, a very certain endpoint's covariance is all zeros: singular
    (lambda: _map(GOOD_P, [[np.eye(3) * 1e-12] * 2]), None, r"segments\[0\]: cov0 .*symmetric positive definite"),
    (lambda: _map([[[0, -1, 2], [np.nan, -1, 2]]], GOOD_C), None, r"segments\[0\]\.p1: expected \[x, y, z\] of finite"),
    # two endpoints 1e-7 m apart are one point once rounded to the file's 6 decimals
    (lambda: _map([[[0, -1, 2], [1e-7, -1, 2]]], GOOD_C), None, r"segments\[0\]: p0 and p1 are the same point"),
    (lambda: _map(GOOD_P, GOOD_C, views=[[np.array([0, 0, np.inf, 0.0])]]), None, r"segments\[0\]\.views"),
    (lambda: _map(GOOD_P, GOOD_C), {"objects": [{"footprint": [[0, np.nan]], "height": 0.3}]}, r"meta\.objects\[0\]"),
])
def test_save_refuses_what_load_would_refuse_and_writes_nothing(tmp_path, lmap, meta, why):
    """save_map wrote maps load_map then refused (a map build's whole drive lost at the next goto); it checks
    what it writes with load_map's own checks first, and leaves the file there untouched."""
    path = tmp_path / "map.json"
    path.write_text("the previous map\n")
    with pytest.raises(MapFileError, match=rf"map\.json: not saved, it could not be loaded back: .*{why}"):
        save_map(lmap(), path, meta)
    assert path.read_text() == "the previous map\n" and sorted(p.name for p in tmp_path.iterdir()) == ["map.json"]


@pytest.mark.parametrize("field, value, expected", [
    ("verified", "false", "expected true or false"),       # a non-empty string was np.array(..., bool): True
    ("hypothesis", 0, "expected true or false"),
    ("support", 2.5, "expected an integer >= 0"),           # cut to 2
    ("misses", -1, "expected an integer >= 0"),
    ("group", True, "expected an integer >= -1"),
])
def test_segment_counts_and_flags_of_another_type_are_refused(tmp_path, field, value, expected):
    """A hand-edited map's "verified": "false" loaded as verified (planning trusted the segment), 2.5 support
    as 2: refused naming the segment and the field."""
    path = _saved(tmp_path)
    _edit(path, lambda s: s[1].__setitem__(field, value))
    with pytest.raises(MapFileError, match=rf"map\.json: segments\[1\]\.{field}: {expected}, got {value!r}"):
        load_map(path)


def test_frames_must_be_a_count(tmp_path):
    path = _saved(tmp_path)
    data = json.loads(path.read_text())
    data["frames"] = -3
    path.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match=r"map\.json: frames: expected an integer >= 0, got -3"):
        load_map(path)


@pytest.mark.parametrize("frames", ["many", -1, 2.5])
def test_meta_frames_must_be_a_count(tmp_path, frames):
    """goto --map-out adds its frames to meta.frames when it saves the grown map: a word there loaded, and the
    drive ended in a traceback with the grown map lost. Refused at load."""
    path = tmp_path / "map.json"
    save_map(LineMap(MapParams()), path, {"frames": 3})
    data = json.loads(path.read_text())
    data["meta"]["frames"] = frames
    path.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match=rf"map\.json: meta\.frames: expected an integer >= 0, got {frames!r}"):
        load_map(path)


def test_a_key_given_twice_is_refused(tmp_path):
    """JSON readers keep the last of two equal keys: a hand-edited second "params" or "segments" replaced
    the first silently."""
    path = _saved(tmp_path)
    text = path.read_text()
    path.write_text(text[:-1] + ', "frames": 7}')
    with pytest.raises(MapFileError, match=r"map\.json: not a JSON map file \(duplicate key 'frames'\)"):
        load_map(path)


@pytest.mark.parametrize("field, value, expected", [
    ("support", 10 ** 30, r"support: expected an integer >= 0, at most 2\^53"),     # numpy overflow: a traceback
    ("id", True, r"id: expected an integer >= 0, got True"),                         # loaded as id 1
    ("id", 2.0, r"id: expected an integer >= 0, got 2.0"),
    ("p0", ["1", "2", "3"], r"p0: expected \[x, y, z\] of finite numbers"),          # read as 1, 2, 3
    ("p1", [True, False, True], r"p1: expected \[x, y, z\] of finite numbers"),
    ("cov0", [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, "1e-4"]], r"cov0: expected a 3x3 matrix of finite numbers"),
    ("cov1", (np.eye(3) * 1e-300).tolist(), r"cov1: sigmas .* expected between 1e-09 and 1000 m"),  # Singular matrix
    ("cov1", (np.eye(3) * 1e300).tolist(), r"cov1: sigmas .* expected between 1e-09 and 1000 m"),
    ("views", [[0, 0, 0, "north"]], r"views: expected \[x, y, z, heading\] finite numbers per view"),
])
def test_segment_numbers_that_are_not_numbers_or_not_sane_are_refused(tmp_path, field, value, expected):
    """Found by an adversarial run: numbers given as strings or true/false loaded (np.array(..., float) reads
    them), a support of 10^30 was an OverflowError traceback, a covariance of 1e-300 a LinAlgError one."""
    path = _saved(tmp_path)
    _edit(path, lambda s: s[1].__setitem__(field, value))
    with pytest.raises(MapFileError, match=rf"map\.json: segments\[1\]\.?{expected}" if field != "cov1"
                       else rf"map\.json: segments\[1\]: {expected}"):
        load_map(path)


def test_a_segment_without_a_field_is_named(tmp_path):
    path = _saved(tmp_path)
    _edit(path, lambda s: s[1].pop("cov0"))
    with pytest.raises(MapFileError, match=r"map\.json: segments\[1\]: missing cov0"):
        load_map(path)
    data = json.loads(path.read_text())
    data["segments"] = {}
    path.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match=r"map\.json: segments: expected a list of segments, got dict"):
        load_map(path)


@pytest.mark.parametrize("params, expected", [
    ({"max_range_m": -3.0}, r"max_range_m: expected > 0, got -3.0"),
    ({"verify_views": 0}, r"verify_views: expected >= 1, got 0"),
    ({"miss_limit": -1}, r"miss_limit: expected >= 1, got -1"),
    ({"min_range_m": 100.0}, r"min_range_m 100.0 must be below max_range_m 3.0"),
    ({"view_angle_deg": 0.0}, r"view_angle_deg: expected > 0 and <= 180, got 0.0"),
])
def test_map_parameters_the_mapping_cannot_work_with_are_refused(tmp_path, params, expected):
    """A map's params are applied to the mapping that goes on from it (goto --map keeps mapping): max_range_m
    -3 was taken without a word and grew another map. The values each parameter's meaning allows, or refused."""
    path = _saved(tmp_path)
    data = json.loads(path.read_text())
    data["params"].update(params)
    path.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match=rf"map\.json: params: {expected}"):
        load_map(path)
    with pytest.raises(ValueError, match=expected):
        MapParams(**params)


def test_an_object_of_negative_height_is_refused(tmp_path):
    m = LineMap(MapParams())
    with pytest.raises(MapFileError, match=r"meta\.objects\[0\]: expected footprint .* and height \(>= 0\)"):
        save_map(m, tmp_path / "map.json", {"objects": [{"footprint": [[0, 0], [1, 0], [1, 1]], "height": -0.5}]})


@pytest.mark.parametrize("footprint", [[[1.0, 2.0]], [[1.0, 2.0], [1.0, 2.0]]])
def test_an_object_whose_footprint_is_one_point_is_refused(tmp_path, footprint):
    """meta.objects took a footprint of one point (or one point twice): an object of no extent, which the
    planning grid drew as one cell. Two distinct points are a face (the abstraction writes one for two corners
    it saw) and three or more a polygon: both load."""
    path = _saved(tmp_path)
    data = json.loads(path.read_text())
    data["meta"] = {"objects": [{"footprint": footprint, "height": 0.5}]}
    path.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match=r"map\.json: meta\.objects\[0\]: footprint .* is one point, expected "
                                           r"at least two distinct \[x, z\] points"):
        load_map(path)
    for ok in ([[0.0, 2.0], [0.6, 2.0]], [[0.0, 2.0], [0.6, 2.0], [0.6, 2.5]]):
        data["meta"] = {"objects": [{"footprint": ok, "height": 0.5}]}
        path.write_text(json.dumps(data))
        assert load_map(path)[1]["objects"][0]["footprint"] == ok
