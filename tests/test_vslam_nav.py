"""VslamStage, the mount conversion and the GotoController (control/vslam_nav.py)."""
import math
import re

import numpy as np
import pytest

from line_scenes import loop_poses

from vbnav.control.runtime.interfaces import ControlContext, Estimate, Twist
from vbnav.control.config.vslam import GotoConfig, VslamNavConfig
from vbnav.control.controllers.goto import GotoController, polar_coordinates
from vbnav.control.stages.vslam import VslamFix, VslamStage, camera_to_robot, robot_to_camera_matrix
from vbnav.drivers.camera import Frame
from vbnav.drivers.sim.camera import SimCamera
from vbnav.drivers.sim.world import World
from vbnav.drivers.wheels import WheelState
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, arc_step, wrap_angle


# ------------------------------------------------------------------------------------ mount
@pytest.mark.parametrize("mount", [CameraMount(), CameraMount(0.4, 0.12, -0.05, math.radians(15), math.radians(-20))])
def test_camera_to_robot_inverts_camera_pose(mount, rng):
    for _ in range(20):
        p = Pose2(*rng.uniform(-5, 5, 2), rng.uniform(-math.pi, math.pi))
        back, dh, tilt = camera_to_robot(robot_to_camera_matrix(p, mount), mount)
        assert back.x == pytest.approx(p.x, abs=1e-12) and back.z == pytest.approx(p.z, abs=1e-12)
        assert wrap_angle(back.theta - p.theta) == pytest.approx(0.0, abs=1e-12)
        assert dh == pytest.approx(0.0, abs=1e-12) and tilt == pytest.approx(0.0, abs=1e-7)


def test_camera_to_robot_reports_a_camera_off_the_floor():
    mount = CameraMount(0.25, 0.1)
    M = robot_to_camera_matrix(Pose2(1.0, 2.0, 0.3), mount)
    M[1, 3] -= 0.05                                    # 5 cm higher (y points down)
    _, dh, _ = camera_to_robot(M, mount)
    assert dh == pytest.approx(-0.05)


# ------------------------------------------------------------------------------------ polar law
def test_polar_coordinates_signs_follow_the_package_conventions():
    rho, alpha, beta = polar_coordinates(Pose2(), Pose2(0.0, 2.0, 0.0))
    assert (rho, alpha, beta) == pytest.approx((2.0, 0.0, 0.0))
    _, alpha, _ = polar_coordinates(Pose2(), Pose2(1.0, 1.0, 0.0))   # ahead and to the right
    assert alpha == pytest.approx(math.pi / 4)                          # positive like theta (turn right)
    pose, goal = Pose2(0.3, -0.2, 0.4), Pose2(-1.0, 2.0, -1.0)
    _, alpha, beta = polar_coordinates(pose, goal)
    assert wrap_angle(alpha + beta) == pytest.approx(wrap_angle(goal.theta - pose.theta))


class Unicycle:
    """Ideal kinematics; VSLAM fixes at 10 Hz (truth, 30 ms old); odometry with a scale and heading bias."""

    def __init__(self, start: Pose2, odom_scale=1.0, odom_drift=0.0, fixes=True, travel_held=False):
        self.true = start
        self.start = start
        self.odom = Pose2()
        self.odom_scale, self.odom_drift, self.fixes = odom_scale, odom_drift, fixes
        self.travel_held = travel_held      # an obstacle stop holding the travel, a turn on the spot let through
        self.history = []

    def run(self, ctrl: GotoController, seconds=40.0, dt=0.01):
        est, v_log = None, []
        for k in range(int(seconds / dt)):
            now = int(k * dt * 1e9)
            if self.fixes and k % 10 == 0 and len(self.history) > 3:
                t_ns, truth, odom = self.history[-3]
                est = Estimate(t_ns, "vslam", True, VslamFix(self.start.between(truth), odom, np.eye(4), 100, 0))
            ctx = ControlContext(now, dt, self.odom, WheelState(now, (0.0, 0.0), (0.0, 0.0)), {"vslam": est}, k)
            tw = ctrl.update(ctx)
            if self.travel_held:
                tw = Twist(0.0, tw.w)
            v_log.append((tw.v, tw.w))
            self.true = arc_step(self.true, tw.v * dt, tw.w * dt)
            self.odom = arc_step(self.odom, tw.v * dt * self.odom_scale, tw.w * dt + self.odom_drift * abs(tw.v) * dt)
            self.history.append((now, self.true, self.odom))
            if ctrl.finished:
                break
        return np.array(v_log)


