"""Robot configuration: YAML files validated on load into one typed model, :class:`Config`.

Every error names the file, the key path and what was expected, e.g.
``configs/sim.yaml: robot.wheel_radius: Input should be greater than 0 (got -0.05)``.
Unknown keys are errors (typos must not silently fall back to defaults).

The sections of the features have their own modules next to this one
(``vbc.py``, ``vslam.py``, ``obstacles.py``, ``telemetry.py``); the strict base
and the error formatting are in ``base.py``. Driver-specific ``options`` blocks
are validated by the chosen driver's own ``Options`` model (see
vbnav.drivers.registry), so adding a driver never edits this file beyond the
registry line.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal, Optional

import yaml
from pydantic import Field, PrivateAttr, ValidationError, field_validator, model_validator

from vbnav.drivers.calibration import CalibrationError, CameraCalibration, load_camera_calibration
from vbnav.drivers.errors import yaml_problem
from vbnav.drivers.plain_values import load_yaml
from vbnav.control.config.base import ConfigError, Strict, format_errors, written
from vbnav.control.config.obstacles import ObstaclesConfig
from vbnav.control.config.telemetry import TelemetryConfig
from vbnav.control.config.vbc import VBCConfig
from vbnav.control.config.vslam import VslamNavConfig
from vbnav.drivers import registry
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera, check_distortion
from vbnav.vision.geometry import CameraMount, Pose2

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"   # control/config/__init__.py -> repo/configs


class RobotConfig(Strict):
    name: str = Field("sim", pattern=r"^[A-Za-z0-9_\-]+$", description="robot name, used in telemetry keys")
    wheel_radius: float = Field(0.05, gt=0, le=1.0, description="wheel radius, m")
    wheel_separation: float = Field(0.30, gt=0, le=5.0, description="distance between wheel contact points, m")
    max_wheel_speed: float = Field(20.0, gt=0, description="wheel speed limit, rad/s, per wheel; at most the "
                                   "drive's own (Dynamixel velocity_limit_rad_s, ODrive vel_limit_turns_s / "
                                   "gear_ratio x 2 pi), which clips one wheel alone")
    max_linear_speed: float = Field(0.5, gt=0, description="forward speed limit, m/s; at most "
                                    "max_wheel_speed * wheel_radius")
    max_angular_speed: float = Field(1.5, gt=0, description="turn rate limit, rad/s; at most "
                                     "2 * max_wheel_speed * wheel_radius / wheel_separation (on the spot: the "
                                     "default is cut to it, a value written above it is refused)")
    max_linear_accel: float = Field(1.0, gt=0, description="forward acceleration limit, m/s^2")
    max_angular_accel: float = Field(4.0, gt=0, description="angular acceleration limit, rad/s^2")
    footprint_radius: Optional[float] = Field(
        None, gt=0, le=5.0, description="a round robot: its whole outline lies within this radius of the axle centre, "
                                        "m; it then turns on the spot without sweeping floor it does not already "
                                        "cover (obstacles.turn_when_held needs it), and vbnav goto --map plans with it "
                                        "as the robot's radius (unless --robot-radius is given)")


class MountConfig(Strict):
    height: float = Field(0.25, gt=0, description="optical centre above the floor, m")
    forward: float = Field(0.10, description="ahead of the axle centre, m")
    lateral: float = Field(0.0, description="to the right of the axle centre, m")
    pitch_deg: float = Field(0.0, ge=-90, le=90, description="camera pitch, deg, positive looking down")
    yaw_deg: float = Field(0.0, ge=-180, le=180, description="camera yaw, deg, positive looking right")
    roll_deg: float = Field(0.0, ge=-45, le=45, description="camera roll about its optical axis, deg, positive "
                            "turned clockwise seen from behind (the image's right side lower)")

    def to_mount(self) -> CameraMount:
        return CameraMount(self.height, self.forward, self.lateral, math.radians(self.pitch_deg),
                           math.radians(self.yaw_deg), math.radians(self.roll_deg))


class CameraConfig(Strict):
    driver: str = Field("sim", description=f"camera driver: {', '.join(registry.CAMERAS)} (drivers/registry.py; "
                                           f"each driver's options are under Driver options)")
    model: Literal["pinhole", "fisheye"] = Field("pinhole", description="lens model of the intrinsics below")
    width: int = Field(640, gt=0, description="image width, px")
    height: int = Field(480, gt=0, description="image height, px")
    fx: float = Field(400.0, gt=0, allow_inf_nan=False, description="focal length along x, px")
    fy: float = Field(400.0, gt=0, allow_inf_nan=False, description="focal length along y, px")
    cx: float = Field(319.5, allow_inf_nan=False, description="principal point x, px")
    cy: float = Field(239.5, allow_inf_nan=False, description="principal point y, px")
    distortion: list[float] = Field(default_factory=list, max_length=14,
                                    description="OpenCV distortion coefficients, finite numbers: pinhole k1 k2 p1 "
                                                "p2 [k3 ...] (4, 5, 8, 12 or 14 of them), fisheye k1 k2 k3 k4; "
                                                "empty: none")
    calibration_file: Optional[str] = Field(
        None, description="camera calibration: OpenCV YAML/XML, ROS camera_info YAML, vbnav stereo YAML or KITTI "
                          "calib.txt (docs/hardware.md); loaded with the config, its model, size, intrinsics, "
                          "distortion, stereo baseline and a stereo YAML's mount (height, pitch, roll) replace the "
                          "inline values (a different inline width/height, baseline or mount is an error; a "
                          "disparity_scale is refused). A relative path is taken from the config file's folder")
    rate_hz: float = Field(15.0, gt=0, le=1000, description="frame rate, Hz (not used for files: the replay "
                                                             "camera plays at the recorded times or its "
                                                             "options.rate_hz, a v4l2 video file at its own rate "
                                                             "or options.replay_rate_hz; rate_hz only for a file "
                                                             "that gives no rate). Written for the replay camera "
                                                             "or an OAK replay_file, which never read it: refused. "
                                                             "On the simulated clock at most loop.rate_hz (read "
                                                             "once a cycle: the default is cut to it, a value "
                                                             "written above it is refused)")
    stale_after_s: float = Field(0.5, gt=0, description="a frame older than this, s, is a safety stop; so "
                                                        "is an image that has not changed for this long "
                                                        "while the wheels moved (a frozen camera); above the "
                                                        "frame period (plus the simulated vision latency): a "
                                                        "limit every frame outlives is refused")
    mount: MountConfig = Field(default_factory=MountConfig, description="where the camera sits on the robot")
    options: dict[str, Any] = Field(default_factory=dict, description="driver-specific, see the driver's Options")

    _calibration: Optional[CameraCalibration] = PrivateAttr(None)

    @property
    def calibration(self) -> Optional[CameraCalibration]:
        """The loaded ``calibration_file`` (None: the inline intrinsics are the calibration)."""
        return self._calibration

    def stereo_baseline(self) -> Optional[float]:
        """The stereo baseline, m: the calibration file's, else ``options.stereo_baseline``, else None."""
        if self._calibration is not None and self._calibration.baseline is not None:
            return self._calibration.baseline
        b = (self.options or {}).get("stereo_baseline")
        return float(b) if b else None

    def rectified_problem(self) -> str:
        """"" when the images are a rectified pinhole camera's (no distortion), as the stereo stages (obstacles,
        line map) take them; else which field says otherwise (they would read distorted images as rectified)."""
        src = " (from camera.calibration_file)" if self._calibration is not None else ""
        if self.model == "fisheye":
            return f"camera.model fisheye{src}"
        if any(self.distortion):
            return f"camera.distortion {list(self.distortion)}{src}"
        return ""

    def rectified_refusal(self, who: str, remedy: str) -> str:
        """"" when ``who`` (a stage reading a rectified stereo pair) can take this camera, else the one sentence
        every such stage refuses it with: which field describes distorted images, and ``remedy``."""
        distorted = self.rectified_problem()
        if not distorted:
            return ""
        return (f"{who} takes a rectified stereo pair (a pinhole camera without distortion), and {distorted} "
                f"describes distorted images it would read as rectified ({remedy})")

    def calibration_record(self) -> dict:
        """The calibration in use as a route manifest records it: the intrinsics every stage uses, and the
        file they came from with its hash (file None, format 'inline': the values in the config)."""
        cal = self._calibration
        return {"file": cal.file if cal else None, "sha256": cal.sha256 if cal else None,
                "format": cal.format if cal else "inline", "model": self.model, "width": self.width,
                "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "distortion": list(self.distortion), "baseline": self.stereo_baseline()}

    @field_validator("distortion")
    @classmethod
    def _distortion_opencv_takes(cls, v, info):
        # NaN, inf or a count OpenCV refuses failed the first undistortPoints of the run (a fisheye's was
        # padded or cut to 4); the model is validated first (declared before)
        return list(check_distortion(info.data.get("model", "pinhole"), v))

    @model_validator(mode="after")
    def _principal_point_in_image(self):
        # A principal point outside the image is a calibration for another image size (or a typo).
        for name, v, size in (("cx", self.cx, self.width), ("cy", self.cy, self.height)):
            if not 0 <= v <= size:
                raise ValueError(f"{name} {v} px is outside the {self.width}x{self.height} image")
        return self

    def to_model(self):
        cls = FisheyeCamera if self.model == "fisheye" else PinholeCamera
        dist = tuple(self.distortion)
        if self.model == "fisheye":
            dist = dist or (0.0,) * 4           # none: the equidistant projection (check_distortion: 0 or 4)
        return cls(self.width, self.height, self.fx, self.fy, self.cx, self.cy, dist)


class DriveConfig(Strict):
    driver: str = Field("sim", description="wheel drive driver: a name from drivers/registry.py (see Driver options)")
    invert_left: bool = Field(False, description="flip the sign of the left wheel (a motor mounted the other "
                                                 "way; the serial drives; refused for the simulated one)")
    invert_right: bool = Field(False, description="flip the sign of the right wheel (as invert_left)")
    options: dict[str, Any] = Field(default_factory=dict, description="driver-specific, see the driver's Options")
    reconnect_window_s: float = Field(
        5.0, ge=0, le=600,
        description="after the drive's bus is lost (USB adapter gone), how long the run waits for it to come back "
                    "before it ends with reason 'drive'. Meanwhile the device's own watchdog keeps the wheels "
                    "stopped; back within the window, the drive repeats its safe bring-up and the robot stays "
                    "stopped until resume. 0 ends the run at once. A few seconds covers an adapter that "
                    "re-enumerates after a loose plug or a brown-out, and is short enough that an operator "
                    "learns soon when it does not")


class LoopConfig(Strict):
    rate_hz: float = Field(100.0, gt=0, le=5000, description="control loop rate, Hz")
    overrun_policy: Literal["skip", "catch_up"] = Field(
        "skip", description="skip: a late cycle drops the missed ticks and re-aligns to the grid; "
                            "catch_up: run missed ticks back to back")
    max_missed_streak: int = Field(5, ge=1, description="consecutive overruns that trigger a safety stop "
                                   "(fatal 'deadline'); with catch_up, a tick that only ran late to catch up "
                                   "(its work took less than a period) ends the streak")
    spin_us: int = Field(0, ge=0, le=2000, description="busy-wait before each deadline, microseconds")
    realtime_priority: int = Field(0, ge=0, le=99, description="SCHED_FIFO priority of the loop thread "
                                   "(0: normal scheduling); needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO as high (the "
                                   "unit of 'vbnav service install' sets LimitRTPRIO), else a warning event")
    cpu_affinity: list[int] = Field(default_factory=list, description="CPUs the loop thread may run on (empty: any)")
    process_cpu_affinity: list[int] = Field(
        default_factory=list, description="CPUs every thread of the process may run on (vision, telemetry; empty: "
                                          "any); the loop thread then narrows to loop.cpu_affinity. 'vbnav service "
                                          "install' writes it as the unit's CPUAffinity=; a run applies it itself")
    gil_switch_interval_us: int = Field(200, ge=50, le=5000, description="Python's thread switch interval "
                                        "while a real-time loop runs: how long a busy vision thread may "
                                        "keep the loop waiting for the GIL (Python's default is 5000)")
    stall_periods: float = Field(5.0, gt=1, description="a cycle that starts more than this many periods after "
                                 "the tick it follows is a stall: wheels to zero and a latched 'stall' stop "
                                 "until resume (the wheels kept their last command during the stall)")

    @field_validator("cpu_affinity", "process_cpu_affinity")
    @classmethod
    def _cpu_numbers(cls, v: list[int]) -> list[int]:
        if any(c < 0 for c in v):
            raise ValueError("CPU numbers are >= 0")
        return v


class SafetyConfig(Strict):
    command_timeout_s: float = Field(0.5, gt=0, description="teleop/network command silence that stops the robot")
    estimate_timeout_s: float = Field(1.0, gt=0, description="vision estimate age that stops a vision controller; "
                                      "above the frame period (plus the simulated vision latency): a limit every "
                                      "estimate outlives is refused")
    release_s: float = Field(0.5, ge=0, le=10, description="s: a held stop (stale frame or "
                             "estimate) ends after its cause has been clear this long: a debounce, so "
                             "a flickering cause does not start and stop the wheels every cycle (a silent "
                             "command stream ends with the first fresh command; an obstacle stop after "
                             "obstacles.release_s, its stage's own debounce)")
    latch_file: Optional[str] = Field(
        None, min_length=1,
        description="file that keeps an operator's estop across restarts of the process: written when an estop "
                    "latches, removed by the resume that clears it; found at start-up it latches the run before "
                    "the wheels are powered (unreadable or unparsable: latched all the same). ~ expanded, relative "
                    "to the config file's folder. Default: $STATE_DIRECTORY/estop.json when systemd sets "
                    "STATE_DIRECTORY (the unit 'vbnav service install' writes has StateDirectory=vbnav), else "
                    "none: an estop then holds only until the process ends (docs/safety.md)")


# The simulated worlds the room's loop (controller.teach room_loop, vbnav demo) runs in: the room's walls.
ROOM_WORLDS = ("room", "empty_room")


class SimConfig(Strict):
    seed: int = Field(0, ge=0, description="random seed of the world's textures, the image noise and the wheel "
                                           "slip")
    realtime: bool = Field(False, description="run on the wall clock instead of the simulated clock (a camera "
                                              "that is not simulated runs on the wall clock anyway: written "
                                              "there, refused)")
    world: Literal["room", "empty_room", "corridor", "corridor_step"] = Field(
        "room", description="simulated world the simulated camera renders (drivers/sim/world.py World.by_name; "
                            "written with another camera, refused)")
    motor_time_constant_s: float = Field(0.05, ge=0, description="first-order lag of the wheel speed, s")
    wheel_accel_limit: float = Field(40.0, gt=0, description="rad/s^2, motor torque limit")
    encoder_ticks_per_rev: int = Field(4096, gt=0, description="encoder resolution, ticks per wheel turn")
    slip_std: float = Field(0.002, ge=0, description="wheel slip noise, m per sqrt(m) of wheel travel (random walk)")
    vision_latency_s: float = Field(0.03, ge=0, description="simulated time from exposure to estimate, on the "
                                      "simulated clock (on the wall clock the vision's own time is the latency: "
                                      "written there, refused)")
    image_noise_std: float = Field(2.0, ge=0, description="the simulated camera's image noise, grey levels "
                                                          "(written with another camera, refused)")
    start_pose: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0], min_length=3, max_length=3,
        description="where the simulated robot starts in the world: [x m (right), z m (forward), heading deg "
                    "(positive turning right)]")

    @field_validator("start_pose")
    @classmethod
    def _finite_pose(cls, v: list[float]) -> list[float]:
        if not all(math.isfinite(c) for c in v):
            raise ValueError("expected finite numbers [x, z, heading_deg]")
        return v

    def start(self) -> Pose2:
        x, z, theta_deg = self.start_pose
        return Pose2(x, z, math.radians(theta_deg))

    def set_start(self, pose: Pose2) -> None:
        self.start_pose = [pose.x, pose.z, math.degrees(pose.theta)]


