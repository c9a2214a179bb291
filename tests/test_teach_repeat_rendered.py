"""Teach and repeat on rendered frames of the simulated room (drivers/sim_camera.py), kinematic base.

The base is an ideal unicycle integrated at 100 Hz with odometry errors (1 % scale, 1 % turn rate);
the camera renders at 15 Hz from the true pose with pixel noise. Teaching drives a straight line, a
90 degree left turn and a straight line; repeating starts 0.3 m to the right and 10 degrees off.
"""
from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from vbnav.control.runtime.interfaces import ControlContext
from vbnav.control.route import Route
from vbnav.control.controllers.repeat import RepeatController
from vbnav.control.stages.repeat import RepeatStage
from vbnav.control.stages.teach import TeachStage
from vbnav.control.config.vbc import VBCConfig
from vbnav.drivers.camera import Frame
from vbnav.drivers.sim.camera import SimCamera
from vbnav.drivers.sim.world import World
from vbnav.drivers.wheels import WheelState
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(height=0.25, forward=0.10)
DT = 0.01
FRAME_EVERY = 7                       # ~14 Hz
START = Pose2(-3.5, -2.0, math.pi / 2)   # heading +x along the room's south side
SCRIPT = [(0.25, 0.0, 10.0), (0.25, -0.5, math.pi / 2 / 0.5), (0.25, 0.0, 6.0)]   # 2.5 m, left 90 deg, 1.5 m


def drive(p: Pose2, v: float, w: float, dt: float) -> Pose2:
    return p.compose(Pose2(0.0, v * dt, w * dt))


