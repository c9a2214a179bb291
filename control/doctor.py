"""The self-check of ``vbnav doctor``: can this machine run this configuration?

Each check returns a :class:`Check`: ``ok``, ``warn`` (the run works, worse:
no real-time scheduling, no calibration file), ``fail`` (the run would stop or
misbehave: a device missing or silent, no permission, the telemetry endpoint
taken) or ``skip`` (does not apply), with what was found and, for a problem,
the fix. Devices are opened with their drivers' own safe bring-up (torque off,
axes idle) and closed again: nothing moves.
"""
from __future__ import annotations

import os
import resource
import socket
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

OK, WARN, FAIL, SKIP = "ok", "warn", "fail", "skip"

#: udev rule files that give users access to OAK (Movidius, USB vendor 03e7) devices
UDEV_DIRS = ("/etc/udev/rules.d", "/lib/udev/rules.d", "/usr/lib/udev/rules.d")
OAK_VENDOR = "03e7"
OAK_RULE_FIX = ("sudo $(command -v vbnav) service install -c CONFIG writes it (/etc/udev/rules.d/99-vbnav.rules, "
                "docs/service.md); or the rule alone: "
                "echo 'SUBSYSTEM==\"usb\", ATTRS{idVendor}==\"03e7\", MODE=\"0666\"' | sudo tee "
                "/etc/udev/rules.d/80-movidius.rules && sudo udevadm control --reload-rules && sudo udevadm trigger")
FIRST_FRAME_S = 5.0        # a USB camera's first frame after opening: exposure settles, MJPG starts


@dataclass
class Check:
    name: str
    status: str
    detail: str
    fix: str = ""


def _serial_access(name: str, port: str) -> Optional[Check]:
    """A failed check when the serial device is missing or not ours to open, else None."""
    if not os.path.exists(port):
        return Check(name, FAIL, f"{port} does not exist",
                     "plug the adapter in; 'vbnav find' lists the serial ports and their /dev/serial/by-id names "
                     "(set drive.options.port to one)")
    if not os.access(port, os.R_OK | os.W_OK):
        return Check(name, FAIL, f"no permission to open {port}",
                     "sudo usermod -aG dialout $USER, then log out and in (or reboot)")
    return None


def check_drive(cfg, robot) -> list[Check]:
    """The drive opens and answers (its bring-up), and an FTDI adapter's latency timer suits the driver."""
    from vbnav.drivers import discovery
    driver = cfg.drive.driver
    drive = robot.drive
    checks = []
    port = drive.serial_port
    if port is not None:
        problem = _serial_access("drive permission", port)
        if problem is not None:
            return [problem]
        checks.append(Check("drive permission", OK, f"{port} can be opened"))
        timer = discovery.read_latency_timer(port)
        wanted = drive.serial_latency_ms
        if timer is None:
            checks.append(Check("serial latency timer", SKIP, f"{port} has none (not an FTDI USB adapter)"))
        elif wanted is not None and timer > wanted:
            checks.append(Check("serial latency timer", FAIL,
                                f"{port}: {timer} ms, the driver waits {wanted:g} ms (drive.options.latency_ms): "
                                f"every answer would come too late",
                                f"echo 1 | sudo tee {discovery.latency_timer_path(port)} (a udev rule makes it "
                                f"permanent, see docs/hardware.md)"))
        else:
            checks.append(Check("serial latency timer", OK, f"{port}: {timer} ms"))
    from vbnav.drivers.odrive import clear_errors_command
    from vbnav.drivers.wheels import DriveError
    try:
        drive.connect()
        checks.append(Check("drive", OK, f"{driver}: {_drive_summary(drive)}"))
    except DriveError as exc:
        fix = {"dynamixel": f"'vbnav find servos --port {port}' shows which ids answer at which rate; "
                            f"'vbnav servo set-id/set-baud' changes them",
               "odrive": f"see the message ('{clear_errors_command(cfg.source)}' clears latched errors)"}
        checks.append(Check("drive", FAIL, f"{driver}: {exc}", fix.get(driver, "see the message")))
    finally:
        drive.close()
    return checks


def _drive_summary(drive) -> str:
    """What the drive's bring-up found (called once it succeeded)."""
    from vbnav.drivers.dynamixel import DynamixelDrive
    from vbnav.drivers.odrive import ODriveDrive
    port = drive.serial_port
    if isinstance(drive, DynamixelDrive) and drive.models:
        from vbnav.drivers.dynamixel_setup import MODEL_NAMES
        servos = ", ".join(f"{i} ({drive.sides[i]}, {MODEL_NAMES.get(m, m)})" for i, m in drive.models.items())
        return f"servos {servos} answer on {port} at {drive.opt.baudrate} bit/s; brought up, torque off"
    if isinstance(drive, ODriveDrive) and drive.vbus_voltage is not None:
        return f"answers on {port}, bus {drive.vbus_voltage:.1f} V; brought up, axes idle"
    return "opened and brought up" + (f" on {port}" if port else "")