class ControllerConfig(Strict):
    kind: Literal["idle", "scripted", "teleop", "operator"] = Field(
        "scripted", description="controller of 'vbnav run': scripted (the script below), teleop (cmd/teleop), "
                                "operator (teleop plus cmd/mode idle/teach/repeat), idle")
    script: list[list[float]] = Field(
        default_factory=lambda: [[0.3, 0.0, 3.0], [0.3, 0.4, 4.0], [0.0, 0.0, 1.0]],
        description="[linear m/s, angular rad/s, duration s] segments for the scripted drive")
    teach: Literal["teleop", "room_loop"] = Field(
        "teleop", description="who drives while 'vbnav teach' records: teleop (the operator, cmd/teleop) or "
                              "room_loop (simulated drive and room only: a scripted teacher once around the simulated "
                              "room's 20.6 m loop at 0.4 m/s, or robot.max_linear_speed when lower, from "
                              "sim.start_pose)")
    routes_dir: str = Field(
        "~/.local/share/vbnav/routes", min_length=1, max_length=1024,
        description="where the operator controller's cmd/mode teach and repeat find routes: a route there is "
                    "named by a plain name (letters, digits, _ . -), never a path; ~ is the home directory, a "
                    "relative path is taken from the config file's folder")

    @field_validator("script")
    @classmethod
    def _drivable_script(cls, v: list[list[float]]) -> list[list[float]]:
        if not v:
            raise ValueError("the script has no segments")
        for i, seg in enumerate(v):
            if len(seg) != 3:
                raise ValueError(f"segment {i}: expected [linear, angular, seconds], got {seg}")
            if not all(math.isfinite(x) for x in seg):
                raise ValueError(f"segment {i}: expected finite numbers, got {seg}")
            if seg[2] <= 0:
                raise ValueError(f"segment {i}: expected seconds > 0, got {seg[2]}")
        return v

    @field_validator("routes_dir")
    @classmethod
    def _plain_dir(cls, v: str) -> str:
        if any(ord(c) < 32 for c in v):
            raise ValueError("contains control characters")
        return v


