"""The README's bring-up ("On a real robot", between the ``bring-up`` markers), run line by line as written.

Each line of the section's ``sh`` blocks goes through bash in a fresh folder (``configs/`` linked in, as in
the repository folder), with ``vbnav`` on PATH. What stands in for the hardware:

- the serial port: ``$PORT`` is the stable link of a Dynamixel emulator (``vbnav emulate dynamixel --link``).
  It starts as one factory-new XL430 (id 1 at 57600 bit/s), so the README's set-id/set-baud really happen;
  at the README's comments that say which servos are on the bus, the emulator is restarted with those
  servos, as the user plugs them in by hand;
- the camera: after the README's ``sed`` has put ``$CAMERA`` into the copied config, the V4L2 camera section
  is replaced by a replay camera over frames rendered by the simulator with the calibration the README's
  ``calibrate intrinsics`` produced (a user with a V4L2 camera keeps ``driver: v4l2`` and ``device``);
- the photos: ``board_views/`` holds OpenCV's chessboard samples (../shared/data/calib_chessboard) and
  ``board_on_floor.png`` is a board rendered on the floor from a known camera height, pitch and roll;
- a test beside others: the robot listens on a free port (``--connect`` added to send/monitor), runs with
  normal scheduling and does not end on missed deadlines on a loaded machine.

Lines marked "terminal 1" run in the background until the test presses Ctrl-C (SIGINT), after the
"terminal 2" lines that follow them.
"""
from __future__ import annotations

import math
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BEGIN, END = "<!-- bring-up: begin -->", "<!-- bring-up: end -->"
VBNAV = [sys.executable, "-m", "vbnav.control.cli"]

# The README's comments where the user plugs servos in by hand, and the bus the emulator then stands for.
BUS_CHANGES = {
    "# the left wheel's servo alone on the bus (it keeps id 1):": ("--ids", "1", "--baud", "57600"),
    "# both servos on the bus:": ("--ids", "1,2", "--baud", "1000000"),
}
FLOOR_MOUNT = dict(height=0.19, pitch_deg=12.0, roll_deg=1.5)     # the camera that took board_on_floor.png
FRAMES = 60                # replayed at 10 Hz, looped: 6 s of a drive 0.6 m along the simulated room


def readme_lines() -> list[str]:
    """The lines of the ```sh blocks between the bring-up markers (blank lines left out)."""
    text = README.read_text()
    assert BEGIN in text and END in text, f"README.md: the {BEGIN} ... {END} markers are gone"
    section = text[text.index(BEGIN):text.index(END)]
    blocks = re.findall(r"```sh\n(.*?)```", section, re.S)
    return [ln.strip() for b in blocks for ln in b.splitlines() if ln.strip()]


def command_of(line: str) -> str:
    """The line without its trailing comment (the README's comments start with two spaces and #)."""
    return re.split(r"\s{2,}#", line, maxsplit=1)[0].strip()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening(port: int) -> bool:
    """Something listens on the TCP port (from /proc: a probing connection would stall zenoh's accept)."""
    rows = [ln.split() for ln in Path("/proc/net/tcp").read_text().splitlines()[1:]]
    return any(r[1].endswith(f":{port:04X}") and r[3] == "0A" for r in rows)


