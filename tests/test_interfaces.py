"""Plug-ins state what they offer (control/runtime/interfaces.py); nothing in control/ probes for it.

Capabilities of controllers, stages and clocks are explicit members with defaults, so the runtime
and the telemetry link call them directly. A new ``getattr(``/``hasattr(`` in control/ fails this
test unless it is added to ``ALLOWED`` with the reason it is not a capability probe.
"""
import re
from pathlib import Path

from runtime_helpers import make_runtime

from vbnav.control.controllers.manual import IdleController, ScriptedController, TeleopController
from vbnav.control.runtime.interfaces import CommandOutcome
from vbnav.control.runtime.runtime import OperatorCommand

CONTROL = Path(__file__).resolve().parents[1] / "control"
PROBE = re.compile(r"\b(getattr|hasattr)\(")

# (file under control/, text of the line) -> why it is not a capability probe
ALLOWED = {
    ("config/__init__.py", 'sec = getattr(cfg, section)'): "a config field read by its name in a loop",
    ("config/__init__.py", 'getattr(cls, "Options", None)'): "driver classes without settings have no Options model",
    ("commands/config.py", "getattr(origin, '__name__', str(origin))"): "typing constructs lack __name__",
    ("commands/config.py", 'getattr(annotation, "__name__", str(annotation))'): "typing constructs lack __name__",
    ("commands/config.py", "if getattr(m, attr, None) is not None:"): "pydantic bound metadata, one attribute each",
    ("commands/config.py", "out.append(words.format(getattr(m, attr)))"): "pydantic bound metadata, one attribute each",
    ("commands/config.py", '"Options", None)'): "driver classes without settings have no Options model",
    ("runtime/pipeline.py", "getattr(fn, '__qualname__', fn)"): "names a listener; a functools.partial has none",
    ("commands/service.py", "getattr(cfg.loop, key)"): "a config field read by its name in a loop",
    ("commands/obstacles.py", "for d in dests if getattr(args, d) is not None]"): "parsed options read by name",
    ("commands/obstacles.py", "if getattr(args, dest) is None:"): "parsed options read by name in a loop",
}


def test_no_capability_probes_in_control():
    found = []
    for path in sorted(CONTROL.rglob("*.py")):
        rel = path.relative_to(CONTROL).as_posix()
        for no, line in enumerate(path.read_text().splitlines(), 1):
            if PROBE.search(line) and not any(f == rel and text in line for f, text in ALLOWED):
                found.append(f"control/{rel}:{no}: {line.strip()}")
    assert not found, ("capability probes in control/ (make the capability an explicit member in "
                       "control/runtime/interfaces.py, or add the line to ALLOWED with a reason):\n" + "\n".join(found))


def test_allow_list_is_not_stale():
    """Every allowed line still exists (a removed probe leaves no blanket permission behind)."""
    for f, text in ALLOWED:
        assert text in (CONTROL / f).read_text(), (f, text)


def _run_with(controller, commands, duration_s=0.2):
    rt, _, _ = make_runtime(controller, camera=False)
    sent = list(commands)
    applied = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.append((cmd.kind, outcome)))

    def send_once(r, ctx, twist, wheels):     # after the first cycle; the loop applies them at the next
        while sent:
            r.submit(sent.pop(0))

    rt.cycle_observers.append(send_once)
    result = rt.run(duration_s)
    return result, applied


def test_controller_without_teleop_refuses_teleop_with_an_event():
    for controller in (IdleController(), ScriptedController([[0.1, 0.0, 5.0]])):
        result, applied = _run_with(controller, [OperatorCommand("teleop", (0.3, 0.0), "op")])
        rejected = [e for e in result.events if e.kind == "rejected"]
        assert [(e.cause, e.message) for e in rejected] == [("teleop", "command 'teleop' not supported by this run")]
        assert applied == []


def test_teleop_controller_applies_teleop():
    result, applied = _run_with(TeleopController(0.5), [OperatorCommand("teleop", (0.3, 0.0), "op")])
    assert applied == [("teleop", CommandOutcome(True))]
    assert not [e for e in result.events if e.kind == "rejected"]


def test_single_mode_controller_answers_mode_commands():
    """The current mode is acknowledged as unchanged, any other names the command that starts it."""
    result, applied = _run_with(TeleopController(0.5), [OperatorCommand("mode", ("teleop",), "op"),
                                                        OperatorCommand("mode", ("repeat", "r"), "op")])
    assert applied == [("mode", CommandOutcome(True, unchanged=True))]
    rejected = [e.message for e in result.events if e.kind == "rejected"]
    assert rejected == ["this run is 'teleop'; switching to 'repeat' needs a new run (vbnav repeat --path ROUTE)"]


def test_a_repeat_run_refuses_a_repeat_of_another_route():
    """'mode repeat --route other' on a run repeating 'hall' was acknowledged as unchanged: the sender was told
    the robot repeats the route it asked for. Only the route being repeated is the current mode."""
    from test_controller_settings import _straight_route
    from vbnav.control.controllers.repeat import RepeatController
    route = _straight_route()
    route.path = Path("/routes/hall")
    result, applied = _run_with(RepeatController(route), [OperatorCommand("mode", ("repeat", "hall"), "op"),
                                                          OperatorCommand("mode", ("repeat", "other"), "op")])
    assert applied == [("mode", CommandOutcome(True, unchanged=True))]
    rejected = [e.message for e in result.events if e.kind == "rejected"]
    assert rejected == ["this run repeats route 'hall'; repeating 'other' needs a new run "
                        "(vbnav repeat --path ROUTE)"]