class Config(Strict):
    robot: RobotConfig = Field(default_factory=RobotConfig, description="the base: wheels and motion limits")
    camera: CameraConfig = Field(default_factory=CameraConfig, description="the camera: driver, intrinsics, mount")
    drive: DriveConfig = Field(default_factory=DriveConfig, description="the wheel motors: driver and wiring")
    loop: LoopConfig = Field(default_factory=LoopConfig, description="the fixed-rate control loop")
    safety: SafetyConfig = Field(default_factory=SafetyConfig, description="timeouts that stop the robot")
    sim: SimConfig = Field(default_factory=SimConfig, description="the simulated robot and world (drivers sim)")
    controller: ControllerConfig = Field(default_factory=ControllerConfig, description="the controller of 'vbnav run'")
    telemetry: TelemetryConfig = Field(default_factory=TelemetryConfig,
                                       description="zenoh telemetry and commands, see docs/telemetry.md")
    obstacles: ObstaclesConfig = Field(default_factory=ObstaclesConfig, description="stereo obstacle detection and "
                                       "stop zones (control/stages/obstacles.py)")
    vbc: VBCConfig = Field(default_factory=VBCConfig,
                           description="teach-and-repeat by vision-based control (control/stages/teach.py, repeat.py)")
    vslam: VslamNavConfig = Field(default_factory=VslamNavConfig,
                                  description="VSLAM on the robot and the goto controller (control/stages/vslam.py)")

    source: Optional[str] = Field(None, exclude=True, description="file this was loaded from")

    @model_validator(mode="after")
    def _speeds_reachable(self):
        r = self.robot
        if r.max_linear_speed > r.max_wheel_speed * r.wheel_radius + 1e-9:
            raise ValueError(f"robot.max_linear_speed {r.max_linear_speed} m/s exceeds what the wheels can do "
                             f"(max_wheel_speed * wheel_radius = {r.max_wheel_speed * r.wheel_radius:.3f} m/s)")
        turn = 2 * r.max_wheel_speed * r.wheel_radius / r.wheel_separation      # on the spot, wheels opposed
        if r.max_angular_speed > turn + 1e-9:
            if "max_angular_speed" in r.model_fields_set:
                raise ValueError(f"robot.max_angular_speed {r.max_angular_speed:g} rad/s exceeds what the wheels can "
                                 f"do (2 * max_wheel_speed * wheel_radius / wheel_separation = {turn:.3f} rad/s)")
            r.max_angular_speed = turn      # the default, cut to what is driven (and what config show prints)
        return self

    @model_validator(mode="after")
    def _inversion_only_on_real_motors(self):
        # The simulated drive has no motor mounted the other way to correct: flipping its wheels would
        # make the simulated robot drive backwards, and ignoring the flags would accept them for nothing.
        d = self.drive
        if d.driver == "sim" and (d.invert_left or d.invert_right):
            raise ValueError("drive.invert_left/invert_right correct a motor mounted the other way on a real "
                             "robot; drive.driver 'sim' has none (remove them, or choose the robot's driver)")
        return self

    @model_validator(mode="after")
    def _speeds_within_the_robots_limits(self):
        # A controller's speed written above the robot's limit was cut to it by the limiter without a word; the
        # defaults (not written) are cut as documented ("at most robot.max_linear_speed / max_angular_speed").
        r, goto = self.robot, self.vslam.goto
        limited = [("vbc", self.vbc, "cruise_speed", "max_linear_speed", "m/s"),
                   ("vslam.goto", goto, "cruise_speed", "max_linear_speed", "m/s"),
                   ("vslam.goto", goto, "final_turn_speed", "max_angular_speed", "rad/s")]
        if self.vslam.metric_scale == "odometry":       # the only scale that creeps (else refused when written)
            limited.append(("vslam.goto", goto, "init_creep_speed", "max_linear_speed", "m/s"))
        for where, section, name, limit_name, unit in limited:
            speed, limit = section.model_dump(include={name})[name], r.model_dump(include={limit_name})[limit_name]
            if speed <= limit:
                continue
            key = f"{where}.{name}"
            if name in section.model_fields_set:
                raise ValueError(f"{key} {speed:g} {unit} is above robot.{limit_name} {limit:g} {unit}: it would be "
                                 f"cut to {limit:g} {unit} (lower {key}, or raise the robot's limit)")
            # the default, cut here rather than at use: 'vbnav config show' prints the speed driven, and what
            # it prints loads back
            setattr(section, name, limit)
        # A proportional speed is held between a floor and a ceiling (kinematics.saturate, the ceiling wins): a
        # floor at or above its ceiling makes the speed the ceiling all along, and the gain never applies.
        # Crossed by a value written: the floor, or a ceiling other than the robot's limit (a default cut to the
        # limit, which 'config show' then prints, is no choice of the user's).
        for where, section, floor, ceiling, gain, limit in (
                ("vbc", self.vbc, "approach_min_speed", "cruise_speed", "approach_gain", r.max_linear_speed),
                ("vslam.goto", goto, "min_drive_speed", "cruise_speed", "k_rho", r.max_linear_speed),
                ("vslam.goto", goto, "final_turn_min_speed", "final_turn_speed", "final_turn_gain",
                 r.max_angular_speed)):
            values = section.model_dump(include={floor, ceiling})
            low, high = values[floor], values[ceiling]
            chosen = written(section, floor) or (written(section, ceiling) and high != limit)
            if low >= high and chosen:
                raise ValueError(f"{where}.{floor} {low:g} is not below {where}.{ceiling} {high:g}: {where}.{gain} "
                                 f"would never apply (the speed held at {ceiling} all along); lower {where}.{floor}")
        return self

    @model_validator(mode="after")
    def _state_rate_within_the_loop_rate(self):
        # A state is published from a loop cycle: at most one per cycle. A rate written above the loop's was sent
        # at the loop's rate without a word; the default is cut to it (what is sent, and what show prints).
        t, loop_hz = self.telemetry, self.loop.rate_hz
        if t.state_rate_hz > loop_hz:
            if "state_rate_hz" in t.model_fields_set:
                raise ValueError(f"telemetry.state_rate_hz {t.state_rate_hz:g} Hz is above loop.rate_hz {loop_hz:g} Hz: "
                                 f"a state is sent from a cycle, at most one per cycle (lower telemetry.state_rate_hz)")
            t.state_rate_hz = loop_hz
        return self

    @model_validator(mode="after")
    def _camera_rate_within_the_loop_rate(self):
        # On the simulated clock the loop reads the camera once a cycle and the newest due frame wins: a rate
        # written above the loop's dropped the frames in between without a word; the default is cut to it (what
        # is rendered, and what show prints). In real time the vision thread reads every frame.
        c, loop_hz = self.camera, self.loop.rate_hz
        if self.on_simulated_clock() and c.rate_hz > loop_hz:
            if "rate_hz" in c.model_fields_set:
                raise ValueError(f"camera.rate_hz {c.rate_hz:g} Hz is above loop.rate_hz {loop_hz:g} Hz on the "
                                 f"simulated clock: the loop reads the simulated camera once a cycle, the frames in "
                                 f"between would be dropped (lower camera.rate_hz, or raise loop.rate_hz)")
            c.rate_hz = loop_hz
        return self

    def on_simulated_clock(self) -> bool:
        """The simulated clock runs when everything is simulated and real time is not asked for."""
        return self.drive.driver == "sim" and self.camera.driver == "sim" and not self.sim.realtime

    @model_validator(mode="after")
    def _scripted_teacher_only_in_simulation(self):
        # A scripted loop through a room the robot cannot see is never what real motors should drive.
        # (an unknown driver is not a real drive: validate_driver_options names it as unknown)
        if self.controller.teach == "room_loop" and self.drive.driver != "sim" and self.drive.driver in registry.DRIVES:
            raise ValueError(f"controller.teach 'room_loop' drives the simulated room's loop; drive.driver "
                             f"{self.drive.driver!r} is a real drive (use teach: teleop)")
        if self.controller.teach == "room_loop" and self.sim.world not in ROOM_WORLDS:
            raise ValueError(f"controller.teach 'room_loop' drives the simulated room's 7 m x 4 m loop; sim.world "
                             f"{self.sim.world!r} has no room for it (use sim.world {' or '.join(ROOM_WORLDS)})")
        return self