@pytest.mark.parametrize("goal", [(0.0, 3.0, 0.0), (1.8, 2.4, 90.0), (-2.0, -1.0, 180.0), (0.5, 0.0, -90.0)])
def test_goto_converges_from_odometry_with_bias_corrected_by_vslam(goal):
    g = Pose2(goal[0], goal[1], math.radians(goal[2]))
    sim = Unicycle(Pose2(), odom_scale=1.05, odom_drift=0.05)
    ctrl = GotoController(g, GotoConfig())
    vw = sim.run(ctrl)
    assert ctrl.finished, ctrl.status()
    rel = sim.true
    assert math.hypot(rel.x - g.x, rel.z - g.z) < 0.015
    assert abs(math.degrees(wrap_angle(rel.theta - g.theta))) < 1.0
    assert (vw[:, 0] >= 0).all(), "forward only"
    assert np.abs(vw[:, 0]).max() <= GotoConfig().cruise_speed + 1e-9
    near = [abs(v) for (v, w), (_, t, _) in zip(vw, sim.history) if math.hypot(t.x - g.x, t.z - g.z) < 0.05]
    assert max(near, default=0.0) < 0.06, "slows down near the goal"


@pytest.mark.parametrize("goal_deg", [0.0, 90.0])
def test_goto_on_a_planned_route_drives_its_last_leg_straight_and_turns_at_the_goal(goal_deg):
    """`goto --map` plans around obstacles: the last leg (here the whole route, 1 m due west) is driven
    along the plan, and the goal heading (north; east, behind the robot) is taken on the spot. The polar law's
    heading term swings 15 / 32 cm off that line to arrive along the goal heading, where nobody checked the
    clearance (room seeds 5 and 7: the nose turned to a box beyond the goal and the obstacle stop held it)."""
    s, g = Pose2(1.0, 0.0, math.radians(-90.0)), Pose2(0.0, 0.0, math.radians(goal_deg))

    def off_the_leg(follow_route: bool) -> float:
        sim = Unicycle(s)
        ctrl = GotoController(s.between(g), GotoConfig(), follow_route=follow_route)
        sim.run(ctrl)
        assert ctrl.finished, ctrl.status()
        assert math.hypot(sim.true.x - g.x, sim.true.z - g.z) < 0.015
        assert abs(math.degrees(wrap_angle(sim.true.theta - g.theta))) < 1.0
        return max(abs(t.z) for _, t, _ in sim.history)

    assert off_the_leg(True) < 0.005                         # measured 0.0 cm
    assert off_the_leg(False) > 0.1                          # the free law's swing: 15 / 32 cm


def test_goto_on_a_planned_route_held_by_the_obstacle_stop_turns_to_its_next_waypoint():
    """While the obstacle stop holds the travel and lets a turn on the spot through, a robot on a planned
    route turns to face its next waypoint. Benchmarks/goto_replan.py --seed 5 from (-0.9, -1.5): re-planned
    past box_a's corner, the robot at (-0.78, 0.91) facing the box (-114.8 deg) with the next waypoint at
    (-2.41, 1.66) (49.5 deg to its left) and the goal at (-1.3, 1.2) beyond it; the free law's heading term
    (toward the goal from the waypoint, 178 deg from the robot's heading) cancelled its bearing term and the
    robot stood, held, for the rest of the run."""
    s = Pose2(-0.78, 0.91, math.radians(-114.8))
    goal, waypoint = Pose2(-1.3, 1.2, 0.0), Pose2(-2.41, 1.66, 0.0)

    def bearing_left_deg(follow_route: bool) -> float:
        sim = Unicycle(s, travel_held=True)
        w = s.between(waypoint)
        ctrl = GotoController(s.between(goal), GotoConfig(), waypoints=[(w.x, w.z)], follow_route=follow_route)
        sim.run(ctrl, seconds=5.0)
        to = math.atan2(waypoint.x - sim.true.x, waypoint.z - sim.true.z)
        return abs(math.degrees(wrap_angle(to - sim.true.theta)))

    assert bearing_left_deg(True) < 2.0                       # measured 0.0 deg
    assert bearing_left_deg(False) > 30.0                     # the free law: stuck 49 deg off


