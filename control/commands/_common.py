"""Arguments shared by several subcommands, and the checks of what they name.

The ``argparse`` types (``finite``, ``positive``, ``non_negative``) refuse NaN, infinities and
out-of-range numbers with one line naming the argument; ``output_file`` checks a path a
command will write before any work starts.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Optional

from vbnav.drivers.errors import InputError


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults in the help, except None and False (a required option, a flag, or an option that says its
    default in its own words)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def add_config_arg(p: argparse.ArgumentParser, default: str | None = None) -> None:
    p.add_argument("--config", "-c", default=default, metavar="FILE",
                   help=f"robot configuration YAML (default: configs/{default or 'sim'}.yaml; a bare name like "
                        "'sim' is looked up in configs/)")


def add_record_overwrite_arg(p: argparse.ArgumentParser, also: str = "") -> None:
    p.add_argument("--overwrite", action="store_true",
                   help=f"replace {also + ' and ' if also else ''}an existing --record file (the new one takes its "
                        f"place only when complete; an interrupted FILE.part is kept, renamed "
                        f"FILE-STEM.interrupted-N.SUFFIX.part)")


def record_target_error(args, overwrite_is_record_only: bool = False) -> Optional[str]:
    """Why ``--record`` cannot be written (a recording is there and no ``--overwrite``, or its folder is
    missing), or None; checked before any device opens. With ``overwrite_is_record_only`` (the commands
    whose ``--overwrite`` is ``add_record_overwrite_arg``'s), ``--overwrite`` without ``--record`` is an
    error too: it would replace nothing."""
    from vbnav.control.comms.recording import check_record_target
    if not args.record:
        if args.overwrite and overwrite_is_record_only:
            return "--overwrite replaces an existing --record file; without --record it has nothing to replace"
        return None
    try:
        check_record_target(args.record, args.overwrite)
    except (FileExistsError, FileNotFoundError) as exc:
        return str(exc)
    return None


def finite(text: str) -> float:
    """argparse type: a finite number."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def positive(text: str) -> float:
    """argparse type: a finite number > 0 (durations, rates, timeouts)."""
    v = finite(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return v


def non_negative(text: str) -> float:
    """argparse type: a finite number >= 0."""
    v = finite(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


def output_file(path: str | Path | None, option: str) -> None:
    """Raise InputError unless ``path`` (if given) can be written as a file: not a directory, and in a
    folder that exists and this user can write (files are written beside their target and renamed over it).
    Existing files are the caller's business (some replace them, some refuse)."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{option} {p}: is a directory, expected a file name")
    parent = p.parent
    if not parent.is_dir():
        what = "is not a directory" if parent.exists() else "does not exist"
        raise InputError(f"{option} {p}: the folder {parent} {what}")
    import os
    if not os.access(parent, os.W_OK | os.X_OK):      # said now, not after a drive whose result it would lose
        raise InputError(f"{option} {p}: the folder {parent} is not writable by this user")


def add_overwrite_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--overwrite", action="store_true", help=f"replace {what} (written atomically, when complete)")


def not_recorded_yet(paths, option: str, overwrite: bool, what: str) -> None:
    """Raise InputError when one of ``paths`` exists and ``overwrite`` is not given: a map or calibration
    already recorded is not replaced without asking (as teach --out and --record)."""
    there = [str(p) for p in paths if p is not None and Path(p).exists()]
    if there and not overwrite:
        raise InputError(f"{option}: {what} already there ({', '.join(there)}); use --overwrite to replace it")


def refuse_no_camera_with_obstacle_stop(cfg, no_camera: bool) -> None:
    """--no-camera on a configuration whose obstacle stop (a safety function it asks for) needs the camera:
    refused by run and doctor alike."""
    if no_camera and cfg.obstacles.enabled:
        raise InputError(f"--no-camera: {cfg.source}: obstacles.enabled is true, and the obstacle stop needs the "
                         f"camera (set obstacles.enabled: false to run without it)")


def distinct_files(outputs: dict, inputs: Optional[dict] = None) -> None:
    """Raise InputError when two outputs (option -> path) name one file, or an output names one of the
    ``inputs`` (option -> path): one would overwrite the other. Paths that are None are not given."""
    import os
    seen: dict = {}
    given_inputs: dict = {}
    for o, p in (inputs or {}).items():
        if p is not None:
            given_inputs.setdefault(os.path.realpath(p), o)        # the first option naming it
    for option, path in outputs.items():
        if path is None:
            continue
        key = os.path.realpath(path)
        if key in given_inputs:
            raise InputError(f"{option} {path}: is the {given_inputs[key]} file; writing it would replace the input")
        if key in seen:
            raise InputError(f"{seen[key]} and {option} name the same file {path}: one would overwrite the other")
        seen[key] = option


def apart_from_config(cfg, outputs: dict) -> None:
    """Raise InputError when an output (option -> path; None: not given) is the configuration file the run
    was loaded from: the map or recording written at the end would replace the robot's configuration."""
    if cfg.source:
        distinct_files(outputs, {"--config": cfg.source})


def duration_within_script(script, duration, what: str) -> None:
    """Raise InputError when ``--duration`` outlasts the scripted drive: the run ends with its script (the
    controller finishes), so a longer duration was accepted and cut without a word."""
    total = sum(seg[2] for seg in script)
    if duration is not None and duration > total + 1.0:
        raise InputError(f"--duration {duration:g} s: {what} ends after {total:g} s, and the run with it; leave "
                         f"--duration out, or lengthen the script")


def network_closed(cfg, no_telemetry: bool = False) -> str:
    """What keeps the telemetry session (network commands, the live view) closed: "--no-telemetry",
    "<config>: telemetry.enabled: false", or "" when it opens."""
    if no_telemetry:
        return "--no-telemetry"
    return "" if cfg.telemetry.enabled else f"{cfg.source}: telemetry.enabled: false"


def refuse_network_driver_without_network(cfg, what: str, no_telemetry: bool, consequence: str) -> None:
    """Refuse ``what`` (a controller driven by commands over the network: teleop, the operator) when the
    network is kept closed; ``consequence`` says what the run would have been."""
    closed = network_closed(cfg, no_telemetry)
    if closed:
        raise InputError(f"{what}: takes its commands over the network, which {closed} keeps closed "
                         f"({consequence})")


def apply_realtime(cfg, realtime: bool) -> None:
    """--realtime: run the simulated robot on the wall clock (sim.realtime: true). Refused on a configuration
    that is not on the simulated clock anyway (a real drive or camera: always the wall clock), where it would
    change nothing."""
    if not realtime:
        return
    real = [f"{k}.driver {d}" for k, d in (("drive", cfg.drive.driver), ("camera", cfg.camera.driver)) if d != "sim"]
    if real:        # sim.realtime: true kept in such a config's sim section let it through, changing nothing
        raise InputError(f"--realtime: {cfg.source}: {' and '.join(real)} run on the wall clock anyway (only a robot whose "
                         f"drive and camera are both simulated has a simulated clock); leave it out")
    cfg.sim.realtime = True
    from vbnav.control.config import simulated_latency_not_read
    why = simulated_latency_not_read(cfg)
    if why:
        raise InputError(f"--realtime: {cfg.source}: {why}")


def live_view_refusal(cfg, no_telemetry: bool = False, remedy: str = "add --realtime") -> str:
    """Why this run could not serve the live view ("" when it could): it rides on the telemetry session, which
    --no-telemetry or telemetry.enabled: false keeps closed, and which opens only on the wall clock (call after
    applying --realtime). ``remedy``: how this command runs the simulated robot on the wall clock."""
    closed = network_closed(cfg, no_telemetry)
    if closed:
        return f"it is served by the telemetry session, which {closed} keeps closed"
    if cfg.on_simulated_clock():
        return f"the simulated robot runs on the simulated clock, faster than real time, where nothing is served: {remedy}"
    return ""


def refuse_unserved_live_view(cfg, no_telemetry: bool = False, remedy: str = "set sim.realtime: true") -> None:
    """Refuse ``telemetry.live_view.enabled: true`` in a run that could not serve it (``live_view_refusal``)."""
    why = live_view_refusal(cfg, no_telemetry, remedy) if cfg.telemetry.live_view.enabled else ""
    if why:
        raise InputError(f"{cfg.source}: telemetry.live_view.enabled: true: {why}")


def enable_live_view(cfg, no_telemetry: bool) -> None:
    """Turn on ``telemetry.live_view``, checked like a loaded configuration (a non-loopback host needs more).
    Refused where it could not be served (``live_view_refusal``; call after applying --realtime)."""
    from pydantic import ValidationError

    why = live_view_refusal(cfg, no_telemetry)
    if why:
        raise InputError(f"--live-view: {why}")
    t = cfg.telemetry.model_dump()
    t["live_view"]["enabled"] = True
    try:
        cfg.telemetry = type(cfg.telemetry).model_validate(t)
    except ValidationError as exc:
        raise InputError(f"--live-view: {exc.errors()[0]['msg']}") from None