def validate_driver_options(cfg: Config, source: str = "<config>") -> dict[str, Any]:
    """Validate camera.options and drive.options against the chosen drivers' Options models.

    Returns {"camera": options_model, "drive": options_model}.
    """
    out = {}
    for section, table in (("camera", registry.CAMERAS), ("drive", registry.DRIVES)):
        sec = getattr(cfg, section)     # the section named in the loop above (a field access by name)
        if sec.driver not in table:
            raise ConfigError(f"{source}: {section}.driver: unknown driver {sec.driver!r}; "
                              f"expected one of {', '.join(sorted(table))}")
        try:
            cls = registry.load(table, sec.driver)
        except registry.DriverNotAvailable as exc:
            raise ConfigError(f"{source}: {section}.driver: {exc}") from exc
        # A driver class states its settings as a pydantic ``Options`` model, or takes none (no model).
        options_model = getattr(cls, "Options", None)
        if options_model is None:
            out[section] = sec.options
            continue
        try:
            out[section] = options_model.model_validate(sec.options)
        except ValidationError as exc:
            raise ConfigError(format_errors(source, exc, prefix=f"{section}.options")) from None
    return out


def parse_config(data: Any, source: str = "<config>") -> Config:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of sections at the top level, got {type(data).__name__}")
    if "source" in data:        # the field records the file loaded; a key in the file would be overwritten
        raise ConfigError(f"{source}: source: unknown key (check the spelling; see docs/configuration.md or "
                          f"'vbnav config reference')")
    try:
        cfg = Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_errors(source, exc)) from None
    cfg.source = source
    camera_options = validate_driver_options(cfg, source)["camera"]
    _refuse(source, camera_rate_not_read(cfg, camera_options), simulated_latency_not_read(cfg),
            simulated_camera_settings_not_read(cfg))
    check_image_rate(cfg, camera_options, source)
    check_stale_limit(cfg, camera_options, source)
    apply_calibration_file(cfg, source)
    check_image_width(cfg, source)
    check_obstacle_baseline(cfg, source)
    refusal = cfg.camera.rectified_refusal("obstacles.enabled: the obstacle stage", "rectify the pair first, e.g. "
                                           "with a stereo calibration file") if cfg.obstacles.enabled else ""
    if refusal:
        raise ConfigError(f"{source}: {refusal}")
    no_pair = no_right_image(cfg) if cfg.obstacles.enabled and cfg.obstacles.source == "sgbm" else ""
    if no_pair:
        raise ConfigError(f"{source}: obstacles.source: sgbm matches the frames' stereo pair, and {no_pair}: "
                          f"set source: auto or disparity for a camera's own disparity, or use a stereo camera")
    blind = no_disparity(cfg, camera_options) if cfg.obstacles.enabled and cfg.obstacles.source != "sgbm" else ""
    if blind:
        raise ConfigError(f"{source}: obstacles.enabled: the obstacle stage (source {cfg.obstacles.source}) needs a "
                          f"disparity or a stereo pair in every frame, and {blind}: every frame would be blind and the "
                          f"robot held for good (use a stereo camera, or set obstacles.enabled: false)")
    _refuse(source, sgbm_settings_not_read(cfg), sgbm_reach_problem(cfg))
    check_stand_still(cfg, source)
    check_turn_when_held(cfg, source)
    return cfg