def test_goto_waits_for_vslam_and_stops_when_driving_blind():
    sim = Unicycle(Pose2(), fixes=False)
    ctrl = GotoController(Pose2(0.0, 3.0, 0.0))
    vw = sim.run(ctrl, seconds=2.0)
    assert (vw == 0).all() and ctrl.status()["state"] == "waiting"
    # One fix, then none: the robot drives at most blind_distance_m on odometry and stops.
    sim = Unicycle(Pose2(), fixes=True)
    ctrl = GotoController(Pose2(0.0, 3.0, 0.0))
    sim.run(ctrl, seconds=0.2)
    sim.fixes = False
    sim.run(ctrl, seconds=10.0)
    assert not ctrl.finished and ctrl.status()["state"] == "blind"
    assert 0.2 < sim.true.z < GotoConfig().blind_distance_m + 0.1


# ------------------------------------------------------------------------------------ stage
def _render(cam: SimCamera, poses, disparity_only=False):
    for i, p in enumerate(poses):
        f = cam.render_frame(p, int(i * 1e8), i)
        if disparity_only:
            f = Frame(f.image, f.stamp_ns, f.seq, disparity=f.disparity, meta={**f.meta, "baseline_m": 0.12})
        yield f


@pytest.mark.parametrize("disparity_only", [False, True], ids=["stereo-pair", "disparity-image-oak-like"])
def test_stage_follows_a_drive_in_the_rendered_room(disparity_only):
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    # 1.5 m forward while turning 30 degrees right, 3 cm per frame.
    poses = [start]
    for _ in range(50):
        poses.append(arc_step(poses[-1], 0.03, math.radians(0.6)))
    # OAK-like: disparity only, and the baseline comes with the frames (the device's calibration)
    stage = (VslamStage(model, mount, None, VslamNavConfig(), baseline_from_frames=True) if disparity_only
             else VslamStage(model, mount, 0.12, VslamNavConfig()))
    for f, p in zip(_render(cam, poses, disparity_only), poses):
        est = stage.process(f, start.between(p))     # odometry = truth here; only the first one is used
        assert est.ok and est.kind == "vslam"
    truth = start.between(poses[-1])
    got = est.value.pose
    assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.02  # measured 1.65-1.77 cm on 2026-12-04
    assert abs(math.degrees(wrap_angle(got.theta - truth.theta))) < 0.12  # measured 0.058-0.060 deg on 2026-12-04, bar 2x
    assert abs(est.value.quality["height_error_m"]) < 0.001  # measured 0.38-0.50 mm on 2026-12-04, bar 2x


def test_stage_needs_stereo():
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    with pytest.raises(ValueError, match="stereo_baseline.*metric_scale: odometry"):
        VslamStage(model, CameraMount(), None)
    stage = VslamStage(model, CameraMount(), 0.12)
    est = stage.process(Frame(np.zeros((240, 320), np.uint8), 0, 0), Pose2())    # not ok; the next is tried
    assert not est.ok and "neither a right image nor a disparity image" in est.info["reason"]
    stage = VslamStage(model, CameraMount(), None, baseline_from_frames=True)
    est = stage.process(Frame(np.zeros((240, 320), np.uint8), 0, 0), Pose2())   # not ok; the next is tried
    assert not est.ok and "carries no meta['baseline_m']" in est.info["reason"]
    assert est.info["reason"].startswith("vslam: ") and stage.baseline is None


@pytest.mark.parametrize("late", [[8], [0], [8, 9, 10, 11, 12, 13, 14, 15]],
                         ids=["one-frame", "first-frame", "eight-frames"])
def test_a_frame_without_disparity_is_not_ok_and_the_stage_carries_on(late):
    """OAK-like camera (disparity only): the driver publishes a frame without disparity whenever its disparity
    arrives late, the first frame too. That frame is an estimate that is not ok saying why (it raised
    ValueError, which ends the run); the frames after it are ok again and the pose stays right."""
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    poses = [start]
    for _ in range(24):
        poses.append(arc_step(poses[-1], 0.03, 0.0))
    stage = VslamStage(model, mount, None, VslamNavConfig(), baseline_from_frames=True)
    results = []
    for i, (f, p) in enumerate(zip(_render(cam, poses, disparity_only=True), poses)):
        if i in late:
            f = Frame(f.image, f.stamp_ns, f.seq, disparity=None, meta=f.meta)
        results.append(stage.process(f, start.between(p)))
    for i, r in enumerate(results):
        if i in late:
            assert not r.ok and "disparity" in r.info["reason"], i
            assert r.kind == "vslam" and isinstance(r.value, VslamFix)
        else:
            assert r.ok, (i, r.info)
    assert stage.stats["unusable"] == len(late)
    truth, got = start.between(poses[-1]), results[-1].value.pose
    # measured 0.23-0.46 cm and 0.003-0.037 deg over the three cases on 2026-12-04, bars about 2x
    assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.01
    assert abs(math.degrees(wrap_angle(got.theta - truth.theta))) < 0.08


