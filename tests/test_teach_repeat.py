"""Teach and repeat in closed loop on synthetic landmarks (no renderer): keyframes, heights, convergence."""
from __future__ import annotations

import math

import numpy as np
import pytest

from vbnav.control.runtime.interfaces import ControlContext
from vbnav.control.route import Route
from vbnav.control.controllers.repeat import RepeatController
from vbnav.control.stages.repeat import RepeatStage
from vbnav.control.stages.teach import TeachStage
from vbnav.control.config.vbc import VBCConfig
from vbnav.drivers.wheels import WheelState
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(height=0.25, forward=0.10)
DT = 0.01          # control period
FRAME_EVERY = 7    # ~14 Hz camera
NOISE_PX = 0.5


def room_landmarks(rng, n_per_wall=220):
    """Points on the walls of an 8 x 9 m room (x in [-4, 4], z in [-2.5, 6.5]), 0.05..2.2 m high."""
    pts = []
    for wall in range(4):
        u = rng.uniform(0, 1, n_per_wall)
        h = rng.uniform(0.05, 2.2, n_per_wall)
        if wall == 0:
            xz = np.column_stack((-4 + 8 * u, np.full(n_per_wall, 6.5)))
        elif wall == 1:
            xz = np.column_stack((-4 + 8 * u, np.full(n_per_wall, -2.5)))
        elif wall == 2:
            xz = np.column_stack((np.full(n_per_wall, 4.0), -2.5 + 9 * u))
        else:
            xz = np.column_stack((np.full(n_per_wall, -4.0), -2.5 + 9 * u))
        pts.append(np.column_stack((xz[:, 0], -h, xz[:, 1])))
    return np.vstack(pts)


def observe(pose: Pose2, pts: np.ndarray, rng):
    R, t = camera_pose(pose, MOUNT)
    pc = (pts - t) @ R
    px, front = CAM.project(pc)
    vis = front & (pc[:, 2] > 0.3) & CAM.in_image(px, margin=5)
    ids = np.flatnonzero(vis)
    return ids, px[vis] + rng.normal(0, NOISE_PX, (len(ids), 2))


def drive(pose, v, w, dt):
    return pose.compose(Pose2(0.0, v * dt, w * dt))


SCRIPT = [(0.25, 0.0, 6.0), (0.25, 0.5, math.pi / 2 / 0.5), (0.25, 0.0, 4.0)]   # straight, 90 deg right, straight


def teach(rng, pts, cfg):
    stage = TeachStage(CAM, MOUNT, cfg)
    true, odom = Pose2(), Pose2()
    truth_path = [true]
    step = 0
    for v, w, dur in SCRIPT:
        for _ in range(int(round(dur / DT))):
            if step % FRAME_EVERY == 0:
                ids, px = observe(true, pts, rng)
                stage.update(ids, px, odom, step)
            true = drive(true, v, w, DT)
            odom = drive(odom, v * 1.01, w * 1.005, DT)       # 1 % scale, 0.5 % turn-rate error
            truth_path.append(true)
            step += 1
    stage.finish()
    kfs = stage.pop_keyframes()
    return Route(None, "sim", "now", CAM, MOUNT, True, kfs), np.array([[p.x, p.z] for p in truth_path])