def _refuse(source: str, *problems: str) -> None:
    """ConfigError for the first problem found ("" is none), naming the file."""
    for why in problems:
        if why:
            raise ConfigError(f"{source}: {why}")


def camera_rate_not_read(cfg: Config, options) -> str:
    """Why ``camera.rate_hz`` written (other than its default) is never read by the configured camera, "" when
    it is: the replay camera plays at the recorded times (or its options.rate_hz, a folder without times at
    10 Hz), the OAK's host-only replay at its options.replay_fps."""
    c = cfg.camera
    if not written(c, "rate_hz"):
        return ""
    if c.driver == "replay":
        instead = "camera.options.rate_hz (default: the recorded times, a folder of images 10 Hz)"
    elif c.driver == "oak" and options.replay_file is not None:
        instead = "camera.options.replay_fps"
    else:
        return ""
    return (f"camera.rate_hz {c.rate_hz:g} Hz: the {c.driver} camera does not read it (a recording plays at its "
            f"own rate); set the rate with {instead}, and remove camera.rate_hz")


def camera_frame_rate(cfg: Config, options) -> Optional[tuple[float, str]]:
    """(frames per second, the setting that gives it) of the configured camera, or None where only the
    recording knows its rate (the replay camera, a V4L2 video file). ``options``: the camera's validated ones."""
    c = cfg.camera
    if c.driver == "oak" and options.replay_file is not None:
        return options.replay_fps, "camera.options.replay_fps"
    if c.driver in ("sim", "oak") or (c.driver == "v4l2" and not options.plays_a_file()):
        return c.rate_hz, "camera.rate_hz"
    return None