@pytest.mark.parametrize("first", ["dark", "grey"])
@pytest.mark.parametrize("disparity_only", [False, True], ids=["stereo-pair", "disparity-image-oak-like"])
def test_a_first_frame_without_landmarks_is_not_a_start(first, disparity_only):
    """A dark first frame (lens cap just off, exposure not settled) or a uniform grey one gives no landmarks.
    The stage initialised on it with none and stayed lost for the whole run (a restart needs an earlier good
    pose). Now such a start is not ok, says why, and the next frames start the VSLAM at the odometry pose."""
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    poses = [start]
    for _ in range(20):
        poses.append(arc_step(poses[-1], 0.03, 0.0))
    stage = (VslamStage(model, mount, None, VslamNavConfig(), baseline_from_frames=True) if disparity_only
             else VslamStage(model, mount, 0.12, VslamNavConfig()))
    results = []
    for i, (f, p) in enumerate(zip(_render(cam, poses, disparity_only), poses)):
        if i < 2:                                       # the first two frames
            grey = np.full_like(f.image, 0 if first == "dark" else 128)
            f = Frame(grey, f.stamp_ns, f.seq, disparity=None if f.disparity is None else np.full_like(
                f.disparity, np.nan if first == "dark" else 0.0), right=None if f.right is None else grey.copy(),
                meta=f.meta)
        results.append(stage.process(f, start.between(p)))
    for r in results[:2]:
        assert not r.ok and "landmarks" in r.info["reason"] and "min_inliers" in r.info["reason"]
    assert all(r.ok for r in results[2:]), [r.info for r in results]
    assert stage.stats["lost"] == 2 and stage.stats["restarts"] == 0
    truth, got = start.between(poses[-1]), results[-1].value.pose
    # measured 0.32-0.56 cm and 0.012-0.013 deg over the four cases on 2026-12-04, bars about 2x
    assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.012
    assert abs(math.degrees(wrap_angle(got.theta - truth.theta))) < 0.03


VSLAM_BAD_FRAMES = {
    # (make the bad frame from a good one, what the reason says)
    "half-size-image": (lambda f: Frame(f.image[::2, ::2].copy(), f.stamp_ns, f.seq, f.disparity, f.right, f.meta),
                        "the image is 160x120, the camera calibration is for 320x240"),
    "uint16-image": (lambda f: Frame(f.image.astype(np.uint16) * 256, f.stamp_ns, f.seq, f.disparity, f.right,
                                     f.meta), "the image is uint16"),
    "float-image": (lambda f: Frame(f.image.astype(np.float32) / 255.0, f.stamp_ns, f.seq, f.disparity, f.right,
                                    f.meta), "the image is float32"),
    "half-size-right": (lambda f: Frame(f.image, f.stamp_ns, f.seq, f.disparity,
                                        None if f.right is None else f.right[::2, ::2].copy(), f.meta),
                        "the right image is 160x120"),
    "half-size-disparity": (lambda f: Frame(f.image, f.stamp_ns, f.seq,
                                            None if f.disparity is None else f.disparity[::2, ::2].copy(),
                                            f.right, f.meta), "the disparity image is 160x120"),
    # an OAK's raw fixed-point disparity (3 subpixel bits) passed on unscaled: depths 8 times too near, a
    # VSLAM at an eighth of the scale, ok
    "uint16-disparity": (lambda f: Frame(f.image, f.stamp_ns, f.seq,
                                         None if f.disparity is None else
                                         (np.nan_to_num(f.disparity) * 8).astype(np.uint16), f.right, f.meta),
                         "the disparity image is uint16"),
}


@pytest.mark.parametrize("kind", list(VSLAM_BAD_FRAMES))
def test_a_frame_of_another_format_is_not_ok_and_the_stage_carries_on(kind):
    """A frame of another size or dtype raised in the KLT (cv2.error), which ends the run; it is not ok saying
    why, and the frames after it are ok again."""
    make, says = VSLAM_BAD_FRAMES[kind]
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    poses = [start]
    for _ in range(15):
        poses.append(arc_step(poses[-1], 0.03, 0.0))
    disparity_only = kind.endswith("-disparity")
    stage = (VslamStage(model, mount, None, VslamNavConfig(), baseline_from_frames=True) if disparity_only
             else VslamStage(model, mount, 0.12, VslamNavConfig()))
    results = []
    for i, (f, p) in enumerate(zip(_render(cam, poses, disparity_only), poses)):
        results.append(stage.process(make(f) if i in (0, 6) else f, start.between(p)))
    for i in (0, 6):                                       # before and after the start
        assert not results[i].ok and isinstance(results[i].value, VslamFix)
        assert results[i].info["reason"].startswith("vslam: ") and says in results[i].info["reason"], \
            results[i].info["reason"]
    assert all(r.ok for i, r in enumerate(results) if i not in (0, 6))
    assert stage.stats["unusable"] == 2 and stage.stats["restarts"] == 0
    truth, got = start.between(poses[-1]), results[-1].value.pose
    assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.009  # measured 0.19-0.44 cm on 2026-12-04, bar 2x