def ctrl_c(proc: subprocess.Popen, timeout_s: float) -> None:
    """SIGINT, as Ctrl-C in its terminal; killed if it has not ended within ``timeout_s``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class Emulator:
    """``vbnav emulate dynamixel`` on ``link``, restartable with another bus (the user plugging servos)."""

    def __init__(self, link: Path):
        self.link, self.proc = link, None

    def start(self, *bus: str) -> None:
        self.stop()
        self.starts = getattr(self, "starts", 0) + 1
        out, err = (self.link.with_name(f"emulator{self.starts}{s}") for s in (".out", ".err"))
        with open(out, "w") as o, open(err, "w") as e:
            self.proc = subprocess.Popen(VBNAV + ["emulate", "dynamixel", *bus, "-v", "--link", str(self.link)],
                                         stdout=o, stderr=e)
        deadline = time.monotonic() + 30
        while not out.read_text().endswith("\n"):      # the device path: it serves from now on
            assert self.proc.poll() is None and time.monotonic() < deadline, err.read_text()
            time.sleep(0.05)
        assert out.read_text().strip() == str(self.link)

    def stop(self) -> None:
        if self.proc is not None:
            ctrl_c(self.proc, 10)
        self.proc = None


def distorted(image: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """An ideal pinhole image as the calibrated (distorting) camera sees it: each pixel samples the ideal
    image where its undistorted ray goes."""
    h, w = image.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)), -1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(grid, K, dist, P=K).reshape(h, w, 2)
    return cv2.remap(image, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR, borderValue=110)


def take_photos_and_frames(work: Path) -> None:
    """What the user's camera would give once calibrated: the board on the floor and a drive's frames."""
    from test_calibrate_cli import render_floor_board

    from vbnav.drivers.calibration import load_calibration
    from vbnav.drivers.clock import SimClock
    from vbnav.drivers.sim.camera import SimCamera
    from vbnav.drivers.sim.world import World
    from vbnav.vision.geometry import CameraMount, Pose2

    model = load_calibration(work / "calib" / "camera_info.yaml")
    K = np.array([[model.fx, 0, model.cx], [0, model.fy, model.cy], [0, 0, 1]])
    dist = np.asarray(model.dist, float)
    floor = CameraMount(height=FLOOR_MOUNT["height"], forward=0.05, pitch=math.radians(FLOOR_MOUNT["pitch_deg"]),
                        roll=math.radians(FLOOR_MOUNT["roll_deg"]))
    board = render_floor_board(K, floor, (model.width, model.height), square=0.025, ahead=0.45)
    cv2.imwrite(str(work / "board_on_floor.png"), distorted(board, K, dist))
    frames = work / "frames"
    frames.mkdir()
    cam = SimCamera(World.by_name("room", 0), model, CameraMount(height=0.19, forward=0.05,
                    pitch=math.radians(5.0)), lambda: Pose2(0, 0, 0), SimClock(), 10, noise_std=1.0)
    for k in range(FRAMES):
        frame = cam.render_frame(Pose2(-3.5, 0.01 * k, 0.0))      # the room loop's start, 0.1 m/s
        cv2.imwrite(str(frames / f"{k:04d}.png"), frame.image)


def replace_once(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"myrobot.yaml: expected one {old!r}"
    return text.replace(old, new)


def stand_in_camera_and_test_settings(config: Path, camera: str, frames: Path, port: int) -> None:
    """The test's edits of the README's config: the replay camera for the V4L2 one, a free port, and the
    settings of a test on a loaded machine."""
    text = config.read_text()
    assert f"device: {camera} " in text, "the README's sed did not put $CAMERA into camera.options.device"
    text = replace_once(text, "driver: v4l2", "driver: replay")
    text = replace_once(text, "\n  rate_hz: 30\n", "\n")   # the replay camera plays the folder at 10 Hz
    text = re.sub(r"    device: .*\n    fourcc: MJPG\n", f"    path: {frames}\n    loop: true\n", text)
    assert f"path: {frames}" in text, "myrobot.yaml: the V4L2 camera options are not where they were"
    text = replace_once(text, "realtime_priority: 50", "realtime_priority: 0")
    text = replace_once(text, "max_missed_streak: 5", "max_missed_streak: 1000000\n  stall_periods: 1000000")
    # the emulator (a Python process) shares two loaded cores with the test and other suites, and its answers
    # came 7+ ms late for 0.3 s at a time: the widest answer window (a late answer costs a loop period, which
    # this test tolerates), and no fault for missed reads within 0.3 s (the emulated servos' watchdog 0.5 s)
    text = re.sub(r"margin_ms: [0-9.]+", "margin_ms: 20.0", text)
    text = re.sub(r"bus_watchdog_s: [0-9.]+", "bus_watchdog_s: 0.5", text)
    text = re.sub(r"\n    max_missed_reads: .*", "", text)
    text = text.replace("    margin_ms: 20.0", "    max_missed_reads: 30\n    margin_ms: 20.0")
    config.write_text(text + f"\ntelemetry:\n  listen: [tcp/127.0.0.1:{port}]\n")


class Terminal1:
    """A README command that runs until Ctrl-C, in the background; its output in files."""

    def __init__(self, command: str, run: str, env: dict, cwd: Path, n: int):
        """``command``: the README's; ``run``: what runs (the same, or its stand-in)."""
        self.command, self.out, self.err = command, cwd / f"t1-{n}.out", cwd / f"t1-{n}.err"
        with open(self.out, "w") as o, open(self.err, "w") as e:
            self.proc = subprocess.Popen(["bash", "-c", f"exec {run}"], cwd=cwd, env=env, stdout=o, stderr=e)

    def wait_ready(self, port: int, timeout=30.0) -> None:
        """Until the robot's loop runs (its first progress line) and it listens, as the user waits before
        driving."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.proc.poll() is None:
            if re.search(r"\bt=", self.err.read_text()) and listening(port):
                return
            time.sleep(0.2)
        raise AssertionError(f"{self.command}: not running ({self.proc.poll()}):\n{self.err.read_text()}")

    def ctrl_c(self) -> subprocess.CompletedProcess:
        ctrl_c(self.proc, 30)
        return subprocess.CompletedProcess(self.command, self.proc.returncode, self.out.read_text(),
                                           self.err.read_text())


@pytest.fixture(scope="module")
def bringup(tmp_path_factory, shared_data):
    """Every README line run in order: {command: CompletedProcess}, and the folder they ran in."""
    work = tmp_path_factory.mktemp("readme")
    (work / "configs").symlink_to(ROOT / "configs")
    (work / "board_views").mkdir()
    for f in sorted((shared_data / "calib_chessboard" / "stereo").glob("left*.jpg")):
        (work / "board_views" / f.name).symlink_to(f)
    bindir = work / "bin"
    bindir.mkdir()
    (bindir / "vbnav").write_text(f"#!/bin/sh\nexec {shlex.join(VBNAV)} \"$@\"\n")
    (bindir / "vbnav").chmod(0o755)
    values = {"PORT": str(work / "usb-FTDI_emulated-if00-port0"), "CAMERA": "/dev/v4l/by-id/usb-emulated-video-index0"}
    env = dict(os.environ, PATH=f"{bindir}:{os.environ['PATH']}", **values)
    net = free_port()
    emulator = Emulator(Path(values["PORT"]))
    emulator.start("--ids", "1", "--baud", "57600")          # a factory-new XL430, the right wheel's
    results, seen_vars, background, bus_changes, hooks = {}, set(), None, dict(BUS_CHANGES), set()
    try:
        for n, line in enumerate(readme_lines()):
            if line.startswith("#"):
                if line in bus_changes:
                    emulator.start(*bus_changes.pop(line))
                continue
            command = command_of(line)
            var = re.fullmatch(r"([A-Z_]+)=\S+", command)
            if var:                                            # what differs per robot: the test's values
                assert var.group(1) in values, f"README sets {var.group(1)}, which the test does not provide"
                seen_vars.add(var.group(1))
                continue
            run = command
            if re.match(r"vbnav (send|monitor|teleop)\b", run):
                run += f" --connect tcp/127.0.0.1:{net}"
            if "terminal 2" not in line and background is not None:
                results[background.command] = background.ctrl_c()
                background = None
            if "terminal 1" in line:
                background = Terminal1(command, run, env, work, n)
                background.wait_ready(net)
                continue
            results[command] = subprocess.run(["bash", "-c", run], cwd=work, env=env, capture_output=True,
                                              text=True, timeout=120)
            assert results[command].returncode == 0, f"README line failed: {line}\n{results[command].stderr}"
            if "$CAMERA" in command and "myrobot.yaml" in command:       # the config has the user's camera
                stand_in_camera_and_test_settings(work / "myrobot.yaml", values["CAMERA"], work / "frames", net)
                hooks.add("camera")
            if command.startswith("vbnav calibrate intrinsics"):
                take_photos_and_frames(work)
                hooks.add("photos")
        if background is not None:
            results[background.command] = background.ctrl_c()
    finally:
        if background is not None and background.proc.poll() is None:
            background.proc.kill()
        emulator.stop()
    assert seen_vars == set(values), f"README no longer sets {set(values) - seen_vars}"
    assert not bus_changes, f"README no longer has the comments {list(bus_changes)}"
    assert hooks == {"camera", "photos"}, f"README: no line puts $CAMERA into myrobot.yaml or calibrates ({hooks})"
    return results, work


def results_for(bringup, prefix: str) -> list[subprocess.CompletedProcess]:
    """What the README lines starting with ``prefix`` gave, in order."""
    found = [r for c, r in bringup[0].items() if c.startswith(prefix)]
    assert found, f"no README line starts with {prefix!r}"
    return found


def result(bringup, prefix: str) -> subprocess.CompletedProcess:
    found = results_for(bringup, prefix)
    assert len(found) == 1, f"several README lines start with {prefix!r}"
    return found[0]


def test_a_new_servo_is_found_and_set_up(bringup):
    first, last = results_for(bringup, "vbnav find servos")
    assert re.search(r"57600 bit/s: id 1 ", first.stdout), first.stdout
    assert re.search(r"1000000 bit/s: id 1 .*\n.*id 2 ", last.stdout), last.stdout
    assert "is now id 2" in result(bringup, "vbnav servo set-id").stdout


def test_the_config_uses_the_calibration_and_the_measured_mount(bringup):
    from vbnav.control.config import load_config
    _, work = bringup
    assert "camera intrinsics from" in result(bringup, "vbnav config check").stdout
    cfg = load_config(str(work / "myrobot.yaml"))
    assert cfg.camera.calibration_file == "calib/camera_info.yaml"
    assert cfg.drive.options["port"] == str(work / "usb-FTDI_emulated-if00-port0")
    m = cfg.camera.mount
    assert abs(m.height - FLOOR_MOUNT["height"]) < 0.01, m
    assert abs(m.pitch_deg - FLOOR_MOUNT["pitch_deg"]) < 1.0 and abs(m.roll_deg - FLOOR_MOUNT["roll_deg"]) < 1.0, m


def test_the_robot_drove_taught_and_repeated(bringup):
    _, work = bringup
    run = result(bringup, "vbnav run")
    assert run.returncode == 130, run.stderr                     # Ctrl-C: "interrupted"
    for drive in results_for(bringup, "vbnav send teleop"):       # the robot took the teleop stream
        assert "teleop applied by robot sentry-dxl" in drive.stdout, drive.stdout + drive.stderr
    teach = result(bringup, "vbnav teach")
    assert teach.returncode == 0, teach.stderr                   # Ctrl-C ends a teach: the route is kept
    taught = re.search(r"(\d+) keyframes in routes/patrol", teach.stdout + teach.stderr)
    assert taught and int(taught.group(1)) >= 2, teach.stdout + teach.stderr
    check = result(bringup, "vbnav route check").stdout
    assert "intact" in check and "complete" in check, check
    assert "keyframes:   " + taught.group(1) in result(bringup, "vbnav route info").stdout
    assert (work / "routes" / "patrol.png").stat().st_size > 0
    repeat = result(bringup, "vbnav repeat")
    reached = re.search(r"reached keyframe (\d+) of (\d+)", repeat.stdout)
    assert reached and reached.group(1) == reached.group(2) == taught.group(1), repeat.stdout + repeat.stderr