def check_image_rate(cfg: Config, options, source: str) -> None:
    """An image is sent from a camera frame, at most one a frame: telemetry.image_rate_hz written above the
    camera's frame rate is refused (it was sent at the frame rate without a word); the default is cut to it
    (what is sent, and what 'vbnav config show' prints)."""
    t, known = cfg.telemetry, camera_frame_rate(cfg, options)
    if known is None or t.image_rate_hz <= known[0]:
        return
    rate, field = known
    if "image_rate_hz" in t.model_fields_set:
        raise ConfigError(f"{source}: telemetry.image_rate_hz {t.image_rate_hz:g} Hz is above {field} {rate:g} Hz: "
                          f"an image is sent from a camera frame, at most one a frame (lower telemetry.image_rate_hz)")
    t.image_rate_hz = rate


def check_stale_limit(cfg: Config, options, source: str) -> None:
    """camera.stale_after_s or safety.estimate_timeout_s at or below the time a frame (and the estimates the stages
    make of it, one a frame) may age before the next one comes (the frame period, plus the simulated vision latency
    on the simulated clock) makes every frame or estimate stale before the next: the robot would be held for
    good. Refused where the configuration gives the frame rate."""
    known = camera_frame_rate(cfg, options)
    if known is None:
        return
    rate, field = known
    c, s = cfg.camera, cfg.sim
    latency = s.vision_latency_s if cfg.on_simulated_clock() else 0.0        # the latency is added there
    bound = 1.0 / rate + latency

    def secs(x: float) -> str:
        return f"{x:.3f}".rstrip("0").rstrip(".")
    for key, limit, what in (("camera.stale_after_s", c.stale_after_s, "frame"),
                             ("safety.estimate_timeout_s", cfg.safety.estimate_timeout_s, "estimate")):
        if limit > bound:
            continue
        raise ConfigError(f"{source}: {key} {limit:g} s is not above the time a frame may age before the next one "
                          f"comes, {secs(bound)} s (the frame period {secs(1.0 / rate)} s at {field} {rate:g} Hz"
                          + (f", plus sim.vision_latency_s {latency:g} s" if latency else "") + f"): every {what} "
                          f"would go stale before the next and the robot be held for good (raise {key})")


def check_image_width(cfg: Config, source: str) -> None:
    """JPEG frames are scaled down to telemetry.image_width, never up: one written above the camera's width (its
    calibration file's, when it has one) is refused; the default is cut to a narrower camera's width."""
    t, width = cfg.telemetry, cfg.camera.width
    if t.image_width <= width:
        return
    if "image_width" in t.model_fields_set:
        raise ConfigError(f"{source}: telemetry.image_width {t.image_width} px is above camera.width {width} px: "
                          f"images are scaled down to it, never up (lower telemetry.image_width)")
    t.image_width = width


def simulated_latency_not_read(cfg: Config) -> str:
    """Why ``sim.vision_latency_s`` written (other than its default) is never read, "" when it is: the simulated
    latency is added to the estimates on the simulated clock only; on the wall clock (sim.realtime, or a camera
    that is not simulated) the vision thread's own time is the latency. With a real drive the simulator is off
    and its section kept, unread, as a feature switched off."""
    s = cfg.sim
    if cfg.drive.driver != "sim" or not written(s, "vision_latency_s"):
        return ""
    if cfg.camera.driver != "sim":
        why = f"camera.driver {cfg.camera.driver}"
    elif s.realtime:
        why = "sim.realtime: true"
    else:
        return ""
    return (f"sim.vision_latency_s {s.vision_latency_s:g} s: the simulated latency is added on the simulated clock "
            f"only, and {why} runs the robot on the wall clock, where the vision thread's own time is the latency "
            f"(remove sim.vision_latency_s)")


def simulated_camera_settings_not_read(cfg: Config) -> str:
    """Why a ``sim`` setting of the simulated camera written (other than its default) is never read, "" when
    none is: with the simulated drive and another camera (control/runtime/factory.py make_robot) no world is
    built (``sim.world``: the simulated camera renders it), no simulated image is made (``sim.image_noise_std``)
    and the robot runs on the wall clock whatever ``sim.realtime`` says (the simulated clock needs both drivers
    simulated). The drive's settings (``seed``, the motor, encoder and slip ones, ``start_pose``) are read by
    the simulated drive. With a real drive the whole section is kept, unread, as a feature switched off."""
    s, camera = cfg.sim, cfg.camera.driver
    if cfg.drive.driver != "sim" or camera == "sim":
        return ""
    if written(s, "world"):
        return (f"sim.world {s.world!r}: the simulated world is built only for the simulated camera to film, and "
                f"camera.driver {camera} films the real one (remove sim.world)")
    if written(s, "image_noise_std"):
        return (f"sim.image_noise_std {s.image_noise_std:g}: the simulated camera adds the image noise to the images "
                f"it renders, and camera.driver {camera} gives real images (remove sim.image_noise_std)")
    if written(s, "realtime"):
        return (f"sim.realtime: true: the simulated clock runs only when the drive and the camera are both "
                f"simulated, and camera.driver {camera} runs the robot on the wall clock anyway (remove "
                f"sim.realtime)")
    return ""


#: Camera drivers whose frames carry their own disparity whenever they could carry a right image, so that the
#: obstacle stage's ``source: auto`` (the frame's disparity if present, else SGBM on its pair) never runs SGBM:
#: the simulated stereo camera sends its true disparity with every right image, the OAK its own with every image.
OWN_DISPARITY_CAMERAS = {"sim": "the simulated stereo camera sends its true disparity with every right image",
                         "oak": "the OAK sends its own disparity with every image (and its right image only with "
                                "camera.options.right_image)"}


