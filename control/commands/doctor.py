"""``vbnav doctor -c CONFIG``: a checklist of what a run of this configuration needs on this machine.

Checks that the drive opens and answers on its port (its safe bring-up: torque
off, axes idle; nothing moves), the FTDI latency timer of the serial adapter,
the permissions on the serial and video devices (dialout, video groups) and the
OAK udev rule, that the camera opens and gives a frame of the configured size,
the calibration file, real-time scheduling rights (SCHED_FIFO), that the zenoh
endpoint is free and the routes directory writable. Each problem comes with
its fix. Exit 0 when nothing blocks a run (warnings allowed), 1 when something
does, 2 for a configuration that does not load.
"""
from __future__ import annotations

import argparse

from vbnav.control.commands._common import add_config_arg

MARK = {"ok": "[ ok ]", "warn": "[warn]", "fail": "[FAIL]", "skip": "[skip]"}


def register(sub) -> None:
    p = sub.add_parser("doctor", help="check devices, permissions and settings a run of a configuration needs",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_arg(p)
    p.add_argument("--no-camera", action="store_true", help="a robot without a camera: skip the camera checks")
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.control.doctor import FAIL, WARN, run_checks
    cfg = load_config(args.config)
    from vbnav.control.commands._common import refuse_no_camera_with_obstacle_stop
    refuse_no_camera_with_obstacle_stop(cfg, args.no_camera)
    print(f"vbnav doctor: {cfg.source} (robot {cfg.robot.name}, drive {cfg.drive.driver}, camera "
          f"{'none' if args.no_camera else cfg.camera.driver})", flush=True)
    checks = run_checks(cfg, camera=not args.no_camera)
    for c in checks:
        print(f"  {MARK[c.status]} {c.name}: {c.detail}")
        if c.fix and c.status in (FAIL, WARN):
            print(f"         fix: {c.fix}")
    fails = sum(c.status == FAIL for c in checks)
    warns = sum(c.status == WARN for c in checks)
    if fails:
        print(f"{fails} problem(s) block a run, {warns} warning(s)")
        return 1
    print(f"ready to run ({warns} warning(s))")
    return 0