def test_monocular_stage_takes_its_scale_from_the_wheels():
    """metric_scale odometry: no stereo; the two-view initialisation happens once the wheels have moved the
    camera 0.2 m, scaled by that distance (with a 2 % odometry scale error), then the VSLAM carries on."""
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0)
    poses = [start]
    for _ in range(60):                                 # 1.8 m forward while turning 36 degrees right
        poses.append(arc_step(poses[-1], 0.03, math.radians(0.6)))
    stage = VslamStage(model, mount, None, VslamNavConfig(metric_scale="odometry"))
    results = []
    for i, p in enumerate(poses):
        odom = start.between(p)
        results.append(stage.process(cam.render_frame(p, int(i * 1e8), i), Pose2(odom.x, odom.z * 1.02, odom.theta)))
    first = next(i for i, r in enumerate(results) if r.ok)
    assert first == 7                                   # 7 x 3 cm x 1.02 >= 0.2 m
    assert all(r.value.quality.get("initialising") == "monocular" for r in results[:first])
    assert results[first].value.quality["initialised"] in ("essential", "homography")
    assert all(r.ok for r in results[first:]) and stage.stats["restarts"] == 0
    for i in (first, len(poses) - 1):
        truth, got = start.between(poses[i]), results[i].value.pose
        dist = math.hypot(truth.x, truth.z)
        # at the start the scale is the wheels' (2 % off); later the monocular scale drifts a little
        assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.05 * dist, (i, got, truth)
        assert abs(math.degrees(wrap_angle(got.theta - truth.theta))) < 0.1  # measured 0.044 deg on 2026-11-30
    assert stage.stats["rescaled"] >= 1
    # Vslam.rescale: the same rays from the current camera, every distance times s, normal equations kept.
    slam = stage.slam
    X = slam.lm.P @ slam.R.T + slam.T
    AX_b = np.einsum("nij,nj->ni", slam.lm.A, slam.lm.P) - slam.lm.b
    slam.rescale(1.1)
    np.testing.assert_allclose(slam.lm.P @ slam.R.T + slam.T, 1.1 * X, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", slam.lm.A, slam.lm.P) - slam.lm.b, 1.1 * AX_b, atol=1e-9)
    with pytest.raises(ValueError, match="positive"):
        slam.rescale(0.0)


def test_goto_creeps_ahead_while_a_monocular_vslam_initialises():
    ctrl = GotoController(Pose2(0.0, 3.0, 0.0))
    init = VslamFix(Pose2(), Pose2(), np.eye(4), 0, -1, quality={"initialising": "monocular"})

    def step(k, odom, est):
        ctx = ControlContext(int(k * 1e7), 0.01, odom, WheelState(0, (0.0, 0.0), (0.0, 0.0)), {"vslam": est}, k)
        return ctrl.update(ctx)

    tw = step(0, Pose2(), Estimate(0, "vslam", False, init))
    assert (tw.v, tw.w) == (GotoConfig().init_creep_speed, 0.0) and ctrl.status()["state"] == "initialising"
    assert step(1, Pose2(0.0, 0.2), Estimate(1, "vslam", False, init)).v > 0
    assert step(2, Pose2(0.0, 0.31), Estimate(2, "vslam", False, init)).v == 0.0   # crept blind_distance_m
    fix = VslamFix(Pose2(0.0, 0.31), Pose2(0.0, 0.31), np.eye(4), 100, 0)
    tw = step(3, Pose2(0.0, 0.31), Estimate(3, "vslam", True, fix))
    assert tw.v > 0 and ctrl.status()["state"] == "drive"


def test_vslam_section_is_validated_at_load_with_file_and_key_path(tmp_path):
    from vbnav.control.config import ConfigError, load_config, parse_config

    with pytest.raises(ConfigError, match=r"robot.yaml: vslam.goto.k_beta"):
        parse_config({"vslam": {"goto": {"k_beta": 0.5}}}, "robot.yaml")
    with pytest.raises(ConfigError, match=r"vslam.relocalise_radus_m: unknown key"):
        parse_config({"vslam": {"relocalise_radus_m": 1.0}})
    assert parse_config({"vslam": {"max_landmarks": 300, "goto": {"cruise_speed": 0.2}}}).vslam.goto.cruise_speed == 0.2
    bad = tmp_path / "bad.yaml"
    bad.write_text("vslam:\n  goto: {position_tolerance_m: -1}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: vslam.goto.position_tolerance_m"):
        load_config(bad)


def test_stage_restarts_after_the_lens_was_covered_and_still_closes_the_loop_later():
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    poses = [start]
    for _ in range(30):
        poses.append(arc_step(poses[-1], 0.03, 0.0))
    stage = VslamStage(model, mount, 0.12, VslamNavConfig())
    results = []
    for i, p in enumerate(poses):
        cam.occluded = 10 <= i < 15                    # half a second of a covered lens
        odom = start.between(p)
        odom = Pose2(odom.x, odom.z * 1.02, odom.theta)  # 2 % odometry scale error bridges the gap
        results.append(stage.process(cam.render_frame(p, int(i * 1e8), i), odom))
    assert all(r.ok for r in results[:10]) and not any(r.ok for r in results[10:15])
    assert stage.stats["restarts"] >= 1
    assert all(r.ok for r in results[16:])
    refs = [r.value.reference for r in results]
    assert refs == sorted(refs), "reference indices keep growing across a restart"
    truth = start.between(poses[-1])
    got = results[-1].value.pose
    # 0.15 m bridged on odometry with 2 % error: a few mm, plus the VSLAM's own error
    assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.008  # measured 0.37 cm on 2026-12-04, bar 2x


def test_anchors_grow_with_the_area_seen_not_the_distance_driven():
    """Three laps of a 6 m loop (8 cm a frame): every reference frame was kept as an anchor, 14 more a lap
    without end. A place already anchored (within half the relocalisation radius and heading) keeps its
    anchor; the loop still closes against it on every lap."""
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    lap = loop_poses(72)
    start = lap[0]
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    stage = VslamStage(model, mount, 0.12, VslamNavConfig())
    kept, relocalised = [], []
    for i, p in enumerate(lap * 3):
        est = stage.process(cam.render_frame(p, int(i * 1e8), i), start.between(p))
        assert est.ok
        relocalised.append(est.info["anchor"] is not None)
        if (i + 1) % len(lap) == 0:
            kept.append(len(stage.anchors))
            truth, got = start.between(p), est.value.pose
            assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.01   # measured 0.27-0.46 cm on 2026-12-04, bar 2x
    assert kept[0] >= 8, kept                       # a lap is anchored all round (14 measured)
    assert kept[2] <= kept[0] + 2, kept             # measured 14, 14, 15 (without the rule 14, 28, 42)
    assert sum(relocalised[len(lap):]) > len(lap)   # laps 2-3 are posed against lap 1's anchors (144 of 144)
    assert stage.stats["anchors_skipped"] >= 2 * (kept[0] - 2)


def test_guided_matches_pick_the_nearest_descriptor_inside_the_radius_once():
    from vbnav.control.stages.vslam import guided_matches

    rng = np.random.default_rng(3)
    desc_a = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    pred = np.array([[10.0, 10.0], [50.0, 50.0], [200.0, 200.0]])
    noisy = desc_a.copy()
    noisy[:, 0] ^= 0b1                                  # 1 bit off
    far = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    corners = np.array([[12.0, 9.0], [30.0, 30.0], [52.0, 50.0], [51.0, 49.0], [400.0, 400.0]])
    desc_c = np.vstack((noisy[0], noisy[0], noisy[1], far, noisy[2]))
    lm, cn = guided_matches(pred, desc_a, corners, desc_c, radius=5.0)
    # landmark 0 -> corner 0 (corner 1 is as similar but outside the radius); 1 -> 2 (3 is near but unlike);
    # landmark 2's twin is 280 px away: no match
    assert lm.tolist() == [0, 1] and cn.tolist() == [0, 2]


def test_a_frame_with_non_finite_odometry_is_not_ok_and_the_stage_carries_on():
    """A NaN odometry reading (a drive reporting a NaN encoder position) made an ok fix whose odometry was NaN:
    the goto controller's fusion took it as its anchor and every later pose was NaN; the distance travelled
    stayed NaN for the run (relocalise_min_travel_m then never held anchors back). That frame is not ok now,
    saying why, at the last good pose, and the frames after it are ok again."""
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    mount = CameraMount(0.25, 0.1)
    start = Pose2(-1.5, -2.5, 0.0)
    cam = SimCamera(World.room(0), model, mount, lambda: start, clock=None, rate_hz=10, noise_std=2.0,
                    stereo_baseline=0.12)
    poses = [start]
    for _ in range(10):
        poses.append(arc_step(poses[-1], 0.03, 0.0))
    stage = VslamStage(model, mount, 0.12, VslamNavConfig())
    results = []
    for i, (f, p) in enumerate(zip(_render(cam, poses), poses)):
        odom = start.between(p)
        if i in (0, 5):
            odom = Pose2(float("nan"), odom.z, odom.theta)
        results.append(stage.process(f, odom))
    for i in (0, 5):
        r = results[i]
        assert not r.ok and "odometry" in r.info["reason"], (i, r.info)
        assert np.isfinite(r.value.pose.as_array()).all()
    assert all(r.ok for i, r in enumerate(results) if i not in (0, 5))
    assert math.isfinite(stage._travelled)
    truth, got = start.between(poses[-1]), results[-1].value.pose
    assert math.hypot(got.x - truth.x, got.z - truth.z) < 0.006  # measured 0.29 cm on 2026-12-04, bar 2x


@pytest.mark.parametrize("baseline", [float("nan"), float("inf"), -0.12, "0.12"])
def test_a_frame_baseline_that_is_no_distance_is_an_unusable_frame(baseline):
    """meta['baseline_m'] NaN, inf, negative or not a number (a device calibration gone wrong) raised ValueError
    out of the stage, which ended the run, where the obstacle stage and every other bad frame (no disparity,
    another size) are a frame that is not ok and a later frame goes on. It is that now: not ok, naming the
    value, no fix (the go-to controller stays stopped); a later frame with a good baseline starts the VSLAM."""
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    stage = VslamStage(model, CameraMount(), None, baseline_from_frames=True)
    disp = np.full((240, 320), 4.0, np.float32)
    est = stage.process(Frame(np.zeros((240, 320), np.uint8), 0, 0, disparity=disp, meta={"baseline_m": baseline}),
                        Pose2())
    assert not est.ok and stage.baseline is None and stage.stats["unusable"] == 1
    assert f"meta['baseline_m'] is {baseline!r}, not a distance > 0" in est.info["reason"], est.info["reason"]
    stage.process(Frame(np.zeros((240, 320), np.uint8), 1, 1, disparity=disp, meta={"baseline_m": 0.12}), Pose2())
    assert stage.baseline == 0.12 and stage.slam.baseline == 0.12


def test_monocular_start_spreads_its_corners_over_vslam_detect_cells():
    """vslam.detect_cells spread the front end's new corners over the image, but not the monocular start's: its
    first view's corners (the landmarks it starts with) were ranked over the whole image at once, all of them on
    the bright textured half. They are spread like the front end's now."""
    import cv2
    model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    blobs = cv2.GaussianBlur(np.random.default_rng(3).uniform(0, 1, (240, 320)).astype(np.float32), (0, 0), 2.0)
    blobs = (blobs - blobs.mean()) / blobs.std() / 3.0           # texture of about +-1 (3 sigma)
    image = np.where(np.arange(320)[None, :] < 160, 128 + 120 * blobs, 128 + 8 * blobs).clip(0, 255).astype(np.uint8)
    dim_share = {}
    for cells in (0, 16):
        stage = VslamStage(model, CameraMount(0.25, 0.1), None, VslamNavConfig(metric_scale="odometry",
                                                                              detect_cells=cells))
        est = stage.process(Frame(image, 0, 0), Pose2())
        assert not est.ok and est.value.quality["initialising"] == "monocular"
        dim_share[cells] = float(np.mean(stage._mono.px0[:, 0] >= 160))
    assert dim_share[0] < 0.05 and dim_share[16] > 0.3, dim_share



@pytest.mark.parametrize("camera,says", [
    ({"distortion": [-0.3, 0.1, 0.0, 0.0, 0.0]}, "camera.distortion [-0.3, 0.1, 0.0, 0.0, 0.0]"),
    ({"model": "fisheye", "distortion": [0.1, 0.0, 0.0, 0.0]}, "camera.model fisheye"),
])
def test_the_stereo_vslam_refuses_a_distorted_camera(camera, says):
    """The stereo VSLAM takes a rectified pair (Frame.right, or the device's disparity: depth = fx B / d, and
    a right-image match must lie on the same row): with camera.distortion or a fisheye model its rays
    undistorted rectified images, or its stereo read distorted ones as rectified, and every landmark's depth
    was wrong without a word. It is refused, naming the field; the monocular VSLAM (metric_scale odometry)
    takes the distortion."""
    from vbnav.control.config import parse_config
    from vbnav.control.stages.vslam import make_vslam_stage
    cfg = parse_config({"camera": {"options": {"stereo_baseline": 0.1}, **camera}})
    with pytest.raises(ValueError, match=r"rectified stereo pair .*" + re.escape(says)):
        make_vslam_stage(cfg)
    mono = parse_config({"camera": camera, "vslam": {"metric_scale": "odometry"}})
    assert make_vslam_stage(mono).monocular
    make_vslam_stage(parse_config({"camera": {"options": {"stereo_baseline": 0.1}, "distortion": [0.0] * 5}}))


@pytest.mark.parametrize("vslam, key", [
    ({"odometry_scale_gain": 0.3}, "odometry_scale_gain"),                    # stereo scale: never rescaled
    ({"odometry_init_baseline_m": 0.3}, "odometry_init_baseline_m"),
    ({"metric_scale": "odometry", "stereo_max_depth_baselines": 40.0}, "stereo_max_depth_baselines"),
    ({"ba_history": 4}, "ba_history"),                                       # no bundle adjustment at all
    ({"ba_outlier_sigmas": 2.0}, "ba_outlier_sigmas"),
])
def test_vslam_settings_of_the_other_metric_scale_are_refused(vslam, key):
    """The vslam.odometry_* settings steer a single camera's scale (metric_scale odometry), stereo_max_depth_
    baselines a stereo pair's landmarks, ba_history and ba_outlier_sigmas the bundle adjustment (a single
    camera's, ba_window > 0): written where they do not apply they were accepted and never read (as ba_window
    with stereo is refused). Refused, naming the setting; where they apply they are taken."""
    from vbnav.control.config import ConfigError, parse_config
    with pytest.raises(ConfigError, match=rf"vslam.*{key}"):
        parse_config({"vslam": vslam})
    applies = {"odometry_scale_gain": {"metric_scale": "odometry"}, "odometry_init_baseline_m":
               {"metric_scale": "odometry"}, "stereo_max_depth_baselines": {"metric_scale": "stereo"},
               "ba_history": {"metric_scale": "odometry", "ba_window": 5},
               "ba_outlier_sigmas": {"metric_scale": "odometry", "ba_window": 5}}[key]
    assert getattr(parse_config({"vslam": {**vslam, **applies}}).vslam, key) == vslam[key]


def test_bundle_adjustment_settings_are_kept_while_it_is_switched_off():
    """ba_window 0 switches a single camera's bundle adjustment off; its ba_history and ba_outlier_sigmas were
    refused then, against the documented rule that a feature switched off keeps its settings unread (so that
    it can be switched on again without writing them anew; docs/configuration.md). Kept now, listed there, and
    taken once ba_window switches it on; with metric_scale stereo there is none to switch on: still refused."""
    from vbnav.control.commands.config import HEADER
    from vbnav.control.config import parse_config
    off = {"metric_scale": "odometry", "ba_window": 0, "ba_history": 4, "ba_outlier_sigmas": 2.0}
    kept = parse_config({"vslam": off}).vslam
    assert (kept.ba_history, kept.ba_outlier_sigmas) == (4, 2.0)
    on = parse_config({"vslam": {**off, "ba_window": 5}}).vslam
    assert (on.ba_window, on.ba_history, on.ba_outlier_sigmas) == (5, 4, 2.0)
    assert "`vslam.ba_history` and `ba_outlier_sigmas` with `vslam.ba_window` 0" in HEADER


def test_a_creep_speed_with_a_stereo_vslam_is_refused():
    """vslam.goto.init_creep_speed drives the robot while a monocular VSLAM waits for parallax; a stereo one
    never initialises that way, and the setting was accepted and never read. Refused, naming it."""
    from vbnav.control.config import ConfigError, parse_config
    with pytest.raises(ConfigError, match=r"vslam.*goto.init_creep_speed.*metric_scale odometry"):
        parse_config({"vslam": {"goto": {"init_creep_speed": 0.05}}})
    cfg = parse_config({"vslam": {"metric_scale": "odometry", "goto": {"init_creep_speed": 0.05}}})
    assert cfg.vslam.goto.init_creep_speed == 0.05