def lateral_error(path: np.ndarray, p: Pose2) -> float:
    a, b = path[:-1], path[1:]
    ab = b - a
    t = np.clip(((p.x - a[:, 0]) * ab[:, 0] + (p.z - a[:, 1]) * ab[:, 1]) / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
    q = a + t[:, None] * ab
    return float(np.min(np.hypot(q[:, 0] - p.x, q[:, 1] - p.z)))


@pytest.fixture(scope="module")
def world():
    return World.room(seed=1)


def camera(world, gain=1.0, seed=5, mount=MOUNT):
    return SimCamera(world, CAM, mount, pose_fn=lambda: Pose2(), clock=None, rate_hz=15, noise_std=2.0, seed=seed,
                     gain=gain)


@pytest.fixture(scope="module")
def taught(world):
    return teach_route(world)


def teach_route(world, blur_frame=None, blur_sigma=8.0, stage_out=None, script=SCRIPT):
    """Teach ``script`` from START on rendered frames; (route, true path (N, 2)).

    blur_frame: the index (or indices) of frames Gaussian-blurred by blur_sigma px (motion blur, a knock)."""
    blurred = {blur_frame} if isinstance(blur_frame, int) else set(blur_frame or ())
    cam = camera(world)
    stage = TeachStage(CAM, MOUNT, VBCConfig())
    true, odom = START, Pose2()
    path = [(true.x, true.z)]
    step = n = 0
    for v, w, dur in script:
        for _ in range(int(round(dur / DT))):
            if step % FRAME_EVERY == 0:
                frame = cam.render_frame(true, step, step)
                if n in blurred:
                    frame = Frame(cv2.GaussianBlur(frame.image, (0, 0), blur_sigma), frame.stamp_ns, frame.seq,
                                  meta=frame.meta)
                stage.process(frame, odom)
                n += 1
            true = drive(true, v, w, DT)
            odom = drive(odom, v * 1.01, w * 0.99, DT)
            path.append((true.x, true.z))
            step += 1
    stage.finish()
    if stage_out is not None:
        stage_out.append(stage)
    return Route(None, "sim", "", CAM, MOUNT, True, stage.pop_keyframes()), np.array(path)


def repeat(world, route, start: Pose2, occlude=None, gain=1.0, max_time=40.0, seed=5, image_fn=None,
           mount=MOUNT, estimates=None, remount=None):
    """image_fn(n, image) -> image: an image event on the n-th frame (a knock, glare, ...). mount: where
    the camera really sits now (the route keeps the taught one). estimates: a list the stage's go to.
    remount: (n, mount): the camera moves to ``mount`` at the n-th frame (a knock while repeating)."""
    cam = camera(world, gain, seed, mount)
    cfg = VBCConfig()
    stage = RepeatStage(route, cfg)
    ctl = RepeatController(route, cfg)
    true, odom, est = start, Pose2(), None
    trace = []
    for step in range(int(max_time / DT)):
        t = step * DT
        if step % FRAME_EVERY == 0:
            cam.occluded = bool(occlude and occlude[0] <= t < occlude[1])
            if remount is not None and step // FRAME_EVERY == remount[0]:
                cam.mount = remount[1]
            frame = cam.render_frame(true, step, step)
            if image_fn is not None:
                frame = Frame(image_fn(step // FRAME_EVERY, frame.image), frame.stamp_ns, frame.seq, meta=frame.meta)
            est = stage.process(frame, odom)
            if estimates is not None:
                estimates.append(est)
        cmd = ctl.update(ControlContext(step, DT, odom, WheelState(step, (0.0, 0.0), (0.0, 0.0)), {"vbc": est}, step))
        if ctl.finished:
            break
        true = drive(true, cmd.v, cmd.w, DT)
        odom = drive(odom, cmd.v * 0.99, cmd.w * 1.01, DT)
        trace.append((t, true, cmd))
    return ctl, stage, trace


def test_rendered_teach_makes_a_usable_route(taught):
    route, path = taught
    kfs = route.keyframes
    assert len(kfs) >= 10
    for kf in kfs:
        assert len(kf) >= 80                                     # measured >= 158 on 2026-11-30, bar 1/2
        assert np.mean(np.isfinite(kf.inv_height)) > 0.95        # measured >= 0.979 on 2026-11-30
        assert kf.descriptors.any()                       # real ORB descriptors from the rendered image


def test_rendered_repeat_from_offset(world, taught):
    route, path = taught
    start = START.compose(Pose2(0.3, 0.0, math.radians(10)))
    ctl, stage, trace = repeat(world, route, start)
    assert ctl.finished
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    t = np.array([x[0] for x in trace])
    settled = t > 8.0
    rms = float(np.sqrt(np.mean(lat[settled] ** 2)))
    print(f"rendered repeat: settled lateral RMS {100 * rms:.2f} cm, max {100 * lat[settled].max():.2f} cm, "
          f"{len(route.keyframes)} keyframes, re-acquired {stage.stats['reacquired']}")
    assert rms < 0.012 and lat[settled].max() < 0.03  # measured 0.62 / 1.43 cm on 2026-11-30, bars 2x
    # smooth through all keyframe switches: no jumps in the commands after the start
    w = np.array([c.w for _, _, c in trace])
    v = np.array([c.v for _, _, c in trace])
    after = t[1:] > 0.5
    assert stage.stats["switches"] == len(route.keyframes) - 1
    # measured 0.022 / 0.0038 on 2026-11-30
    assert np.abs(np.diff(w))[after].max() < 0.045 and np.abs(np.diff(v))[after].max() < 0.008
    end = trace[-1][1]
    assert math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]) < 0.08  # measured 3.8 cm on 2026-11-30, bar 2x


def test_one_blurred_frame_while_teaching_is_set_aside(world):
    """A heavily blurred frame mid-route (sigma 8 px; KLT loses the tracks on it) started a keyframe
    whose tracks died at the next sharp frame, 181 of 189 landmarks without a height, and the repeat
    then had ok fixes 2.8 m off, ended 2.6 m off the path and never finished (audit). The frame is set
    aside: tracking goes on from the frame before, the route is as without it, and the repeat finishes
    on the path."""
    script = [(0.25, 0.0, 5.0), (0.25, -0.5, 1.5), (0.25, 0.0, 1.0)]    # 1.25 m, left 43 deg, 0.25 m
    clean, _ = teach_route(world, script=script)
    stages = []
    route, path = teach_route(world, blur_frame=50, stage_out=stages, script=script)
    for kf in route.keyframes:
        assert np.mean(np.isfinite(kf.inv_height)) > 0.95, kf.index
    assert len(route.keyframes) == len(clean.keyframes) and stages[0].suspect_frames == 1
    ctl, stage, trace = repeat(world, route, START.compose(Pose2(0.05, 0.0, 0.0)), max_time=20.0,
                               seed=9)                   # the audit's pixel noise
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    end = trace[-1][1]
    print(f"blurred frame: finished {ctl.finished}, max lateral {100 * lat.max():.2f} cm, end "
          f"{100 * math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]):.2f} cm")
    assert ctl.finished
    assert lat.max() < 0.08     # measured 5.0 cm (the 5 cm start offset), as unblurred; 261 cm before
    assert math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]) < 0.08    # measured 3.2 cm; 261 cm before