def check_camera(cfg, robot) -> list[Check]:
    """The camera opens and gives a frame of the configured size (plus the OAK udev rule, V4L2 access)."""
    driver, cam = cfg.camera.driver, cfg.camera
    checks = []
    from vbnav.drivers.v4l2_camera import V4L2Camera
    device = robot.camera.opt.device if isinstance(robot.camera, V4L2Camera) else None
    if driver == "v4l2" and device and not os.path.isfile(device):
        if not os.path.exists(device):
            return [Check("camera", FAIL, f"{device} does not exist",
                          "plug the camera in; 'vbnav find' lists V4L2 devices with their sizes and rates "
                          "(set camera.options.device, prefer /dev/v4l/by-id/...)")]
        if not os.access(device, os.R_OK | os.W_OK):
            return [Check("camera permission", FAIL, f"no permission to open {device}",
                          "sudo usermod -aG video $USER, then log out and in")]
        checks.append(Check("camera permission", OK, f"{device} can be opened"))
    if driver == "oak":
        checks.append(check_oak_udev_rule())
    try:
        robot.camera.connect()
    except Exception as exc:  # CameraError, InputError, ImportError of a missing SDK: all mean "no camera"
        checks.append(Check("camera", FAIL, f"{driver}: cannot open: {exc}", "'vbnav find' lists the cameras"))
        return checks
    try:
        frame = robot.camera.read(FIRST_FRAME_S)
    finally:
        robot.camera.disconnect()
    if frame is None:
        checks.append(Check("camera", FAIL, f"{driver}: opened, but no frame within {FIRST_FRAME_S:g} s",
                            "check the cable and camera.rate_hz / camera.options against 'vbnav find'"))
        return checks
    h, w = frame.image.shape[:2]
    if (w, h) != (cam.width, cam.height):
        checks.append(Check("camera", FAIL, f"{driver}: frames are {w}x{h}, the configuration says "
                                            f"{cam.width}x{cam.height}",
                            "set camera.width/height (and a calibration for that size)"))
    else:
        checks.append(Check("camera", OK, f"{driver}: a {w}x{h} frame"))
    return checks


def check_oak_udev_rule(dirs=UDEV_DIRS) -> Check:
    for d in dirs:
        for rule in sorted(Path(d).glob("*.rules")) if Path(d).is_dir() else []:
            try:
                if OAK_VENDOR in rule.read_text(errors="replace"):
                    return Check("OAK udev rule", OK, f"{rule} covers USB vendor {OAK_VENDOR}")
            except OSError:
                continue
    root = os.geteuid() == 0
    return Check("OAK udev rule", WARN if root else FAIL,
                 f"no udev rule for USB vendor {OAK_VENDOR} (Luxonis) in {', '.join(dirs)}: only root can open the "
                 f"camera" + (" (this is root; a normal user cannot)" if root else ""), OAK_RULE_FIX)


def check_calibration(cfg) -> Check:
    """The calibration file is there, loads and fits the configured image size."""
    cam = cfg.camera
    if cam.driver == "sim":
        return Check("calibration", SKIP, "simulated camera: its intrinsics are exact")
    if not cam.calibration_file and cam.driver == "oak" and cam.options.get("use_device_calibration", True):
        return Check("calibration", OK, f"OAK: the inline fx {cam.fx:g} fy {cam.fy:g} cx {cam.cx:g} cy {cam.cy:g} "
                                        f"are checked against the device's own calibration at start-up "
                                        f"(camera.options.use_device_calibration; a mismatch refuses to start "
                                        f"and prints the device's values)")
    if not cam.calibration_file:
        return Check("calibration", WARN, f"no camera.calibration_file: the inline fx {cam.fx:g} fy {cam.fy:g} "
                                          f"cx {cam.cx:g} cy {cam.cy:g} are used",
                     "calibrate the camera (vbnav calibrate intrinsics) and set camera.calibration_file")
    # The config loader has already read the file (a missing or invalid one fails the load, naming it) and
    # put its intrinsics in force; what is left to check is whether the values are plausible.
    from vbnav.drivers.calibration import calibration_problems
    cal = cam.calibration
    c = cal.camera
    summary = (f"{cal.file}: {c.width}x{c.height}, fx {c.fx:.1f} fy {c.fy:.1f} cx {c.cx:.1f} cy {c.cy:.1f}")
    problems = calibration_problems(cal)
    if problems:
        return Check("calibration", WARN, f"{summary}: " + "; ".join(problems),
                     "check the calibration (was it made at this image size? a fisheye lens needs "
                     "camera.model: fisheye)")
    return Check("calibration", OK, summary)


