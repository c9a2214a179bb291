"""What the runtime plugs together: vision stages, estimates, controllers and operator commands.

This module is the one place that states what a plug-in offers. Every optional
capability is an explicit member with a default here (a stage's
``safety_critical``, a controller's ``handle_command`` and ``forget_command``),
so the runtime and telemetry call them directly and never probe with
``getattr``/``hasattr``.

Data flow (DESIGN.md): a camera frame goes through the configured vision stages
(VBC, VSLAM, obstacles), each of which returns an Estimate; the fixed-rate loop
gives the latest estimates (with their age) and odometry to one controller,
which returns a Twist; the safety monitor may override it; the drive executes.

Controllers never touch I/O. Vision stages are pure with respect to the robot
(frame and odometry in, estimate out); they may keep state (tracks, keyframe
index) but must not block on anything but computation.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Optional

from vbnav.control.runtime.mailbox import OperatorCommand
from vbnav.drivers.camera import Frame
from vbnav.drivers.wheels import WheelState
from vbnav.vision.geometry import Pose2


@dataclass(frozen=True)
class Twist:
    """Body velocity command: v forward m/s, w rad/s (positive turns right, see vision/geometry.py)."""

    v: float = 0.0
    w: float = 0.0


STOP = Twist(0.0, 0.0)


@dataclass
class Estimate:
    """Output of a vision stage for one frame.

    stamp_ns: the frame's stamp (not the time processing finished), so its age
    says how old the information is. kind: the stage's name ('vbc', 'vslam',
    'obstacles'). ok: whether the stage trusts it. value: stage-specific result.
    """

    stamp_ns: int
    kind: str
    ok: bool
    value: Any = None
    info: dict = field(default_factory=dict)

    def age_s(self, now_ns: int) -> float:
        return (now_ns - self.stamp_ns) * 1e-9


class PoseFix:
    """Base of stage results that place the robot (``Estimate.value`` of vbc and vslam).

    pose: the robot's planar pose in the stage's frame (relative to a keyframe for VBC, the
    world for VSLAM); telemetry shows it. Subclasses are dataclasses that declare the field.
    """

    pose: Pose2


@dataclass
class ControlContext:
    now_ns: int
    dt: float                       # s since the previous cycle
    odom: Pose2                     # dead-reckoned pose from wheel odometry
    wheels: WheelState
    estimates: dict[str, Optional[Estimate]]  # latest per stage kind (may be None)
    cycle: int = 0

    def estimate(self, kind: str, max_age_s: float) -> Optional[Estimate]:
        """The latest estimate of ``kind`` if it is younger than ``max_age_s``."""
        e = self.estimates.get(kind)
        if e is None or e.age_s(self.now_ns) > max_age_s:
            return None
        return e


class VisionStage(abc.ABC):
    """One vision computation run on every frame (on the vision thread)."""

    kind: str = "vision"
    #: True for stages the robot must not move without (obstacle zones): the safety monitor stops the
    #: robot when this stage's estimate is older than safety.estimate_timeout_s, whatever the controller.
    safety_critical: bool = False

    @abc.abstractmethod
    def process(self, frame: Frame, odom: Pose2) -> Optional[Estimate]:
        """Estimate from one frame; ``odom`` is the wheel odometry at (about) the frame time."""

    def overlay(self, estimate: Optional[Estimate]) -> Optional["StageOverlay"]:
        """What to draw for the frame just processed (``estimate``: this stage's result for it), for
        the live view and the recording (comms/overlays.py); None for a stage with nothing to show."""
        return None

    def start(self) -> None:
        """Start threads of the stage's own (the line map's slow loop); the command that runs the stage on
        a real clock calls it. Nothing by default."""

    def stop(self) -> None:
        """Stop what ``start`` started. Nothing by default."""


@dataclass
class StageOverlay:
    """What one vision stage saw in a frame, in its own image pixels or world frame; None = nothing."""

    tracked: Any = None               # (N, 2) pixels of the features tracked in this frame
    matched: Any = None               # (M, 2) keyframe pixels of the matched keyframe's features tracked now
    stop_zone: Any = None             # (K, 2) pixels: outline of the stop corridor on the floor
    obstacle_labels: Any = None       # (H, W) obstacle label image, > 0 on obstacles
    route: Optional[tuple[str, list]] = None   # (name, keyframe odometry poses) of the route followed
    landmarks: Any = None             # (L, 3) landmark positions in the stage's world frame
    line_map: Any = None              # stages/line_map.MapScene: the line map's segments and its revision


@dataclass(frozen=True)
class CommandOutcome:
    """A controller's answer to an operator command.

    applied: the command took effect (the runtime tells its ``command_listeners``; ``reason``, if any, is a
    note on what it did not change, e.g. a resume with a hold still active); otherwise it is
    refused and ``reason`` becomes the ``rejected`` safety event the operator sees. unchanged: applied,
    but the state already was what the command asked for (a ``mode`` equal to the current one).
    pending: neither yet: the controller finishes the command later (a mode switch that loads a route
    off the loop thread) and answers it then with ``Runtime.complete_command``; until then nobody is told
    it took effect.
    """

    applied: bool
    reason: str = ""
    unchanged: bool = False
    pending: bool = False

    @classmethod
    def refused(cls, reason: str) -> "CommandOutcome":
        return cls(False, reason)


APPLIED = CommandOutcome(True)
PENDING = CommandOutcome(False, pending=True)

#: what starts each mode when a run has a single controller (the refusal names it)
_NEW_RUN_FOR = {"idle": "stop this run", "teach": "vbnav teach --out ROUTE", "repeat": "vbnav repeat --path ROUTE"}


class Controller(abc.ABC):
    """Turns odometry and estimates into a Twist, at the loop rate."""

    name: str = "controller"
    #: estimate kinds this controller needs fresh; the safety monitor stops the robot when
    #: one is older than safety.estimate_timeout_s.
    requires: tuple[str, ...] = ()

    def start(self, ctx: ControlContext) -> None:
        """Called once before the first update."""

    @abc.abstractmethod
    def update(self, ctx: ControlContext) -> Twist: ...

    @property
    def finished(self) -> bool:
        """True when the job is done (route completed, script ended); the runtime then stops."""
        return False

    def status(self) -> dict:
        """Small JSON-able summary for progress lines and telemetry."""
        return {}

    @property
    def teaching_route(self) -> Optional[str]:
        """The route (name under controller.routes_dir) an operator-switched teach is recording now, which
        a route push must not replace; None when none is."""
        return None

    @property
    def followed_route(self) -> Optional[str]:
        """The route an operator-switched teach or repeat is on now (the telemetry state's ``route``); None
        when none is (vbnav teach and repeat name theirs on the link)."""
        return None

    def safety_conditions(self) -> dict[str, tuple[bool, str]]:
        """Held stop conditions the controller detects: cause -> (active, message).

        The runtime feeds them to the safety monitor, which stops the wheels at once
        (not through the acceleration limiter) while one is active.
        """
        return {}

    # -- operator commands (loop thread) ---------------------------------------
    def handle_command(self, cmd: OperatorCommand, now_ns: int) -> CommandOutcome:
        """Apply an operator command; the runtime itself handles ``estop`` and ``resume``.

        The default is a controller that runs one mode and takes no teleop: a ``mode`` command
        naming the current mode is acknowledged as unchanged, any other mode is refused with the
        command that starts it (switching lives in controllers/operator.py), and anything else
        (``teleop``) is refused as not supported. Controllers that take teleop or switch modes
        override this.
        """
        if cmd.kind == "mode":
            target = cmd.args[0] if cmd.args else None
            if target == self.name:
                return CommandOutcome(True, unchanged=True)
            how = _NEW_RUN_FOR.get(target, "a new run")
            return CommandOutcome.refused(f"this run is '{self.name}'; switching to '{target}' needs a new run "
                                          f"({how})")
        return CommandOutcome.refused(f"command {cmd.kind!r} not supported by this run")

    def forget_command(self) -> None:
        """Drop any held operator command (after a loop stall), so only a fresh one moves the robot."""

    def close(self) -> None:
        """End of the run, after the loop stopped: release what the controller opened (a route being taught)."""