def test_four_blurred_frames_while_teaching(world):
    """Four blurred frames in a row (frames 20-23, 1.4 s in) are more than teach sets aside: a keyframe
    is taught on one, and repeat finds few of its landmarks in sharp images (7-15 of 189). Its fix then
    converged 21 m away with 15 'inliers' (the robust scale had grown to 50 sigma), the repeat switched
    through four keyframes on it and stood 1.5 m from the end for good (audit). Now the keyframe after
    it takes over when it gives no fix and the next one does where odometry expects it (here before the
    wild fix comes); such a fix would also be refused by the gate on the odometry prediction alone
    (vbc.fix_gate_m, test_teach_repeat.py), which left the robot stopped before the keyframe. The
    repeat finishes on the path."""
    script = [(0.25, 0.0, 5.0), (0.25, -0.5, 1.5), (0.25, 0.0, 1.0)]    # 1.25 m, left 43 deg, 0.25 m
    route, path = teach_route(world, blur_frame=(20, 21, 22, 23), script=script)
    ctl, stage, trace = repeat(world, route, START.compose(Pose2(0.05, 0.0, 0.0)), max_time=20.0, seed=9)
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    end = trace[-1][1]
    print(f"four blurred frames: finished {ctl.finished}, max lateral {100 * lat.max():.2f} cm, end "
          f"{100 * math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]):.2f} cm, {stage.stats}")
    assert ctl.finished
    assert stage.stats["skipped"] >= 1
    assert lat.max() < 0.08     # measured 5.0 cm (the 5 cm start offset); 151 cm from the end before
    assert math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]) < 0.08    # measured 3.3 cm


def test_a_knock_on_the_first_repeat_frame_is_outvoted(world, taught):
    """The camera knocked on the first frame of a repeat (the image shifted 40 px, ~5.7 deg of yaw, for
    that frame only): the first fix, which no prediction gates, was 5.7 deg off; every right fix after
    it fell outside the gate around it, and the repeat stood 3.4 m from the end for good (audit, 856
    fixes refused). Until a fix has passed the gate, one that fails it replaces the reference; the
    next one confirms it, and the repeat finishes as without the knock."""
    route, path = taught
    shift = np.float32([[1, 0, 40], [0, 1, 0]])

    def knock(n, image):
        return cv2.warpAffine(image, shift, image.shape[::-1], borderMode=cv2.BORDER_REPLICATE) if n == 0 else image

    ctl, stage, trace = repeat(world, route, START.compose(Pose2(0.05, 0.0, 0.0)), max_time=30.0, seed=9,
                               image_fn=knock)
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    t = np.array([x[0] for x in trace])
    end = trace[-1][1]
    print(f"knocked first frame: finished {ctl.finished}, settled max lateral {100 * lat[t > 8].max():.2f} cm, "
          f"end {100 * math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]):.2f} cm, {stage.stats}")
    assert ctl.finished
    assert lat[t > 8].max() < 0.03      # measured 1.37 cm (1.39 without the knock); 3.9 cm before, stopped
    assert math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]) < 0.08    # measured 3.8 cm; 338 cm before