def lateral_error(path: np.ndarray, p: Pose2) -> float:
    a, b = path[:-1], path[1:]
    ab = b - a
    t = np.clip(((p.x - a[:, 0]) * ab[:, 0] + (p.z - a[:, 1]) * ab[:, 1]) / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
    q = a + t[:, None] * ab
    return float(np.min(np.hypot(q[:, 0] - p.x, q[:, 1] - p.z)))


def repeat(rng, pts, route, cfg, start: Pose2, occlude=None, max_time=40.0, silent=None):
    """``occlude`` (t0, t1): the camera sees nothing (failed fixes); ``silent`` (t0, t1): no new fix at all."""
    stage = RepeatStage(route, cfg)
    ctl = RepeatController(route, cfg, max_linear_speed=0.5, max_angular_speed=1.5)
    true, odom = start, Pose2()
    est = None
    trace = []
    for step in range(int(max_time / DT)):
        t = step * DT
        if step % FRAME_EVERY == 0 and not (silent and silent[0] <= t < silent[1]):
            ids, px = observe(true, pts, rng)
            if occlude and occlude[0] <= t < occlude[1]:
                ids, px = ids[:0], px[:0]
            est = stage.localise(ids, px, odom, step)
        ctx = ControlContext(step, DT, odom, WheelState(step, (0.0, 0.0), (0.0, 0.0)), {"vbc": est}, step)
        cmd = ctl.update(ctx)
        if ctl.finished:
            break
        true = drive(true, cmd.v, cmd.w, DT)
        odom = drive(odom, cmd.v * 0.99, cmd.w * 1.01, DT)        # a different odometry error than teaching
        trace.append((t, true, cmd, est.ok if est else False, ctl.status()))
    return ctl, stage, trace


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    pts = room_landmarks(rng)
    cfg = VBCConfig()
    route, truth = teach(rng, pts, cfg)
    return pts, cfg, route, truth


def test_teaching_emits_keyframes_with_heights(scene):
    pts, cfg, route, truth = scene
    kfs = route.keyframes
    length = sum(v * d for v, _, d in SCRIPT)
    assert len(kfs) >= length / cfg.keyframe_distance_m          # distance and rotation both trigger
    assert [k.index for k in kfs] == list(range(len(kfs)))
    assert np.all(np.diff([k.distance for k in kfs]) > 0)
    # heights: the landmark's true height below the camera vs 1/w, for well-observed ones
    errs = []
    for kf in kfs[:-1]:
        good = np.isfinite(kf.inv_height) & (kf.inv_height_var < (0.2 * kf.inv_height) ** 2)
        assert good.mean() > 0.7  # measured >= 0.863 on 2026-11-30: bar near twice the 14 % bad
        y_true = -pts[kf.track_ids[good], 1] - MOUNT.height
        y_true = -y_true        # camera y is down: height below the camera = cam_height - point height
        errs.append(np.abs(1 / kf.inv_height[good] - (MOUNT.height - (-pts[kf.track_ids[good], 1]))))
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.02


def test_repeat_from_offset_converges_and_finishes(scene):
    pts, cfg, route, truth = scene
    rng = np.random.default_rng(11)
    start = Pose2().compose(Pose2(0.3, 0.0, math.radians(10)))     # 0.3 m right, 10 deg right
    ctl, stage, trace = repeat(rng, pts, route, cfg, start)
    assert ctl.finished and stage.index == len(route.keyframes) - 1
    lat = np.array([lateral_error(truth, p) for _, p, *_ in trace])
    t = np.array([x[0] for x in trace])
    settled = t > 6.0                                      # after the start transient
    assert lat[0] > 0.25
    assert np.sqrt(np.mean(lat[settled] ** 2)) < 0.02, np.sqrt(np.mean(lat[settled] ** 2))
    assert lat[settled].max() < 0.05
    end = trace[-1][1]
    assert math.hypot(end.x - truth[-1, 0], end.z - truth[-1, 1]) < 0.1


def test_repeat_slows_stops_and_resumes_through_an_occlusion(scene):
    pts, cfg, route, truth = scene
    rng = np.random.default_rng(12)
    ctl, stage, trace = repeat(rng, pts, route, cfg, Pose2(), occlude=(3.0, 7.0))
    t = np.array([x[0] for x in trace])
    v = np.array([x[2].v for x in trace])
    blind = (t > 3.2) & (t < 7.0)
    before = (t > 2.0) & (t < 3.0)
    assert v[before].min() > 0.2
    assert 0 < v[blind].max() <= cfg.blind_speed_factor * cfg.cruise_speed + 1e-9     # slowed
    assert np.all(v[(t > 6.0) & (t < 7.0)] == 0)                                         # then stopped
    assert ctl.finished                                                                  # resumed, completed
    lat = np.array([lateral_error(truth, p) for _, p, *_ in trace])
    assert lat.max() < 0.05


def test_repeat_stops_after_blind_distance_when_fixes_stop_coming(scene):
    """No fix at all (the stage delivers nothing) is driving blind too: the last fix was strong, but after
    vbc.blind_distance_m on odometry alone the robot stops, and goes on when fixes return."""
    pts, cfg, route, truth = scene
    ctl, stage, trace = repeat(np.random.default_rng(13), pts, route, cfg, Pose2(), silent=(3.0, 7.0))
    t = np.array([x[0] for x in trace])
    v = np.array([x[2].v for x in trace])
    blind_m = np.array([x[4].get("blind_m", 0.0) for x in trace])
    assert v[(t > 3.0) & (t < 3.3)].min() > 0.2                 # a strong last fix: on at speed for a while
    stopped = (t > 3.0) & (t < 7.0) & (v == 0)
    assert stopped.any() and np.all(v[(t > 6.0) & (t < 7.0)] == 0)
    assert blind_m[stopped].min() >= cfg.blind_distance_m and blind_m[stopped].max() < cfg.blind_distance_m + 0.05
    assert ctl.finished


def test_fix_against_a_keyframe_without_heights_is_not_ok(scene):
    """A keyframe whose landmarks have no height (taught from a blurred frame: its tracks died before
    their heights were known; 181 of 189 in the audit) gives not-ok fixes, however many landmarks
    agree: only landmarks with a height fix the translation. The same view against the keyframe
    with its heights gives ok, accurate fixes."""
    from dataclasses import replace
    from vbnav.control.route import Route
    pts, cfg, route, truth = scene
    kf = route.keyframes[0]                                   # taught at the origin (odometry = truth)
    keep = cfg.min_known_landmarks - 4                        # 8 keep a height, as in the audit
    w = np.where(np.arange(len(kf)) < keep, kf.inv_height, np.nan)
    var = np.where(np.arange(len(kf)) < keep, kf.inv_height_var, np.inf)
    true = Pose2(0.05, -0.3, math.radians(3))                 # behind the keyframe: no switch, no finish
    for stripped, want_ok in ((kf, True), (replace(kf, inv_height=w, inv_height_var=var), False)):
        stage = RepeatStage(Route(None, "sim", "", CAM, MOUNT, True, [stripped]), cfg)
        for i in range(3):
            ids, px = observe(true, pts, np.random.default_rng(20 + i))
            est = stage.localise(ids, px, Pose2(), i)
            assert est.ok is want_ok, (want_ok, est.value.quality)
            assert est.value.n_agree >= cfg.slow_landmarks       # they all agree: that is not enough
            if want_ok:
                assert abs(est.value.pose.x - true.x) < 0.03 and abs(est.value.pose.z - true.z) < 0.03
            else:
                assert est.value.quality["n_known"] <= keep


def test_a_fix_that_odometry_cannot_explain_is_not_trusted(scene):
    """After a trusted fix, a fix farther from where odometry carries it than vbc.fix_gate_m (plus
    fix_gate_fraction of the distance driven since) is not ok and says why, however many landmarks
    agree; the keyframe does not change on it. The same view with odometry that moved alike is ok."""
    pts, cfg, route, truth = scene
    start = Pose2(0.05, -0.3, 0.0)
    for odom_moves, want_ok in ((False, False), (True, True)):
        stage = RepeatStage(route, cfg)
        for i in range(3):
            ids, px = observe(start, pts, np.random.default_rng(30 + i))
            assert stage.localise(ids, px, Pose2(), i).ok
        # The view 0.5 m to the side (a kidnapped robot, or a fix converged somewhere wrong).
        moved = Pose2(0.5, 0.0, 0.0)
        ids, px = observe(start.compose(moved), pts, np.random.default_rng(40))
        est = stage.localise(ids, px, moved if odom_moves else Pose2(), 3)
        assert est.ok is want_ok, est.info
        assert est.value.n_agree >= cfg.slow_landmarks               # the landmarks agree all the same
        if want_ok:
            assert abs(est.value.pose.x - 0.55) < 0.03
        else:
            assert "vbc.fix_gate_m" in est.info["reason"] and "gate 0.15 m" in est.info["reason"], est.info
            assert abs(est.value.pose.x - 0.05) < 0.03 and est.value.keyframe == 0   # odometry's pose
            assert stage.stats["gated"] >= 1          # (and the look-ahead to keyframe 1, alike)


def test_an_unconfirmed_replacement_fix_does_not_pass_keyframes(scene):
    """Before any fix has passed the gate, one outside it replaces the reference (a knocked first frame
    is outvoted), not ok. It must not carry the keyframe index along the route: a wrong one 1 m ahead
    switched past two keyframes the robot never reached."""
    pts, cfg, route, truth = scene
    stage = RepeatStage(route, cfg)
    start = Pose2(0.0, -0.3, 0.0)
    ids, px = observe(start, pts, np.random.default_rng(50))
    assert stage.localise(ids, px, Pose2(), 0).ok
    ids, px = observe(start.compose(Pose2(0.0, 1.0, 0.0)), pts, np.random.default_rng(51))   # odometry: still
    est = stage.localise(ids, px, Pose2(), 1)
    assert not est.ok and "replaces the first" in est.info["reason"], est.info
    assert stage.index == 0 and stage.stats["switches"] == 0


def test_the_same_knocked_frame_twice_does_not_confirm_itself(scene):
    """A frame delivered twice (a driver re-queuing its buffer while the robot still stands: the frozen-camera
    check lets it through) is no second view. Its fix agreed with itself and confirmed a first frame taken
    while the camera was knocked; every right fix after it was refused and the robot stopped for good. Now
    the right fixes replace it and are trusted."""
    pts, cfg, route, truth = scene
    stage = RepeatStage(route, cfg)
    start = Pose2(0.0, -0.3, 0.0)
    ids, px = observe(start.compose(Pose2(0.0, 0.0, 0.1)), pts, np.random.default_rng(60))   # knocked ~6 deg
    assert stage.localise(ids, px, Pose2(), 0).ok                       # the first fix: nothing to check it
    stage.localise(ids.copy(), px.copy(), Pose2(), 1)                   # the same frame again
    oks = []
    for i in range(2, 6):                                               # the camera is right again
        ids, px = observe(start, pts, np.random.default_rng(60 + i))
        est = stage.localise(ids, px, Pose2(), i)
        oks.append(est.ok)
    # measured 0.0005 rad and 4.1 mm on 2026-12-04 (the knocked frame was 0.1 rad off), bars about 2x
    assert oks[-1] and abs(est.value.pose.theta) < 0.001 and abs(est.value.pose.z + 0.3) < 0.01, (oks, est.info)

def test_repeat_skips_a_keyframe_whose_landmarks_cannot_be_found(scene):
    """A keyframe none of whose landmarks are found again (taught from a blurred frame: its image and
    descriptors match nothing sharp) gave no fix; the robot stopped after blind_distance_m (0.3 m),
    short of the keyframe (0.4 m on), and stayed there. The keyframe after it, where odometry expects
    it, now takes over."""
    from dataclasses import replace
    from vbnav.control.route import Route
    pts, cfg, route, truth = scene
    kfs = list(route.keyframes)
    kfs[2] = replace(kfs[2], track_ids=kfs[2].track_ids + 10 ** 6)    # ids that are never observed
    broken = Route(None, "sim", "now", CAM, MOUNT, True, kfs)
    ctl, stage, trace = repeat(np.random.default_rng(5), pts, broken, cfg, Pose2(), max_time=40.0)
    print(f"unfindable keyframe 2: finished {ctl.finished}, {stage.stats}")
    assert ctl.finished, trace[-1][4]
    assert stage.stats["skipped"] >= 1
    assert max(lateral_error(truth, p) for _, p, _, _, _ in trace) < 0.05


def test_vbc_config_section_is_validated():
    from vbnav.control.config import ConfigError, parse_config
    assert parse_config({"vbc": {"cruise_speed": 0.2}}).vbc.cruise_speed == 0.2
    with pytest.raises(ConfigError, match=r"robot.yaml: vbc.lookahed_m: unknown key"):
        parse_config({"vbc": {"lookahed_m": 0.3}}, "robot.yaml")   # typo: extra keys are errors
    with pytest.raises(ConfigError, match="vbc.min_landmarks"):
        parse_config({"vbc": {"min_landmarks": 2}})


def test_teach_sets_aside_one_frame_that_loses_most_tracks():
    """A frame that keeps a third of the last frame's tracks (a blurred frame) starts no keyframe; a
    keyframe due by distance on it comes one frame later. When the next frame has lost them too (all
    tracks replaced: the scene changed), the keyframe starts there."""
    def keyframes(glitch=None, change=None):
        rng = np.random.default_rng(5)
        pts = room_landmarks(rng)
        stage = TeachStage(CAM, MOUNT, VBCConfig())
        pose = Pose2()
        for i in range(60):                               # 1.5 m straight, a frame every 2.5 cm
            ids, px = observe(pose, pts, rng)
            if change is not None and i >= change:
                ids = ids + 100_000
            if i == glitch:
                ids, px = ids[::3], px[::3]
            stage.update(ids, px, pose, i)
            pose = pose.compose(Pose2(0.0, 0.025, 0.0))
        stage.finish()
        return [kf.stamp_ns for kf in stage.pop_keyframes()], stage.suspect_frames

    plain, none = keyframes()
    assert plain == [0, 16, 32, 49, 59] and none == 0            # by distance (0.4 m = 16 frames), and the end
    assert keyframes(glitch=20) == (plain, 1)                    # no keyframe on it, none after it
    assert keyframes(glitch=16) == ([0, 17, 33, 50, 59], 1)      # the distance trigger, one frame late
    assert keyframes(change=20) == ([0, 16, 21, 37, 54, 59], 1)  # the change is real: a keyframe at the next


def teach_straight(frames: int, keep=None):
    """A TeachStage (default VBCConfig) fed ``frames`` frames 2.5 cm apart straight ahead in the room, frame
    ``i`` stamped ``i``; ``keep(i, ids, px)`` may thin a frame's tracks. Returns (stage, next pose, rng, pts)."""
    rng = np.random.default_rng(5)
    pts = room_landmarks(rng)
    stage = TeachStage(CAM, MOUNT, VBCConfig())
    pose = Pose2()
    for i in range(frames):
        ids, px = observe(pose, pts, rng)
        if keep is not None:
            ids, px = keep(i, ids, px)
        stage.update(ids, px, pose, i)
        pose = pose.compose(Pose2(0.0, 0.025, 0.0))
    return stage, pose, rng, pts


def test_keyframe_taken_at_the_last_frame_has_heights():
    """A keyframe triggered by the very last frame is emitted with its tracks' heights (else a repeat
    can never localise at the route's end)."""
    cfg = VBCConfig()
    stage, pose, rng, pts = teach_straight(40)            # 1 m straight, a frame every 2.5 cm
    pose = pose.compose(Pose2(0.0, cfg.keyframe_distance_m, 0.0))   # the last frame is due a keyframe
    ids, px = observe(pose, pts, rng)
    before = stage.n_keyframes
    stage.update(ids, px, pose, 41)
    assert stage.n_keyframes == before + 1                 # the previous one emitted, the last one pending
    stage.finish()
    kfs = stage.pop_keyframes()
    assert stage.n_keyframes == before + 2                 # no extra keyframe: the last frame already was one
    assert kfs[-1].stamp_ns == 41
    last = kfs[-1]
    assert np.isfinite(last.inv_height).mean() > 0.8


def test_route_does_not_end_on_a_last_frame_below_the_keyframe_minimum():
    """finish() takes a keyframe at the last frame only when it keeps ``min_keyframe_landmarks`` tracks,
    as every other keyframe: a last frame of 5 tracks (the lens covered as the teach stopped) ends the
    route at the keyframe before, and the stage says so (a repeat cannot localise on 5 landmarks)."""
    cfg = VBCConfig()
    # 0.75 m straight, a frame every 2.5 cm; the last two frames keep 5 tracks (the first is set aside)
    stage, _, _, _ = teach_straight(32, keep=lambda i, ids, px: (ids[:5], px[:5]) if i >= 30 else (ids, px))
    stage.finish()
    kfs = stage.pop_keyframes()
    assert [kf.stamp_ns for kf in kfs] == [0, 16]          # by distance; none on the 5 tracks of frame 31
    assert all(len(kf.track_ids) >= cfg.min_keyframe_landmarks for kf in kfs)
    assert "5 tracks" in stage.end_note and f"min_keyframe_landmarks {cfg.min_keyframe_landmarks}" in stage.end_note


@pytest.mark.parametrize("damage", ["no heights", "no landmarks"])
def test_repeat_starts_when_the_first_keyframe_gives_no_fix(scene, damage):
    """A route whose first keyframe gives no fix (taught from a blurred frame: no landmark has a height; or
    damaged: none at all) never started: keyframes are skipped only from a trusted fix on, so the robot
    waited for a first match, its status asking to start at the route's beginning, where it stood. Before
    the first fix, the keyframe after the first is now tried where it was taught."""
    from dataclasses import replace
    pts, cfg, route, truth = scene
    kfs = list(route.keyframes)
    n = len(kfs[0])
    if damage == "no heights":
        kfs[0] = replace(kfs[0], inv_height=np.full(n, np.nan), inv_height_var=np.full(n, np.inf))
    else:
        z = np.zeros(0)
        kfs[0] = replace(kfs[0], pixels=np.zeros((0, 2), np.float32), alpha=z, beta=z, inv_height=z,
                         inv_height_var=z, descriptors=np.zeros((0, 32), np.uint8), track_ids=np.zeros(0, np.int64))
    broken = Route(None, "sim", "now", CAM, MOUNT, True, kfs)
    ctl, stage, trace = repeat(np.random.default_rng(5), pts, broken, cfg, Pose2(), max_time=40.0)
    assert ctl.finished and stage.index == len(kfs) - 1, trace[-1][4]
    assert stage.stats["skipped"] == 1
    assert max(lateral_error(truth, p) for _, p, _, _, _ in trace) < 0.05


def test_the_keyframe_at_the_last_frame_has_that_frames_distance():
    """A route's last keyframe is taken at the last frame kept (a last frame that lost most tracks, a blurred
    one as the teach stopped, is set aside), but it was given the distance of the frame set aside: the route
    said it was 2.5 cm longer than where its last keyframe stands. Straight ahead, distance = odometry z."""
    stage, _, _, _ = teach_straight(40, keep=lambda i, ids, px: (ids[::3], px[::3]) if i == 39 else (ids, px))
    stage.finish()
    kfs = stage.pop_keyframes()
    assert stage.suspect_frames == 1 and kfs[-1].stamp_ns == 38
    for kf in kfs:
        assert math.isclose(kf.distance, kf.odom.z, abs_tol=1e-9), (kf.stamp_ns, kf.distance, kf.odom.z)