def sgbm_settings_not_read(cfg: Config) -> str:
    """Why ``obstacles.sgbm_*`` written (other than its default) is never read, "" when it is or may be: with
    ``obstacles.source: auto`` the stage takes the frame's own disparity when it has one and runs SGBM only on a
    frame with a right image and no disparity (ObstacleStage._sgbm_pair), which the simulated camera and the
    OAK never give. (``source: disparity`` beside them is refused in the section itself; a switched-off
    obstacle stage keeps them.)"""
    o, camera = cfg.obstacles, cfg.camera.driver
    if not o.enabled or o.source != "auto" or camera not in OWN_DISPARITY_CAMERAS:
        return ""
    unused = [k for k in ("sgbm_block_size", "sgbm_near_margin") if written(o, k)]
    if not unused:
        return ""
    keys = " and ".join(f"obstacles.{k}" for k in unused)
    instead = ", or set obstacles.source: sgbm to match the pair with SGBM" if camera == "sim" else ""
    return (f"{keys} {'set' if len(unused) > 1 else 'sets'} the stereo matching (SGBM), which obstacles.source: "
            f"auto never runs with camera.driver {camera}: {OWN_DISPARITY_CAMERAS[camera]}, and auto takes the "
            f"frame's own disparity; remove {' and '.join(unused)}{instead}")


#: Camera drivers whose frames carry no right image (the OAK's only with camera.options.right_image).
ONE_IMAGE_CAMERAS = ("v4l2", "oak")


def no_right_image(cfg: Config) -> str:
    """Why the configured camera's frames carry no right image of a stereo pair, "" when they do or may (a
    replayed recording has one when its folder does; an OAK with ``camera.options.right_image``, which its
    Options allow only with its stereo node's mono pair)."""
    c = cfg.camera
    if c.driver == "oak" and c.options.get("right_image") is True:
        return ""
    if c.driver in ONE_IMAGE_CAMERAS:
        oak = " (set camera.options.right_image: true for the OAK's rectified pair)" if c.driver == "oak" else ""
        return f"camera.driver {c.driver} gives one image per frame, no right image{oak}"
    if c.driver == "sim" and not c.stereo_baseline():
        return ("the simulated camera renders a right image only with a stereo baseline (camera.options."
                "stereo_baseline or a stereo camera.calibration_file), and it has none")
    return ""


def no_disparity(cfg: Config, options) -> str:
    """Why the configured camera's frames carry neither a disparity nor a right image, "" when they do or may
    (a replayed recording has a right image when its folder does). ``options``: the camera's validated options."""
    c = cfg.camera
    if c.driver == "oak" and options.replay_file is not None:
        return "camera.options.replay_file replays images only (no disparity, no right image)"
    if c.driver == "oak" and not options.disparity:
        return "camera.options.disparity: false turns the OAK's disparity off (and it gives no right image)"
    return no_right_image(cfg) if c.driver != "oak" else ""


def calibration_path(cfg: Config, source: str) -> Optional[Path]:
    """``camera.calibration_file`` as a path: ~ expanded, relative to the config file's folder."""
    f = cfg.camera.calibration_file
    if not f:
        return None
    p = Path(f).expanduser()
    if not p.is_absolute() and source and not source.startswith("<"):
        p = Path(source).resolve().parent / p
    return p


# Two stereo baselines for one rig that differ by more than this share: two different rigs in one config.
BASELINE_AGREEMENT = 0.01


def check_obstacle_baseline(cfg: Config, source: str) -> None:
    """Refuse ``obstacles.baseline`` beside another ``camera.options.stereo_baseline``: one rig, two baselines
    (the obstacle stage would use the first, the VSLAM and the line map the second). A calibration file's
    baseline is compared with both in ``apply_calibration_file``."""
    mine, cam = cfg.obstacles.baseline, (cfg.camera.options or {}).get("stereo_baseline")
    if mine and cam and abs(float(mine) - float(cam)) > BASELINE_AGREEMENT * float(cam):
        raise ConfigError(f"{source}: obstacles.baseline {float(mine):g} m, camera.options.stereo_baseline "
                          f"{float(cam):g} m: two stereo baselines for one rig (the obstacle stage would use the first, "
                          f"the VSLAM and the line map the second); remove obstacles.baseline")


def check_stand_still(cfg: Config, source: str) -> None:
    """Refuse a stop band whose ``min_distance`` lies nearer than where the camera's view of the floor under
    the band begins: the speed falls with the nearest obstacle seen in the band, and a step down or a low
    obstacle passes out of view there, its distance then read from what lies beyond it; the robot would drive
    on into it (docs/obstacles.md, 'A stop band that follows the speed')."""
    if not cfg.obstacles.enabled or not any(z.min_distance is not None for z in cfg.obstacles.zones):
        return
    from vbnav.control.stages.obstacles import nearest_floor_ahead
    camera, mount = cfg.camera.to_model(), cfg.camera.mount.to_mount()
    for i, z in enumerate(cfg.obstacles.zones):
        if z.min_distance is None:
            continue
        seen_from = nearest_floor_ahead(camera, mount, z.half_width)
        if not math.isfinite(seen_from):
            raise ConfigError(f"{source}: obstacles.zones.{i}: min_distance {z.min_distance:g} m: the camera does not "
                              f"see the floor under the whole band (|x| <= {z.half_width:g} m) within 5 m, so no "
                              f"stand-still distance can be checked against its view; remove min_distance")
        if z.min_distance < seen_from:
            raise ConfigError(f"{source}: obstacles.zones.{i}: min_distance {z.min_distance:g} m is nearer than the "
                              f"camera's view of the floor under the band, which begins {seen_from:.3f} m ahead of the "
                              f"axle (the camera's intrinsics and camera.mount); a step down or a "
                              f"low obstacle nearer than that is out of view: set min_distance >= {seen_from:.2f}")