@pytest.mark.parametrize("pitch_deg, roll_deg", [(0.0, 2.0), (1.0, 0.0), (-2.0, 2.0)])
def test_a_camera_tilted_on_its_mount_since_teaching(world, taught, pitch_deg, roll_deg):
    """The camera pitched or rolled on its mount after the route was taught (a knock, a load, tyre
    pressure). With planar fixes a 1 deg roll put the robot 10-13 cm off the route, and 2 deg of roll or
    1 deg of pitch stopped the repeat 1.7-2.1 m short (fixes refused by the gate). The repeat now solves
    the tilt with each fix and drives as with the taught mounting (max lateral 1.4 cm, as untilted)."""
    route, path = taught
    tilted = replace(MOUNT, pitch=math.radians(pitch_deg), roll=math.radians(roll_deg))
    ests = []
    ctl, stage, trace = repeat(world, route, START.compose(Pose2(0.05, 0.0, 0.0)), max_time=30.0, mount=tilted,
                               estimates=ests)
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    t = np.array([x[0] for x in trace])
    end = trace[-1][1]
    tilt = np.array([e.info["camera_tilt_deg"] for e in ests if e.ok])
    print(f"camera pitched {pitch_deg} / rolled {roll_deg} deg: finished {ctl.finished}, settled max lateral "
          f"{100 * lat[t > 8].max():.2f} cm, end {100 * math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]):.2f} "
          f"cm, tilt estimate (last) {tilt[-1]}, {stage.stats}")
    assert ctl.finished
    assert lat[t > 8].max() < 0.03          # measured 1.4 cm (1.4 untilted); 10-13 cm or stopped before
    assert math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]) < 0.08         # measured 3.6-3.8 cm
    # the tilt is found: pitch and roll over the second half of the route within 0.048-0.053 deg of the
    # truth (measured on 2026-12-04 over the three cases), bar 2x
    half = tilt[len(tilt) // 2:]
    assert np.max(np.abs(half - [pitch_deg, roll_deg])) < 0.11, half


def test_a_camera_knocked_while_repeating_is_followed(world, taught):
    """The camera pitched 2 deg down at frame 60 (4.3 s, mid-route): before, the gate refused the fixes
    from then on (693 of them) and the robot stood 2.3 m from the end. The smoothed tilt passes its
    threshold within a few frames, is applied, and the repeat finishes as without the knock."""
    route, path = taught
    ests = []
    ctl, stage, trace = repeat(world, route, START.compose(Pose2(0.05, 0.0, 0.0)), max_time=30.0, estimates=ests,
                               remount=(60, replace(MOUNT, pitch=math.radians(2.0))))
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    t = np.array([x[0] for x in trace])
    end = trace[-1][1]
    print(f"knocked at frame 60: finished {ctl.finished}, settled max lateral {100 * lat[t > 8].max():.2f} cm, "
          f"end {100 * math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]):.2f} cm, {stage.stats}")
    assert ctl.finished
    assert lat[t > 8].max() < 0.03                # measured 1.4 cm
    assert math.hypot(end.x - path[-1, 0], end.z - path[-1, 1]) < 0.08   # measured 3.7 cm
    assert not any(e.info["camera_tilt_deg"][0] for e in ests[:60])     # nothing applied before the knock
    assert abs(ests[-1].info["camera_tilt_deg"][0] - 2.0) < 0.012       # measured 2.005 on 2026-12-04, bar ~2x


def test_a_camera_tilted_beyond_max_tilt_deg_stops_the_repeat_naming_the_mount(world, taught):
    """6 deg of roll is beyond vbc.max_tilt_deg (5): no fix is trusted, and each says the camera mount
    has moved; the robot stops within the blind distance instead of patrolling on a loose camera."""
    route, path = taught
    ests = []
    ctl, stage, trace = repeat(world, route, START.compose(Pose2(0.05, 0.0, 0.0)), max_time=5.0,
                               mount=replace(MOUNT, roll=math.radians(6.0)), estimates=ests)
    assert not any(e.ok for e in ests)
    reasons = [e.info.get("reason", "") for e in ests]
    assert sum("check the camera mount" in r and "+6.0 deg (roll)" in r for r in reasons) > 0.9 * len(ests), reasons[:3]
    travelled = math.hypot(trace[-1][1].x - trace[0][1].x, trace[-1][1].z - trace[0][1].z)
    assert travelled < VBCConfig().blind_distance_m + 0.05, travelled


@pytest.mark.parametrize("gain", [0.6, 1.4])
def test_rendered_repeat_through_occlusion_lighting_and_moved_boxes(taught, gain):
    """A 2 s covered lens mid-route, brightness -40 % / +40 %, two boxes of the taught scene moved."""
    route, path = taught
    changed = World.room(seed=1)
    changed.move_box("box_a", (-1.0, 0.8))
    changed.move_box("box_b", (1.8, 0.2))
    ctl, stage, trace = repeat(changed, route, START, occlude=(4.0, 6.0), gain=gain)
    assert ctl.finished
    lat = np.array([lateral_error(path, p) for _, p, _ in trace])
    v = np.array([c.v for _, _, c in trace])
    t = np.array([x[0] for x in trace])
    print(f"gain {gain}, boxes moved, occluded 2 s: max lateral {100 * lat.max():.2f} cm, {stage.stats}")
    assert np.all(v[(t > 5.5) & (t < 6.0)] < VBCConfig().cruise_speed)     # slowed or stopped while blind
    assert lat.max() < 0.03  # measured 1.39 cm on 2026-11-30, bar 2x


def test_route_round_trip_through_disk_localises(world, taught, tmp_path):
    """Keyframes written by RouteWriter and read by load_route give the same fixes as in memory."""
    from vbnav.control.route import RouteWriter, load_route
    route, _ = taught
    with RouteWriter(tmp_path / "route", "sim", CAM, MOUNT) as w:
        for kf in route.keyframes:
            w.append(kf)
    loaded = load_route(tmp_path / "route")
    assert len(loaded) == len(route) and loaded.camera == CAM and loaded.mount == MOUNT
    cam = camera(world)
    fixes = []
    for r in (route, loaded):
        stage = RepeatStage(r, VBCConfig())
        pose = START.compose(Pose2(0.1, 0.0, 0.05))
        for i in range(4):
            est = stage.process(cam.render_frame(pose, i, i), Pose2(0.0, 0.02 * i, 0.0))
            pose = drive(pose, 0.2, 0.0, 0.1)
        assert est.ok and est.value.n_agree > 85  # measured 168 on 2026-11-30, bar 1/2
        fixes.append(est.value.pose.as_array())
    np.testing.assert_allclose(fixes[0], fixes[1], atol=1e-9)


# A frame of another format (a USB camera renegotiating after a reconnect, a 16-bit or float stream) raised
# in the KLT (cv2.error), which ends the run; it is now a frame the stage skips: not ok, saying why.
BAD_FORMATS = {
    "half-size": (lambda im: im[::2, ::2].copy(), "is 320x240, the camera calibration is for 640x480"),
    "uint16": (lambda im: im.astype(np.uint16) * 256, "uint16"),
    "float": (lambda im: im.astype(np.float32) / 255.0, "float32"),
}


def _frames(world, poses):
    cam = camera(world)
    return [cam.render_frame(p, i, i) for i, p in enumerate(poses)]


def _reformat(frame, fn):
    from vbnav.drivers.camera import Frame
    return Frame(fn(frame.image), frame.stamp_ns, frame.seq, meta=frame.meta)


@pytest.mark.parametrize("kind", list(BAD_FORMATS))
def test_teach_skips_a_frame_of_another_format_and_tracks_on(world, kind):
    fn, says = BAD_FORMATS[kind]
    poses = [drive(START, 0.25, 0.0, i / 15) for i in range(10)]
    frames = _frames(world, poses)
    odom = [START.between(p) for p in poses]
    stage = TeachStage(CAM, MOUNT, VBCConfig())
    results = []
    for i, (f, o) in enumerate(zip(frames, odom)):
        if i == 5:
            before = stage.tracker.tracks.ids.copy()
            f = _reformat(f, fn)
        results.append(stage.process(f, o))
    bad = results[5]
    assert not bad.ok and bad.kind == "teach" and bad.value is None
    assert bad.info["reason"].startswith("teach: ") and says in bad.info["reason"]
    assert all(r.ok for i, r in enumerate(results) if i != 5)
    # The tracks go on from the last good frame: most of them are still the ones of frame 4.
    assert np.isin(before, stage.tracker.tracks.ids).mean() > 0.8
    stage.finish()
    assert len(stage.pop_keyframes()) >= 2


@pytest.mark.parametrize("kind", list(BAD_FORMATS))
def test_repeat_skips_a_frame_of_another_format_and_localises_on(world, taught, kind):
    fn, says = BAD_FORMATS[kind]
    route, _ = taught
    cam = camera(world)
    runs = []
    for with_bad in (False, True):
        stage = RepeatStage(route, VBCConfig())
        pose = START.compose(Pose2(0.1, 0.0, 0.05))
        out = []
        for i in range(8):
            f = cam.render_frame(pose, i, i)
            if with_bad and i == 4:
                f = _reformat(f, fn)
            out.append(stage.process(f, Pose2(0.0, 0.02 * i, 0.0)))
            pose = drive(pose, 0.2, 0.0, 0.1)
        runs.append(out)
    good, skipped = runs
    bad = skipped[4]
    assert not bad.ok and bad.kind == "vbc" and bad.value.n_agree == 0
    assert bad.info["reason"].startswith("repeat: ") and says in bad.info["reason"]
    assert all(r.ok and r.value.n_agree > 85 for i, r in enumerate(skipped) if i != 4)
    # Recovered: the last fix is where the run without the bad frame puts it.
    np.testing.assert_allclose(skipped[-1].value.pose.as_array(), good[-1].value.pose.as_array(), atol=0.01)


def test_colour_frames_are_taken_as_before(world):
    """BGR (the sim and V4L2 drivers with grey: false) and BGRA frames are made grey as before: the same tracks."""
    import cv2
    from vbnav.control.stages.frame_input import stage_image

    poses = [drive(START, 0.25, 0.0, i / 15) for i in range(4)]
    frames = _frames(world, poses)
    tracks = []
    for code in (None, cv2.COLOR_GRAY2BGR, cv2.COLOR_GRAY2BGRA):
        stage = TeachStage(CAM, MOUNT, VBCConfig())
        for i, f in enumerate(frames):
            f = f if code is None else _reformat(f, lambda im: cv2.cvtColor(im, code))
            assert stage.process(f, START.between(poses[i])).ok
        tracks.append(stage.tracker.tracks.pts.copy())
    np.testing.assert_array_equal(tracks[0], tracks[1])
    np.testing.assert_array_equal(tracks[0], tracks[2])
    grey = frames[0].image
    assert stage_image(grey, CAM)[0] is grey                     # a valid grey frame is passed through
    np.testing.assert_array_equal(stage_image(grey[:, :, None], CAM)[0], grey)
    assert "shape (480, 640, 2)" in stage_image(np.zeros((480, 640, 2), np.uint8), CAM)[1]
    assert stage_image(None, CAM, "right image") == (None, "the frame has no right image")


def test_teach_skips_a_frame_with_non_finite_odometry(world):
    """A NaN odometry reading was taken: the distance driven stayed NaN (no keyframe by distance again) and a
    keyframe started on that frame went into the route with a NaN pose. The frame is not ok now, saying why."""
    poses = [drive(START, 0.25, 0.0, i / 15) for i in range(40)]
    frames = _frames(world, poses)
    stage = TeachStage(CAM, MOUNT, VBCConfig())
    results = []
    for i, (f, p) in enumerate(zip(frames, poses)):
        o = START.between(p)
        results.append(stage.process(f, Pose2(o.x, float("nan"), o.theta) if i in (0, 20) else o))
    for i in (0, 20):
        assert not results[i].ok and "odometry is not finite" in results[i].info["reason"], results[i].info
    assert all(r.ok for i, r in enumerate(results) if i not in (0, 20))
    assert math.isfinite(stage._distance)
    stage.finish()
    kfs = stage.pop_keyframes()
    assert len(kfs) >= 3 and all(np.isfinite(k.odom.as_array()).all() for k in kfs)


def test_repeat_skips_a_frame_with_non_finite_odometry(world, taught):
    """A NaN odometry reading reached the fix (its odometry, the gate's prediction): the frame is not ok now,
    saying why, with a finite pose, and the fixes after it are those of a run without it."""
    route, _ = taught
    cam = camera(world)
    runs = []
    for with_bad in (False, True):
        stage = RepeatStage(route, VBCConfig())
        pose = START.compose(Pose2(0.1, 0.0, 0.05))
        out = []
        for i in range(8):
            odom = Pose2(0.0, 0.02 * i, 0.0)
            if with_bad and i == 4:
                odom = Pose2(0.0, float("nan"), 0.0)
            out.append(stage.process(cam.render_frame(pose, i, i), odom))
            pose = drive(pose, 0.2, 0.0, 0.1)
        runs.append(out)
    good, skipped = runs
    bad = skipped[4]
    assert not bad.ok and "odometry is not finite" in bad.info["reason"], bad.info
    assert np.isfinite(bad.value.pose.as_array()).all()
    assert all(r.ok and r.value.n_agree > 85 for i, r in enumerate(skipped) if i != 4)
    np.testing.assert_allclose(skipped[-1].value.pose.as_array(), good[-1].value.pose.as_array(), atol=0.01)
