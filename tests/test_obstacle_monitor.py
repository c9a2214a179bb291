"""Stop/slow zones, k-of-n persistence and release debounce (pure logic), config validation."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

import disparity_scenes as ds  # same directory

from vbnav.control.config import ConfigError, parse_config
from vbnav.control.stages.obstacles import ObstacleMonitor, ObstacleStage, make_obstacle_stage, points_in_polygon, to_robot_frame, zone_counts
from vbnav.control.config.obstacles import ObstaclesConfig, ZoneConfig
from vbnav.drivers.camera import Frame
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.obstacles import detect_obstacles
from vbnav.vision.stereo import StereoRig

FRAME_NS = 66_666_667          # 15 Hz


def _pts(z, x=0.0, n=20):
    return np.column_stack([np.full(n, x), np.full(n, z)]).astype(np.float32)


NONE = np.zeros((0, 2), np.float32)


def test_band_and_polygon_zones():
    band = ZoneConfig(name="b", distance=1.0, half_width=0.3)
    pts = np.array([[0.0, 0.5], [0.29, 0.99], [0.31, 0.5], [0.0, 1.01], [0.0, -0.1]], np.float32)
    assert zone_counts(band, pts) == 2
    poly = ZoneConfig(name="p", polygon=[(-0.3, 0.0), (0.3, 0.0), (0.6, 1.0), (-0.6, 1.0)])   # widening ahead
    assert zone_counts(poly, pts) == 3                                  # (0.31, 0.5) is inside the trapezoid
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert points_in_polygon(np.array([[0.5, 0.5], [1.5, 0.5], [0.5, -0.1]]), sq).tolist() == [True, False, False]


def test_monitor_stop_needs_k_of_n_and_releases_after_debounce():
    cfg = ObstaclesConfig(persist_k=2, persist_n=3, release_s=0.5)
    m = ObstacleMonitor(cfg)
    t = 0
    scales = []
    # frame 0: one noisy frame with an obstacle in the stop zone -> no stop
    for pts in [_pts(0.5), NONE, NONE, _pts(0.5), _pts(0.5), _pts(0.5)]:
        scales.append(m.update(t, pts).scale)
        t += FRAME_NS
    assert scales[:4] == [1.0, 1.0, 1.0, 1.0]
    assert scales[4] == 0.0 and scales[5] == 0.0 and "stop" in m.reason
    # obstacle removed: k-of-n needs 2 clear frames, then 0.5 s debounce before moving again
    out = []
    for _ in range(15):
        out.append((t, m.update(t, NONE).scale))
        t += FRAME_NS
    first_go = next(tt for tt, s in out if s > 0)
    clear_from = out[0][0]
    assert first_go - clear_from >= 0.5e9
    assert first_go - clear_from <= 0.5e9 + 3 * FRAME_NS
    assert out[-1][1] == 1.0


def test_monitor_slow_zone_and_negative_points():
    cfg = ObstaclesConfig(persist_k=1, persist_n=1, release_s=0.0)
    m = ObstacleMonitor(cfg)
    assert m.update(0, _pts(1.2)).scale == pytest.approx(0.4)          # slow band 1.5 m
    assert m.update(FRAME_NS, NONE, _pts(0.6)).scale == 0.0             # a step down in the stop band
    assert m.update(2 * FRAME_NS, NONE).scale == 1.0
    m2 = ObstacleMonitor(ObstaclesConfig(persist_k=1, persist_n=1, negative_stops=False))
    assert m2.update(0, NONE, _pts(0.6)).scale == 1.0


def test_config_validation_names_the_key():
    with pytest.raises(ConfigError, match=r"obstacles\.zones\.0: .*band needs both"):
        parse_config({"obstacles": {"zones": [{"name": "z", "distance": 1.0}]}}, "robot.yaml")
    with pytest.raises(ConfigError, match=r"robot.yaml: obstacles\.stop_distance: unknown key"):
        parse_config({"obstacles": {"stop_distance": 1.0}}, "robot.yaml")
    with pytest.raises(ConfigError, match="persist_k"):
        parse_config({"obstacles": {"persist_k": 4, "persist_n": 3}})
    assert parse_config({}).obstacles.zones[0].action == "stop"


def test_to_robot_frame_uses_the_mount():
    mount = CameraMount(0.25, forward=0.1, lateral=0.05, pitch=0.0, yaw=math.radians(90))
    out = to_robot_frame(np.array([[0.0, 1.0]], np.float32), mount)   # 1 m along a camera looking right
    assert out[0] == pytest.approx([1.05, 0.1], abs=1e-6)


def _stage_cfg(mount=None, **kw):
    camera = {"options": {"stereo_baseline": 0.075}}
    if mount:
        camera["mount"] = mount
    cfg = parse_config({"camera": camera,
                        "obstacles": {"persist_k": 1, "persist_n": 1, "release_s": 0.2, **kw}})
    return cfg


def test_stage_from_config_and_frames():
    stage = ObstacleStage.from_config(_stage_cfg())
    assert stage.rig.baseline == 0.075 and stage.kind == "obstacles"
    rig = stage.rig
    near_box = ds.Scene(0.25, 0.0, boxes=(ds.Box(-0.1, 0.1, 0.55, 0.7, 0.05),))   # 0.65 m from the axle
    clear = ds.Scene(0.25, 0.0)
    img = np.zeros((480, 640), np.uint8)
    e = stage.process(Frame(img, 0, 1, disparity=ds.render(clear, rig).disparity), Pose2())
    assert e.ok and e.info["speed_scale"] == 1.0 and e.value.nearest is None
    e = stage.process(Frame(img, FRAME_NS, 2, disparity=ds.render(near_box, rig).disparity), Pose2())
    assert e.info["speed_scale"] == 0.0 and "stop" in e.info["reason"]
    assert e.value.nearest[0] == pytest.approx(0.65, abs=0.02)             # camera 0.1 m ahead of the axle
    e = stage.process(Frame(img, 2 * FRAME_NS, 3, disparity=ds.render(clear, rig).disparity), Pose2())
    assert e.info["speed_scale"] == 0.0                                    # debounce: not yet
    e = stage.process(Frame(img, 5 * FRAME_NS, 4, disparity=ds.render(clear, rig).disparity), Pose2())
    assert e.info["speed_scale"] == 1.0


def test_stage_uses_sgbm_without_disparity_and_stops_when_blind():
    stage = ObstacleStage.from_config(_stage_cfg())
    scene = ds.Scene(0.25, 0.0, boxes=(ds.Box(-0.15, 0.15, 0.6, 0.75, 0.08), ds.Box(-30, 30, 12, 12.5, 8, texel=0.05)))
    left, right, _ = ds.textured_pair(scene, stage.rig)
    e = stage.process(Frame(left, 0, 1, right=right), Pose2())
    assert e.ok and e.info["speed_scale"] == 0.0
    assert e.value.nearest[0] == pytest.approx(0.7, abs=0.05)
    e = stage.process(Frame(left, FRAME_NS, 2), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and "no disparity" in e.info["reason"]


def test_make_obstacle_stage_only_when_enabled():
    assert make_obstacle_stage(parse_config({})) is None
    st = make_obstacle_stage(_stage_cfg(enabled=True))
    assert isinstance(st, ObstacleStage)


def test_stage_takes_the_baseline_from_the_frames_when_the_config_has_none():
    stage = ObstacleStage.from_config(parse_config({"obstacles": {"persist_k": 1, "persist_n": 1}}))
    assert stage.rig is None
    rig = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
    disp = ds.render(ds.Scene(0.25, 0.0, boxes=(ds.Box(-0.1, 0.1, 0.55, 0.7, 0.05),)), rig).disparity
    img = np.zeros((480, 640), np.uint8)
    e = stage.process(Frame(img, 0, 1, disparity=disp), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and "baseline" in e.info["reason"]
    K = [[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]]
    e = stage.process(Frame(img, FRAME_NS, 2, disparity=disp, meta={"baseline_m": 0.075, "K": K}), Pose2())
    assert e.ok and stage.rig == rig and e.info["speed_scale"] == 0.0      # the box is in the stop band
    assert e.value.nearest[0] == pytest.approx(0.65, abs=0.02)


def test_shipped_stereo_config_builds_the_stage():
    from vbnav.control.config import load_config
    stage = make_obstacle_stage(load_config("sim_stereo"))
    assert stage is not None and stage.rig.baseline == 0.075
    assert [z.action for z in stage.cfg.zones] == ["stop", "slow"]


def test_stage_ground_settings_reach_the_ground_model():
    """camera.mount.roll_deg and obstacles.ground_model / mount_* / ground settings are used: the prior carries the roll,
    the fit the bounds, the piecewise ground its corridor, grade and camber; 'plane' turns it off."""
    stage = ObstacleStage.from_config(_stage_cfg(mount={"roll_deg": 1.5}, mount_height_tol=0.03, mount_tilt_tol_deg=1.0,
                                                 ground_corridor_half_width=0.8, max_grade_change=0.05,
                                                 cross_slope_allowance=0.04, ground_band_ratio=1.3))
    assert math.degrees(stage.prior.floor(stage.rig).roll) == pytest.approx(1.5, abs=1e-9)
    fp = stage.fit_params
    assert (fp.max_height_change, fp.max_pitch_change_deg, fp.max_roll_change_deg) == (0.03, 1.0, 1.0)
    g = stage.ground
    assert (g.corridor_half_width, g.max_grade_change, g.cross_slope_allowance, g.band_ratio) == (0.8, 0.05, 0.04, 1.3)
    # The camera is in fact level, the config says 1.5 degrees of roll and allows 1: the fit stays
    # inside the bound (at least 0.5 degrees of roll), and the floor inside the zones is still clear.
    level = ds.render(ds.Scene(0.25, 0.0), stage.rig).disparity
    e = stage.process(Frame(np.zeros((480, 640), np.uint8), 0, 1, disparity=level), Pose2())
    assert e.ok and e.info["speed_scale"] == 1.0
    s = detect_obstacles(level, stage.rig, stage.prior, stage.fit_params, stage.params, stage.ground)
    assert 0.5 - 1e-6 <= math.degrees(s.fit.floor.roll) <= 2.5 + 1e-6
    assert ObstacleStage.from_config(_stage_cfg(ground_model="plane")).ground is None


def _lens_cap_run(box: bool, covered=(10, 40), frames=60):
    """The simulated stereo camera (sim_stereo) standing at the room's start, its lens covered for
    ``covered`` frames (black images, all-NaN disparity: what an OAK gives too)."""
    from vbnav.control.config import load_config
    from vbnav.drivers.sim.camera import SimCamera
    from vbnav.drivers.sim.world import World
    cfg = load_config("sim_stereo")
    world = World.by_name(cfg.sim.world, cfg.sim.seed)
    if box:
        world.add_box("obstacle", (-1.5, -1.55), (0.3, 0.3, 0.3))      # its face 0.75 m ahead: the stop zone
    cam = SimCamera(world, cfg.camera.to_model(), cfg.camera.mount.to_mount(), pose_fn=lambda: Pose2(), clock=None,
                    rate_hz=15, noise_std=2.0, seed=4, stereo_baseline=0.075)
    stage = make_obstacle_stage(cfg)
    out = []
    for i in range(frames):
        cam.occluded = covered[0] <= i < covered[1]
        out.append(stage.process(cam.render_frame(cfg.sim.start(), int(i * 1e9 / 15), i), Pose2()))
    return out


def test_a_covered_lens_is_blind_and_stops_until_the_zones_are_seen_clear():
    """Nothing seen is nothing cleared: with the lens covered the stage says blind (not ok, speed 0) on
    every frame, and after it the speed rises only once the zones were seen clear for release_s."""
    with_box = _lens_cap_run(box=True)
    assert all(e.info["speed_scale"] == 0.0 for e in with_box[3:])          # box, blind, box again
    blind = with_box[10:40]
    assert all(not e.ok and "blind: 0% of the stop zones' floor" in e.info["reason"] for e in blind)
    clear = _lens_cap_run(box=False)
    assert all(e.ok and e.info["speed_scale"] == 1.0 for e in clear[:10])
    assert all(not e.ok and e.info["speed_scale"] == 0.0 for e in clear[10:40])
    release = next(i for i in range(40, 60) if clear[i].info["speed_scale"] == 1.0)
    assert (release - 40) / 15 >= ObstaclesConfig().release_s - 1 / 15       # not the first clear frame


def test_a_frame_of_another_size_is_blind_and_a_bgra_pair_is_matched():
    """A wrong-size frame (a camera that changed mode) stops like a blind one instead of ending the run;
    a BGRA pair (some V4L2 cameras) goes through SGBM like a BGR one."""
    stage = ObstacleStage.from_config(_stage_cfg(source="sgbm"))
    rig = stage.rig
    clear = ds.Scene(0.25, 0.0, boxes=(ds.Box(-30, 30, 12, 12.5, 8, texel=0.05),))
    left, right, _ = ds.textured_pair(clear, rig)
    e = stage.process(Frame(left, 0, 1, right=right), Pose2())
    assert e.ok and e.info["speed_scale"] == 1.0
    small = Frame(left[::2, ::2].copy(), FRAME_NS, 2, right=right[::2, ::2].copy())
    e = stage.process(small, Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and "320x240, the camera calibration is for 640x480" in e.info["reason"]
    bgra = [cv2.cvtColor(im, cv2.COLOR_GRAY2BGRA) for im in (left, right)]
    e = stage.process(Frame(bgra[0], 10 * FRAME_NS, 3, right=bgra[1]), Pose2())
    assert e.ok


def test_a_pair_whose_images_differ_in_size_is_blind():
    """SGBM on a left and right image of different sizes (one camera of the pair renegotiated its mode) raised
    ValueError out of the stage, which ends the run; the frame is blind now (not ok, stop) saying both sizes,
    and the next good pair is judged again."""
    stage = ObstacleStage.from_config(_stage_cfg(source="sgbm"))
    clear = ds.Scene(0.25, 0.0, boxes=(ds.Box(-30, 30, 12, 12.5, 8, texel=0.05),))
    left, right, _ = ds.textured_pair(clear, stage.rig)
    e = stage.process(Frame(left, 0, 1, right=right[::2, ::2].copy()), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0
    assert "640x480" in e.info["reason"] and "320x240" in e.info["reason"], e.info["reason"]
    e = stage.process(Frame(left, FRAME_NS, 2, right=right), Pose2())
    assert e.ok


@pytest.mark.parametrize("baseline", [-0.075, float("nan"), float("inf")])
def test_a_frame_baseline_that_is_no_distance_is_no_baseline(baseline):
    """meta['baseline_m'] of -0.075, NaN or inf (a device calibration gone wrong) raised ValueError from
    StereoRig out of the stage on every frame, which ends the run; the stage now says it has no usable baseline
    (not ok, stop), naming the value, and takes a good one from a later frame."""
    stage = ObstacleStage.from_config(parse_config({"obstacles": {"persist_k": 1, "persist_n": 1}}))
    rig = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
    disp = ds.render(ds.Scene(0.25, 0.0), rig).disparity
    img = np.zeros((480, 640), np.uint8)
    e = stage.process(Frame(img, 0, 1, disparity=disp, meta={"baseline_m": baseline}), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and "baseline" in e.info["reason"]
    assert str(baseline) in e.info["reason"], e.info["reason"]
    assert stage.rig is None
    e = stage.process(Frame(img, FRAME_NS, 2, disparity=disp, meta={"baseline_m": 0.075}), Pose2())
    assert e.ok and stage.rig.baseline == 0.075


def test_a_disparity_that_is_not_float_pixels_is_blind():
    """Frame.disparity is float pixels: an integer one (an OAK's raw fixed-point disparity, 3 subpixel bits,
    passed on unscaled) was judged as pixels, the whole floor 8 times nearer, i.e. high above the plane: a stop
    with an obstacle 'at 0.15 m', ok. It is blind now (not ok, stop), naming the dtype."""
    stage = ObstacleStage.from_config(_stage_cfg())
    clear = ds.render(ds.Scene(0.25, 0.0), stage.rig).disparity
    img = np.zeros((480, 640), np.uint8)
    e = stage.process(Frame(img, 0, 1, disparity=(np.nan_to_num(clear) * 8).astype(np.uint16)), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and "uint16" in e.info["reason"], e.info
    e = stage.process(Frame(img, FRAME_NS, 2, disparity=clear.astype(np.float64)), Pose2())
    assert e.ok and e.info["speed_scale"] == 0.0                  # clear, but the release debounce runs


@pytest.mark.parametrize("source", ["disparity", "sgbm"])
def test_a_frame_without_what_the_source_needs_says_what_it_has(source):
    """obstacles.source disparity on a frame with only a stereo pair (or sgbm on one with only a disparity) said
    'frame has no disparity and no right image' of a frame that had one of them; it says what the source
    needs and that the frame's other input is not used."""
    stage = ObstacleStage.from_config(_stage_cfg(source=source))
    clear = ds.Scene(0.25, 0.0, boxes=(ds.Box(-30, 30, 12, 12.5, 8, texel=0.05),))
    left, right, truth = ds.textured_pair(clear, stage.rig)
    frame = (Frame(left, 0, 1, right=right) if source == "disparity" else
             Frame(left, 0, 1, disparity=truth.disparity))
    e = stage.process(frame, Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0
    assert f"obstacles.source is {source}" in e.info["reason"], e.info["reason"]


@pytest.mark.parametrize("K,says", [
    ([[0.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]], "meta['K']: fx: the focal length must be > 0 px, got 0.0"),
    ([[400.0, 0, float("nan")], [0, 400.0, 239.5], [0, 0, 1]], "meta['K']: cx: expected a finite number, got nan"),
    ([[400.0, 0, 900.0], [0, 400.0, 239.5], [0, 0, 1]], "meta['K']: cx: the principal point 900.0 is outside"),
    ([[400.0, 0, 319.5]], "meta['K'] has shape (1, 3), expected a 3x3"),
    ([400.0, 400.0, 319.5, 239.5], "meta['K'] has shape (4,), expected a 3x3"),
    ("K", "meta['K'] is 'K': not numbers"),
    ([["a", 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]], "not numbers"),
])
def test_frame_intrinsics_that_are_no_camera_are_refused(K, says):
    """meta['K'] with a zero focal length or a NaN principal point raised ValueError from StereoRig out of the
    stage on every frame (which ends the run); a principal point outside the image was used, every floor
    distance wrong; one that is no 3x3 matrix of numbers (a flat list, a row, a string) raised IndexError or
    ValueError, naming no field. Such intrinsics are refused (not ok, stop) naming the value, and good ones
    are taken later."""
    stage = ObstacleStage.from_config(parse_config({"obstacles": {"persist_k": 1, "persist_n": 1}}))
    rig = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
    disp = ds.render(ds.Scene(0.25, 0.0), rig).disparity
    img = np.zeros((480, 640), np.uint8)
    e = stage.process(Frame(img, 0, 1, disparity=disp, meta={"baseline_m": 0.075, "K": K}), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and says in e.info["reason"], e.info["reason"]
    assert stage.rig is None
    good = [[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]]
    e = stage.process(Frame(img, FRAME_NS, 2, disparity=disp, meta={"baseline_m": 0.075, "K": good}), Pose2())
    assert e.ok and stage.rig == rig


def test_the_nearest_obstacle_is_looked_for_in_the_stop_zones_width():
    """The report's nearest obstacle ('in the stop zone's width') was looked for within the narrowest band of
    any zone: with a wide stop band and a narrow slow band, an obstacle that stopped the robot was 'nowhere'
    (nearest None). It is looked for within the stop zones' width, as the watched floor is."""
    zones = [{"name": "stop", "action": "stop", "distance": 0.8, "half_width": 0.5},
             {"name": "slow", "action": "slow", "distance": 1.5, "half_width": 0.2}]
    stage = ObstacleStage.from_config(_stage_cfg(zones=zones))
    box = ds.Scene(0.25, 0.0, boxes=(ds.Box(0.28, 0.42, 0.55, 0.7, 0.05),))     # right of the slow band
    e = stage.process(Frame(np.zeros((480, 640), np.uint8), 0, 1, disparity=ds.render(box, stage.rig).disparity),
                      Pose2())
    assert e.ok and e.info["speed_scale"] == 0.0 and e.info["zones"]["slow"] == 0
    assert e.value.nearest is not None and e.value.nearest[0] == pytest.approx(0.65, abs=0.03), e.value.nearest


def test_obstacles_without_zones_are_refused_at_load():
    """obstacles.zones: [] was accepted, and building the stage then failed with "max() arg is an empty
    sequence" (no stop zone to watch the floor of). It is refused at load, naming the key."""
    with pytest.raises(ConfigError, match=r"robot.yaml: obstacles: zones: at least one zone"):
        parse_config({"obstacles": {"enabled": True, "zones": []}}, "robot.yaml")


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_zone_polygon_with_a_vertex_that_is_no_number_is_refused_at_load(bad):
    """A polygon vertex of NaN or inf was accepted: no point is inside such a polygon, so the stop zone never
    triggered (and its floor outline came out of NaN pixels). It is refused at load, naming the zone."""
    with pytest.raises(ConfigError, match=r"obstacles\.zones\.0: zone 'p': polygon vertices must be finite"):
        parse_config({"obstacles": {"zones": [{"name": "p", "polygon": [(-0.3, 0.0), (0.3, 0.0), (bad, 1.0)]}]}},
                     "robot.yaml")


@pytest.mark.parametrize("make,says", [
    (lambda l, r: (l, r.astype(np.uint16) * 256), "uint8, the right one uint16"),
    (lambda l, r: (l.astype(np.uint16) * 256, r), "uint16, the right one uint8"),
    (lambda l, r: (np.dstack([l, l]), r), "shape (480, 640, 2)"),
])
def test_a_pair_sgbm_cannot_match_is_blind(make, says):
    """A pair of two dtypes (8-bit left, 16-bit right) raised cv2.error out of the stage, which ends the run, and
    the other way round SGBM matched a 16-bit left against an 8-bit right each stretched on its own; a 2-channel
    image raised ValueError. Each is blind now (not ok, stop), saying why; the next good pair is judged."""
    stage = ObstacleStage.from_config(_stage_cfg(source="sgbm"))
    clear = ds.Scene(0.25, 0.0, boxes=(ds.Box(-30, 30, 12, 12.5, 8, texel=0.05),))
    left, right, _ = ds.textured_pair(clear, stage.rig)
    bad_left, bad_right = make(left, right)
    e = stage.process(Frame(bad_left, 0, 1, right=bad_right), Pose2())
    assert not e.ok and e.info["speed_scale"] == 0.0 and says in e.info["reason"], e.info["reason"]
    assert stage.process(Frame(left, FRAME_NS, 2, right=right), Pose2()).ok


@pytest.mark.parametrize("make", [
    # 16-bit, a highlight (a lamp, a reflection) in the right image only: each image was stretched to 8 bits on
    # its own, so the right one came out darker than the left and SGBM matched little ("covered lens, darkness")
    lambda l, r: (l.astype(np.uint16) * 64, np.where(np.arange(r.shape[1]) < 8, 65535,
                                                     r.astype(np.uint16) * 64).astype(np.uint16)),
    # float 0-1 with NaN pixels: NORM_MINMAX over a NaN gave a black pair, blind as "darkness"
    lambda l, r: (np.where(np.arange(l.shape[0])[:, None] == 0, np.nan, l / 255.0).astype(np.float32),
                  (r / 255.0).astype(np.float32)),
], ids=["uint16-highlight", "float-nan"])
def test_a_pair_of_another_dtype_than_8_bits_is_refused_naming_it(make):
    """The tracking stages refuse images that are not uint8 (no clearly right conversion); the obstacle stage
    stretched each image of a 16-bit or float pair to 8 bits on its own, and stopped the robot for the wrong
    reason ("covered lens, darkness") or slowed it for an obstacle that was not there. Such a pair is now an
    unusable frame that holds the robot, its reason naming the dtype; the next 8-bit pair is judged."""
    stage = ObstacleStage.from_config(_stage_cfg(source="sgbm"))
    clear = ds.Scene(0.25, 0.0, boxes=(ds.Box(-30, 30, 12, 12.5, 8, texel=0.05),))
    left, right, _ = ds.textured_pair(clear, stage.rig)
    bad_left, bad_right = make(left, right)
    e = stage.process(Frame(bad_left, 0, 1, right=bad_right), Pose2())
    dtype = str(bad_left.dtype)
    assert not e.ok and e.info["speed_scale"] == 0.0, e.info
    assert f"is {dtype}, the stage takes 8-bit (uint8) images" in e.info["reason"], e.info["reason"]
    assert "covered lens" not in e.info["reason"]
    assert stage.process(Frame(left, FRAME_NS, 2, right=right), Pose2()).ok


def _speed_band(min_distance=0.35, **kw):
    return ObstaclesConfig(zones=[ZoneConfig(name="stop", action="stop", distance=0.8, half_width=0.25,
                                             min_distance=min_distance)], **kw)


def test_a_stop_band_with_min_distance_scales_the_speed_with_the_obstacles_distance():
    m = ObstacleMonitor(_speed_band(persist_k=1, persist_n=1, release_s=0.0))
    t = iter(range(0, 100 * FRAME_NS, FRAME_NS))
    assert m.update(next(t), _pts(0.79)).scale == pytest.approx((0.79 - 0.35) / 0.45)
    assert m.update(next(t), _pts(0.575)).scale == pytest.approx(0.5)
    assert "0.57 m ahead: speed x0.50" in m.reason
    assert m.update(next(t), _pts(0.35)).scale == 0.0 and "within 0.35 m" in m.reason    # a held stop
    assert m.update(next(t), _pts(0.2)).scale == 0.0
    assert m.update(next(t), _pts(0.85)).scale == 1.0                                     # beyond the band
    # Fewer pixels than the zone needs do not set the distance: 5 noise pixels at 0.4 m, 20 at 0.6 m.
    assert m.update(next(t), np.vstack([_pts(0.4, n=5), _pts(0.6)])).scale == pytest.approx(0.25 / 0.45)
    # Without min_distance the same band stops the robot for any obstacle in it.
    fixed = ObstacleMonitor(ObstaclesConfig(persist_k=1, persist_n=1, release_s=0.0))
    assert fixed.update(0, _pts(0.79)).scale == 0.0


def test_a_stop_band_following_the_speed_keeps_the_k_of_n_and_the_release_debounce():
    m = ObstacleMonitor(_speed_band(persist_k=2, persist_n=3, release_s=0.5))
    t = 0
    scales = []
    for pts in [_pts(0.5), NONE, NONE, _pts(0.5), _pts(0.4), NONE]:
        scales.append(m.update(t, pts).scale)
        t += FRAME_NS
    assert scales[:4] == [1.0, 1.0, 1.0, 1.0]                     # one frame is noise
    assert scales[4] == pytest.approx(0.05 / 0.45)                # triggered: this frame's 0.4 m
    assert scales[5] == pytest.approx(0.05 / 0.45)                # 2 of 3 still: the last distance seen
    # Farther again: less caution only after release_s.
    out = []
    for _ in range(12):
        out.append((t, m.update(t, _pts(0.7)).scale))
        t += FRAME_NS
    rise = next(tt for tt, s in out if s > 0.2)
    assert rise - out[0][0] >= 0.5e9
    assert out[-1][1] == pytest.approx(0.35 / 0.45)


def _closest_approach(d0: float, min_distance, v_max=0.5, decel=1.0, latency=0.03, rate=15.0, T=6.0):
    """A robot at full speed towards an obstacle that appears d0 m ahead (1-D, 2 ms steps): the camera's
    frames at ``rate`` with ``latency``, the monitor's scale on the commanded speed, the speed changing at
    most ``decel``. Returns how near it came."""
    m = ObstacleMonitor(_speed_band(min_distance))
    dt, x, v, scale, next_frame, past = 0.002, 0.0, v_max, 1.0, 0.0, []
    for i in range(int(T / dt)):
        t = i * dt
        past.append(x)
        if t >= next_frame:
            seen = past[max(0, len(past) - 1 - round(latency / dt))]
            scale = m.update(round(t * 1e9), _pts(d0 - seen)).scale
            next_frame += 1.0 / rate
        target = v_max * scale
        v = max(target, v - decel * dt) if target < v else min(target, v + decel * dt)
        x += v * dt
    return d0 - x


def test_the_band_following_the_speed_never_brings_the_robot_nearer_than_the_fixed_band_or_min_distance():
    """The closed loop (docs/obstacles.md, 'A stop band that follows the speed'): from full speed, an obstacle
    appearing anywhere up to the band's full length ends no nearer than the fixed 0.8 m band stops the robot
    (a sudden obstacle: both brake at once) or than min_distance (one approached: the speed falls with the
    distance and the robot comes to rest there)."""
    for d0 in np.arange(0.40, 0.90, 0.04):
        fixed, following = _closest_approach(d0, None), _closest_approach(d0, 0.35)
        assert following >= min(fixed, 0.35) - 0.005, (d0, fixed, following)
        assert following <= 0.35 + 0.01 or following >= fixed - 0.005, (d0, fixed, following)
    # Approached from afar it comes to rest at min_distance, where the fixed band stops it 0.6 m off.
    assert _closest_approach(2.0, 0.35, T=20.0) == pytest.approx(0.35, abs=0.01)
    assert _closest_approach(2.0, None) == pytest.approx(0.61, abs=0.02)


@pytest.mark.parametrize("zone, says", [
    ({"name": "s", "action": "slow", "distance": 1.5, "half_width": 0.3, "min_distance": 0.3}, "a slow zone"),
    ({"name": "p", "polygon": [[-0.3, 0], [0.3, 0], [0, 1]], "min_distance": 0.3}, "a polygon"),
    ({"name": "b", "distance": 0.8, "half_width": 0.25, "min_distance": 0.8}, "shorter than the band's distance"),
])
def test_min_distance_is_refused_where_it_cannot_be_used(zone, says):
    with pytest.raises(ConfigError, match=rf"robot.yaml: obstacles\.zones\.0: .*min_distance.*{says}"):
        parse_config({"obstacles": {"zones": [zone]}}, "robot.yaml")


def test_a_band_standing_still_nearer_than_the_camera_sees_the_floor_is_refused_at_load():
    """A step down or a low obstacle nearer than where the camera's view of the floor begins is out of view,
    and the band would read its distance from what lies beyond: min_distance must not be nearer."""
    from vbnav.control.stages.obstacles import nearest_floor_ahead
    base = {"camera": {"width": 640, "height": 480, "fx": 400.0, "fy": 400.0, "cx": 319.5, "cy": 239.5,
                       "options": {"stereo_baseline": 0.075},
                       "mount": {"height": 0.25, "forward": 0.10, "pitch_deg": 0.0}},
            "obstacles": {"enabled": True, "zones": [{"name": "stop", "distance": 0.8, "half_width": 0.25,
                                                      "min_distance": 0.35}]}}
    cfg_level = parse_config({**base, "obstacles": {"enabled": False}}, "robot.yaml")
    # Level camera: the lowest row is (479 - 239.5) / 400 down, the floor 0.25 m below: 0.4175 m + 0.10 m.
    seen = nearest_floor_ahead(cfg_level.camera.to_model(), cfg_level.camera.mount.to_mount(), 0.25)
    assert 0.10 + 0.25 * 400 / 239.5 <= seen <= 0.10 + 0.25 * 400 / 239.5 + 0.005        # sampled every 5 mm
    with pytest.raises(ConfigError, match=r"robot.yaml: obstacles\.zones\.0: min_distance 0\.35 m is nearer than "
                                          r"the camera's view of the floor under the band, which begins 0\.520 m"):
        parse_config(base, "robot.yaml")
    # Pitched 20 deg down it sees the floor from 0.10 + 0.25 / tan(30.9 + 20 deg) = 0.30 m: accepted.
    pitched = {**base, "camera": {**base["camera"], "mount": {"height": 0.25, "forward": 0.10, "pitch_deg": 20.0}}}
    assert parse_config(pitched, "robot.yaml").obstacles.zones[0].min_distance == 0.35
    assert parse_config({**base, "obstacles": {**base["obstacles"], "enabled": False}}, "robot.yaml")   # kept unread
    # A band wider than the camera sees the floor: its edges are never seen, nothing to check against.
    wide = {**base, "obstacles": {**base["obstacles"], "zones": [{"name": "stop", "distance": 0.8, "half_width": 4.0,
                                                                  "min_distance": 0.7}]}}
    with pytest.raises(ConfigError, match=r"obstacles\.zones\.0: min_distance 0\.7 m: the camera does not see the floor "
                                          r"under the whole band"):
        parse_config(wide, "robot.yaml")


def test_turn_when_held_lets_a_turn_through_only_for_an_obstacle_seen_in_a_stop_zone():
    """``turn_ok`` (obstacles.turn_when_held) marks a held stop that an obstacle seen in a stop zone holds; a
    blind frame, and the release debounce after it, hold without it; a slow zone or no zone never carries it;
    without the setting it is never set."""
    cfg = ObstaclesConfig(persist_k=1, persist_n=1, release_s=0.2, turn_when_held=True)
    m = ObstacleMonitor(cfg)
    t = iter(range(0, 10**12, FRAME_NS))
    v = m.update(next(t), _pts(1.2))
    assert (v.scale, v.turn_ok) == (pytest.approx(0.4), False)       # slowed, not held
    v = m.update(next(t), _pts(0.5))
    assert (v.scale, v.turn_ok) == (0.0, True)                      # the box in the stop band
    v = m.blind("obstacles: blind: covered lens")
    assert (v.scale, v.turn_ok) == (0.0, False)
    v = m.update(next(t), NONE)
    assert (v.scale, v.turn_ok) == (0.0, False)                     # seen clear, but within release_s of blindness
    v = m.update(next(t), _pts(0.6))
    assert (v.scale, v.turn_ok) == (0.0, True)                      # an obstacle seen again holds it now
    out = [m.update(next(t), NONE) for _ in range(6)]
    assert out[-1].scale == 1.0 and not out[-1].turn_ok
    off = ObstacleMonitor(ObstaclesConfig(persist_k=1, persist_n=1))
    assert off.update(0, _pts(0.5)).turn_ok is False


def test_turn_when_held_needs_a_round_robot():
    base = {"obstacles": {"enabled": True, "turn_when_held": True},
            "camera": {"options": {"stereo_baseline": 0.075}}}
    with pytest.raises(ConfigError, match=r"obstacles\.turn_when_held .*set robot\.footprint_radius"):
        parse_config(base, "robot.yaml")
    cfg = parse_config({**base, "robot": {"footprint_radius": 0.2}}, "robot.yaml")
    assert cfg.obstacles.turn_when_held and cfg.robot.footprint_radius == 0.2


def test_the_stage_keeps_the_sighting_that_holds_the_robot_and_drops_it_when_nothing_does():
    """``ObstacleStage.sighting``: while an obstacle seen in the stop band holds the robot, the obstacle points
    there (robot frame, one per 5 cm cell, with the frame's odometry), for the planner's grid; none before the
    k-of-n holds, none while the lens is covered (blind: nothing seen), none once the hold ends."""
    from vbnav.control.config import load_config
    from vbnav.drivers.sim.camera import SimCamera
    from vbnav.drivers.sim.world import World
    cfg = load_config("sim_stereo")
    world = World.by_name(cfg.sim.world, cfg.sim.seed)
    world.add_box("obstacle", (-1.5, -1.55), (0.3, 0.3, 0.3))          # its face 0.8 m ahead: the stop band
    cam = SimCamera(world, cfg.camera.to_model(), cfg.camera.mount.to_mount(), pose_fn=lambda: Pose2(), clock=None,
                    rate_hz=15, noise_std=2.0, seed=4, stereo_baseline=0.075)
    stage = make_obstacle_stage(cfg)
    seen = []
    for i in range(40):
        cam.occluded = 10 <= i < 14
        if i == 20:
            world.remove("obstacle")
        odom = Pose2(0.0, 0.01 * i, 0.0)
        e = stage.process(cam.render_frame(cfg.sim.start(), int(i * 1e9 / 15), i), odom)
        seen.append((e.info["speed_scale"], stage.sighting))
    assert seen[0][1] is None                                           # k-of-n: one frame is not a hold yet
    held = [s for scale, s in seen[2:10] if scale == 0.0]
    assert held and all(s is not None for s in held)
    odom, pts = held[-1]
    assert odom == Pose2(0.0, 0.09, 0.0)                                # the frame's own odometry
    assert len(pts) >= 5 and np.all(np.abs(pts[:, 0]) <= 0.25 + 0.025)
    assert np.all((pts[:, 1] >= 0.75) & (pts[:, 1] <= 0.80)), pts[:, 1]   # the face, 0.8 m from the axle
    assert all(s is None for _, s in seen[10:14])                       # blind
    assert seen[-1] == (1.0, None)                                      # removed, released: nothing holds it


def test_stop_reach_is_where_an_obstacle_holds_the_robot_for_good():
    """The planner's Approach reach: a fixed band's distance, a speed-following band's min_distance (it crawls on
    to there), a polygon's farthest point; slow zones do not hold."""
    from vbnav.control.stages.obstacles import stop_reach
    assert stop_reach(ObstaclesConfig().zones) == 0.8
    band = ZoneConfig(name="stop", distance=0.8, half_width=0.25, min_distance=0.55)
    assert stop_reach([band, ZoneConfig(name="slow", action="slow", distance=1.5, half_width=0.35)]) == 0.55
    poly = ZoneConfig(name="p", polygon=[(-0.3, 0.0), (0.3, 0.0), (0.2, 0.9), (-0.2, 0.7)])
    assert stop_reach([poly]) == 0.9