def sgbm_reach_problem(cfg: Config) -> str:
    """Why the obstacle stage's stereo matching cannot cover what ``obstacles.sgbm_near_margin`` asks, "" when
    it can: depths down to that share of the nearest floor in view (the camera's intrinsics and mount), which
    on a steep camera or a wide baseline needs more than the 256 disparities SGBM searches. The stage cut it
    to 256 without a word, and obstacles standing nearer went unmatched. Only where SGBM runs (not on a
    camera that gives its own disparity) and the baseline is configured."""
    from vbnav.vision.stereo import MAX_SGBM_DISPARITIES, StereoRig, nearest_floor_m, sgbm_disparities_for
    o, c = cfg.obstacles, cfg.camera
    baseline = o.baseline or c.stereo_baseline()
    if not o.enabled or o.source == "disparity" or not baseline:
        return ""
    if o.source == "auto" and c.driver in OWN_DISPARITY_CAMERAS:
        return ""
    rig = StereoRig(PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy), float(baseline))
    mount = c.mount.to_mount()
    floor = nearest_floor_m(rig, mount.height, mount.pitch)
    depth = o.sgbm_near_margin * floor
    need = sgbm_disparities_for(rig, depth)
    if need <= MAX_SGBM_DISPARITIES:
        return ""
    reach = rig.fb / MAX_SGBM_DISPARITIES
    fix = (f"set sgbm_near_margin to at least {math.ceil(100 * reach / floor) / 100:.2f} to accept that, or pitch "
           f"the camera up" if reach <= floor else
           "not even the nearest floor is reached: pitch the camera up, or use a camera with a shorter baseline")
    return (f"obstacles.sgbm_near_margin {o.sgbm_near_margin:g}: stereo matching should cover depths down to "
            f"{o.sgbm_near_margin:g} x the nearest floor in view ({floor:.3g} m, camera.mount and the intrinsics) "
            f"= {depth:.3g} m, which needs {need} disparities (fx B {rig.fb:.3g} px m); SGBM searches at most "
            f"{MAX_SGBM_DISPARITIES}, down to {reach:.3g} m: {fix}")


def check_turn_when_held(cfg: Config, source: str) -> None:
    """Refuse ``obstacles.turn_when_held`` for a robot not declared round: turning on the spot, a robot sweeps
    the circle through its farthest point about the axle centre, and the stop zones watch only the floor ahead;
    a round robot's circle is its own footprint (docs/obstacles.md, 'Turning on the spot while held')."""
    if cfg.obstacles.enabled and cfg.obstacles.turn_when_held and cfg.robot.footprint_radius is None:
        raise ConfigError(f"{source}: obstacles.turn_when_held lets a robot held by an obstacle turn on the spot, "
                          f"which sweeps no new floor only for a round robot; set robot.footprint_radius (m: its "
                          f"outline lies within it about the axle centre) or remove turn_when_held")


def apply_calibration_file(cfg: Config, source: str) -> None:
    """Load ``camera.calibration_file`` and let it replace the inline model, size, intrinsics and distortion
    (every later reader of ``cfg.camera`` sees the calibrated camera). Errors name the config and the file."""
    p = calibration_path(cfg, source)
    if p is None:
        return
    c = cfg.camera
    where = f"{source}: camera.calibration_file"
    try:
        cal = load_camera_calibration(p, c.width, c.height)
    except CalibrationError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    cam = cal.camera
    size, inline = (int(cam.width), int(cam.height)), (c.width, c.height)
    if size != inline and {"width", "height"} & c.model_fields_set:
        raise ConfigError(f"{where}: {p} is a calibration of {size[0]}x{size[1]} images, camera.width/height say "
                          f"{inline[0]}x{inline[1]} (remove them or calibrate at that size)")
    for name, other in (("camera.options.stereo_baseline", (c.options or {}).get("stereo_baseline")),
                        ("obstacles.baseline", cfg.obstacles.baseline)):
        if cal.baseline and other and abs(float(other) - cal.baseline) > BASELINE_AGREEMENT * cal.baseline:
            raise ConfigError(f"{where}: {p} gives a stereo baseline of {cal.baseline:.4f} m, {name} says "
                              f"{float(other):.4f} m (remove {name}: the calibration is the rig)")
    if cal.disparity_scale is not None:
        raise ConfigError(f"{where}: {p} sets disparity_scale {cal.disparity_scale:g}, the scale of a stored integer "
                          f"disparity image, which only the offline 'vbnav obstacles --disparity' reads; a camera gives "
                          f"its disparity in px (remove it, or give vbnav obstacles a copy of the file with it)")
    data = c.model_dump()
    data.update(model="fisheye" if isinstance(cam, FisheyeCamera) else "pinhole", width=size[0], height=size[1],
                fx=float(cam.fx), fy=float(cam.fy), cx=float(cam.cx), cy=float(cam.cy),
                distortion=[float(d) for d in cam.dist])
    if cal.mount is not None:
        # the file's mounting replaces camera.mount's height, pitch and roll, as its intrinsics replace the inline
        # ones; a camera.mount that gives other values is a second mounting for one camera
        fields = ("height", "pitch_deg", "roll_deg")
        given = c.mount.model_fields_set if "mount" in c.model_fields_set else set()
        inline = [data["mount"][f] for f in fields]
        if any(f in given and abs(a - b) > 1e-9 for f, a, b in zip(fields, inline, cal.mount)):
            def say(values):
                return f"height {values[0]:g} m, pitch_deg {values[1]:g}, roll_deg {values[2]:g}"
            raise ConfigError(f"{where}: {p} gives mount {say(cal.mount)}; camera.mount says {say(inline)} (remove "
                              f"one of them: the camera has one mounting)")
        data["mount"] = {**data["mount"], **dict(zip(fields, cal.mount))}
    try:
        calibrated = CameraConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_errors(f"{where} {p}", exc, prefix="camera")) from None
    calibrated._calibration = cal
    cfg.camera = calibrated


def resolve_config_path(path: str | Path | None) -> Path:
    """A config path as given, or the name of a file in configs/ ('sim' -> configs/sim.yaml)."""
    if path is None:
        return CONFIG_DIR / "sim.yaml"
    p = Path(path)
    if not p.exists() and not p.suffix and (CONFIG_DIR / f"{p}.yaml").exists():
        return CONFIG_DIR / f"{p}.yaml"
    return p


def load_config(path: str | Path | None = None, overrides: Optional[dict] = None) -> Config:
    """Load and validate a YAML config. ``overrides`` is merged (deep) on top."""
    p = resolve_config_path(path)
    if not p.exists():
        raise ConfigError(f"{p}: config file not found (give --config FILE, or a name from {CONFIG_DIR})")
    if p.is_dir():
        raise ConfigError(f"{p}: is a directory, expected a YAML config file")
    try:
        data = load_yaml(p.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: {yaml_problem(exc)}") from None
    if overrides:
        data = deep_merge(data or {}, overrides)
    return parse_config(data, str(p))


def deep_merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out