def check_realtime(priority: int) -> Check:
    """SCHED_FIFO at ``loop.realtime_priority`` is allowed here (tried on a short-lived thread)."""
    if priority <= 0:
        return Check("real-time scheduling", SKIP, "loop.realtime_priority is 0: normal scheduling")
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    result: list = []

    def attempt():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))   # 0: this thread only
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            result.append(None)
        except OSError as exc:
            result.append(exc)

    t = threading.Thread(target=attempt, name="doctor-rt")
    t.start()
    t.join()
    if result and result[0] is None:
        return Check("real-time scheduling", OK, f"SCHED_FIFO priority {priority} allowed (RLIMIT_RTPRIO {soft})")
    return Check("real-time scheduling", WARN,
                 f"SCHED_FIFO priority {priority} refused (RLIMIT_RTPRIO {soft}): the loop runs with normal "
                 f"scheduling and more jitter",
                 f"echo \"$USER - rtprio {priority}\" | sudo tee /etc/security/limits.d/99-vbnav.conf, then log in "
                 f"again (or sudo setcap cap_sys_nice+ep on the venv's python)")


def check_endpoints(cfg) -> list[Check]:
    """Each zenoh listen endpoint can be bound (nobody else, e.g. another vbnav, holds it)."""
    tel = cfg.telemetry
    if not tel.enabled:
        return [Check("telemetry endpoint", SKIP, "telemetry.enabled is false")]
    return [check_endpoint(e) for e in tel.listen] or [Check("telemetry endpoint", SKIP, "no listen endpoint")]


def check_endpoint(endpoint: str) -> Check:
    name = "telemetry endpoint"
    proto, _, rest = endpoint.partition("/")
    if proto not in ("tcp", "udp", "tls", "quic"):
        return Check(name, SKIP, f"{endpoint}: not an IP endpoint")
    addr = rest.split("#")[0]
    host, _, port = addr.rpartition(":")
    host = host.strip("[]")
    kind = socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(host or None, int(port), type=kind)
    except (OSError, ValueError) as exc:
        return Check(name, FAIL, f"{endpoint}: cannot resolve ({exc})", "fix telemetry.listen")
    family, stype, proto_no, _, sockaddr = infos[0]
    with socket.socket(family, stype, proto_no) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)   # as zenoh does: TIME_WAIT is no conflict
        try:
            s.bind(sockaddr)
            if stype == socket.SOCK_STREAM:
                s.listen(1)
        except OSError as exc:
            return Check(name, FAIL, f"{endpoint}: cannot be bound ({exc.strerror}): another process listens there "
                                     f"(a running vbnav or zenohd?)",
                         f"stop it (ss -ltnp | grep :{port} shows which), or choose another port in "
                         f"telemetry.listen")
    return Check(name, OK, f"{endpoint} is free")


def check_routes_dir(cfg) -> Check:
    from vbnav.control.route import routes_root
    root = routes_root(cfg.controller.routes_dir, cfg.source)
    probe = root
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        return Check("routes directory", FAIL, f"{root}: {probe} is not a directory",
                     "set controller.routes_dir to a folder")
    if probe != root:
        if os.access(probe, os.W_OK | os.X_OK):
            return Check("routes directory", OK, f"{root} will be created (in {probe}, writable)")
        return Check("routes directory", FAIL, f"{root} does not exist and {probe} is not writable",
                     f"mkdir -p {root} as a user who may, or set controller.routes_dir")
    try:
        with tempfile.NamedTemporaryFile(dir=root, prefix=".doctor-"):
            pass
    except OSError as exc:
        return Check("routes directory", FAIL, f"{root}: not writable ({exc.strerror})",
                     f"chown $USER {root}, or set controller.routes_dir")
    return Check("routes directory", OK, f"{root} is writable")


def run_checks(cfg, camera: bool = True) -> list[Check]:
    """Every check for ``cfg``; ``camera`` False for a robot without one (teleop only)."""
    from vbnav.control.runtime.factory import make_robot
    camera_problem = None
    try:
        robot = make_robot(cfg, with_camera=camera)
    except (ImportError, ValueError) as exc:     # a camera driver whose SDK is missing, a sim camera on real wheels
        camera_problem = Check("camera", FAIL, f"{cfg.camera.driver}: {exc}", "see the message")
        robot = make_robot(cfg, with_camera=False)
    checks = check_drive(cfg, robot)
    if camera:
        checks += [camera_problem] if camera_problem else check_camera(cfg, robot)
        checks.append(check_calibration(cfg))
    else:
        checks.append(Check("camera", SKIP, "--no-camera: a robot without a camera (teleop only)"))
    checks.append(check_realtime(cfg.loop.realtime_priority))
    checks += check_endpoints(cfg)
    checks.append(check_routes_dir(cfg))
    return checks
