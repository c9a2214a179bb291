"""Documented commands and their promised messages (README.md, docs/*.md), checked cheaply at the CLI."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest


@pytest.mark.parametrize("argv, message", [
    (["send", "mode", "teach"], "vbnav send: --route: mode teach needs a route (--route NAME"),
    (["send", "mode", "repeat"], "vbnav send: --route: mode repeat needs a route (--route NAME"),
    (["send", "mode", "teach", "--route", "../hall"], "vbnav send: --route: route must be a plain name"),
])
def test_send_mode_route_errors_name_the_flag(capsys, argv, message):
    """`vbnav send mode teach|repeat` without --route (or with a path) said 'mode: mode: Value error, mode
    'teach' needs a route ("route": "NAME")': pydantic's words and the JSON field, not the flag to give."""
    from vbnav.control import cli
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(message) and "Value error" not in err and len(err.splitlines()) == 1, err


ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL_VARS = {"$PORT": "/dev/ttyUSB0", "$CAMERA": "/dev/video0",     # README, bring-up
              "$TLS": "--tls-ca ca.pem --tls-cert alice.pem --tls-key alice.key"}    # docs/fleet.md


def _documented_command_lines():
    """Every `vbnav ...` line of a code block in README.md and docs/ (fenced or indented), and every
    `vbnav ...` command of the README's benchmark table: (file:line, argv). Syntax summaries (with
    [optional] parts or a|b alternatives) are left out."""
    for doc in DOCS:
        fenced = benchmarks = False
        for n, line in enumerate(doc.read_text().splitlines(), 1):
            benchmarks = line.startswith("## Benchmarks") or (benchmarks and not line.startswith("## "))
            if line.startswith("```"):
                fenced = not fenced
                continue
            cmds = []
            if fenced or line.startswith("    vbnav "):
                text = line.split(" #")[0].strip().rstrip("\\").strip()
                text = text.replace("sudo $(command -v vbnav)", "vbnav")
                cmds = [c.strip() for c in text.split(";")]
            elif benchmarks and line.startswith("| ") and "`vbnav " in line:
                cmds = [c for c in re.findall(r"`(vbnav [^`]*)`", line.split(" | ")[1])]
            for cmd in cmds:
                if not cmd.startswith("vbnav ") or re.search(r"[\[|]|\.\.\.", cmd):
                    continue
                for var, value in SHELL_VARS.items():
                    cmd = cmd.replace(var, value)
                yield f"{doc.name}:{n}", shlex.split(cmd)[1:]


def test_every_documented_command_line_parses():
    """The README's benchmark table showed `vbnav vo ../shared/data/kitti06_stereo --init stereo`, which
    stops at 'the following arguments are required: --out': every command line the documentation shows
    must at least be accepted by the parser."""
    from vbnav.control.cli import build_parser
    parser = build_parser()
    seen, refused = 0, []
    for where, argv in _documented_command_lines():
        seen += 1
        try:
            parser.parse_args(argv)
        except SystemExit:
            refused.append(f"{where}: vbnav {shlex.join(argv)}")
    assert seen > 40 and not refused, "\n".join(refused)


def test_telemetry_doc_names_the_route_keys_and_chunk_sizes_the_robot_serves():
    """docs/telemetry.md described an older route transfer (`vbnav/<robot>/routes?chunk=K`, tar archives of
    512 KiB, pushes on `cmd/route/<name>` in 36 KiB chunks, `route_received` events) that the robot does not
    serve: its keys and chunk sizes are those of control/comms/route_transfer.py."""
    from vbnav.control.comms import route_transfer as rt
    text = (ROOT / "docs" / "telemetry.md").read_text()
    section = text[text.index("## Routes"):text.index("## Live view")]
    for name, key in rt.keys("<robot>").items():
        if name != "all":
            assert f"`{key}" in section, key
    assert f"{rt.PULL_CHUNK // 1024} KiB" in section and f"{rt.PUSH_CHUNK // 1024} KiB" in section
    assert "cmd/route" not in section and "route_received" not in text
    fleet = (ROOT / "docs" / "fleet.md").read_text()
    assert f"Pushed chunks are {rt.PUSH_CHUNK // 1024} KiB" in fleet and f"pulled chunks {rt.PULL_CHUNK // 1024} KiB" in fleet


def _subparsers(parser, path=()):
    """(command words, parser) of every command and subcommand."""
    import argparse
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _subparsers(sub, path + (name,))


def test_no_help_says_default_none_or_false():
    """`vbnav vo --help` and `vbnav lines --help` printed '(default: None)' after the required --out and after
    options that say their default in their own words ('--init ... (default: stereo if right images, ...)
    (default: None)'), and '(default: False)' after flags."""
    from vbnav.control.cli import build_parser
    bad = []
    for path, parser in _subparsers(build_parser()):
        text = " ".join(parser.format_help().split())
        for noise in ("(default: None)", "(default: False)"):
            if noise in text:
                bad.append(f"vbnav {' '.join(path)} --help: {noise}")
    assert not bad, "\n".join(bad)


def test_every_argument_is_explained_in_its_help():
    """`vbnav map plot --help` listed --out and MAP bare, `map view --help` hid its --port default (8765, the
    one docs/line_map.md names), `calibrate stereo --help` its folders, --out and --quiet, `send mode --help`
    the mode: every option and positional of every command says what it is."""
    import argparse
    from vbnav.control.cli import build_parser
    bare = [f"vbnav {' '.join(path)}: {a.option_strings[0] if a.option_strings else a.dest}"
            for path, parser in _subparsers(build_parser()) for a in parser._actions
            if not a.help and not isinstance(a, argparse._SubParsersAction)]
    assert not bare, "\n".join(bare)
    view = next(p for path, p in _subparsers(build_parser()) if path == ("map", "view"))
    assert "default 8765" in " ".join(view.format_help().split())


def test_telemetry_doc_names_the_commands_whose_overwrite_is_for_the_recording_only():
    """docs/telemetry.md said `map build --overwrite` without --record is refused, as in run, repeat and demo;
    map build's --overwrite also replaces its --out map (as teach's the route), so it is accepted."""
    from vbnav.control.cli import build_parser
    record_only, also_more = set(), set()
    for path, parser in _subparsers(build_parser()):
        opts = {a.option_strings[0]: a for a in parser._actions if a.option_strings}
        if "--record" in opts and "--overwrite" in opts:
            only = opts["--overwrite"].help.startswith("replace an existing --record file")
            (record_only if only else also_more).add(" ".join(path))
    text = " ".join((ROOT / "docs" / "telemetry.md").read_text().split())
    listed = re.search(r"Without `--record`, `--overwrite` is refused \(([^:]*):", text).group(1)
    assert set(re.findall(r"`([a-z ]+)`", listed)) == record_only, (listed, record_only)
    for command in also_more:
        assert f"`{command} --overwrite` also replaces" in text, command


def test_telemetry_doc_names_every_cause_of_a_safety_warning():
    """docs/telemetry.md's `safety_warning` row named only `drive_lost`; the runtime also warns
    `stop_unconfirmed` (a motor that did not take a stop) and `scheduling` (a refused CPU set or priority)."""
    causes = set()
    for path in (ROOT / "control").rglob("*.py"):
        causes |= set(re.findall(r'note\(\s*\w+,\s*"warning",\s*"(\w+)"', path.read_text()))
    row = next(line for line in (ROOT / "docs" / "telemetry.md").read_text().splitlines()
               if line.startswith("| `safety_warning`"))
    assert causes >= {"drive_lost", "stop_unconfirmed", "scheduling"}, causes
    assert all(f"`{c}`" in row for c in causes), (causes, row)


def test_telemetry_doc_names_every_cause_of_a_safety_trip():
    """docs/telemetry.md's `safety_trip` row left out the fatal `camera` (a camera that fails mid-run, exit 3;
    docs/safety.md)."""
    from vbnav.control.runtime.safety import FATAL
    causes = set(FATAL)
    for path in (ROOT / "control").rglob("*.py"):
        causes |= set(re.findall(r'\.trip\(\s*\w+,\s*"(\w+)"', path.read_text()))
    row = next(line for line in (ROOT / "docs" / "telemetry.md").read_text().splitlines()
               if line.startswith("| `safety_trip`"))
    assert {"estop", "stall", "drive_lost", "camera"} <= causes, causes
    assert all(f"`{c}`" in row for c in causes), (causes, row)


def test_telemetry_doc_names_the_causes_of_a_safety_hold():
    """docs/telemetry.md's `safety_hold` row said 'obstacles'; the cause a monitor or a script sees is
    `obstacle`."""
    row = next(line for line in (ROOT / "docs" / "telemetry.md").read_text().splitlines()
               if line.startswith("| `safety_hold`"))
    for cause in ("command_timeout", "camera_stale", "<kind>_stale", "obstacle"):
        assert f"`{cause}`" in row, (cause, row)
    src = (ROOT / "control" / "runtime" / "runtime.py").read_text()
    assert '.hold(now, "obstacle",' in src and '.hold(now, "camera_stale",' in src


def test_cannot_connect_says_why_without_zenohs_source_paths(capsys):
    """`vbnav send` (monitor, teleop, route) to an endpoint where nobody listens said 'cannot connect to
    tcp/127.0.0.1:1: Unable to connect to any of [...]!  at /root/.cargo/git/checkouts/zenoh-.../
    orchestrator.rs:447. (is `vbnav run` going ...)': the Rust source location is no help to an operator.
    The robot's own 'cannot open the zenoh session' goes through the same open_session."""
    from vbnav.control import cli
    assert cli.main(["send", "estop", "--connect", "tcp/127.0.0.1:1", "--wait", "1"]) == 3
    err = capsys.readouterr().err.strip()
    assert err.startswith("vbnav send: cannot connect to tcp/127.0.0.1:1: ") and "Unable to connect" in err, err
    assert ".rs:" not in err and ".cargo" not in err and len(err.splitlines()) == 1, err


def test_find_servos_on_a_port_that_is_not_there_prints_no_scan(capsys, tmp_path):
    """`vbnav find servos --port NOPE` printed 'Scanning NOPE (broadcast ping at each rate):' on stdout and
    then refused the port: a script reading stdout saw a scan begin. The port is checked first."""
    from vbnav.control import cli
    missing = tmp_path / "ttyNOPE"
    assert cli.main(["find", "servos", "--port", str(missing)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and f"--port {missing}: no such device" in err and len(err.splitlines()) == 1, (out, err)


def test_teach_help_says_what_ends_a_teach():
    """`vbnav teach --help` said a teleop teach is stopped 'with Ctrl-C or vbnav send estop'; an estop latches
    the wheels' stop and the teach goes on recording (the run ends on Ctrl-C, SIGTERM or --duration), so the
    help now says that, as the README's bring-up does ('until Ctrl-C once the route is driven')."""
    from vbnav.control.cli import build_parser
    teach = next(p for path, p in _subparsers(build_parser()) if path == ("teach",))
    text = " ".join(teach.format_help().split())
    assert "stop with Ctrl-C or 'vbnav send estop'" not in text
    assert "end it with Ctrl-C" in text and "'vbnav send estop' stops the wheels" in text, text


def test_line_map_doc_gives_the_prediction_range_the_map_uses():
    """docs/line_map.md said the map's prediction is clipped 'to 0.5-3 m' (the old min_range_m); LineMap.predict
    clips at 0.1 m in front of the camera and at max_range_m in depth (min_range_m, 0.35 m, only limits what
    is inserted)."""
    from vbnav.vision.line_map import MapParams
    text = " ".join((ROOT / "docs" / "line_map.md").read_text().split())
    assert "0.5-3 m" not in text
    assert f"to `max_range_m` ({MapParams().max_range_m:g} m) in depth" in text


def test_vo_refuses_a_bundle_adjustment_it_would_not_run(tmp_path, capsys):
    """`vbnav vo KITTI --init stereo --ba-window 7` was accepted and changed nothing (ATE 0.1370 m with and
    without): the window adjusts landmarks placed by the camera's own motion, and a stereo run measures
    every landmark with the pair. The option is now refused there, before any tracking."""
    from test_cli_errors import _sequence
    from vbnav.control import cli
    _sequence(tmp_path, "seq")
    for init in (["--init", "stereo"], []):          # stereo is also the default with right images
        code = cli.main(["vo", str(tmp_path / "seq"), "--out", str(tmp_path / "t.txt"), "--ba-window", "7",
                         "--quiet", *init])
        out, err = capsys.readouterr()
        assert code == 2 and out == "" and "--ba-window 7" in err and "stereo" in err, (init, out, err)
    assert not (tmp_path / "t.txt").exists()


def test_each_help_says_what_its_command_does_with_the_option():
    """Helps that did not say what the code does: `route list --help` gave -c a default (configs/sim.yaml) while
    `route list` without DIR or -c is refused; `send resume` was 'clear the estop latches this sender has seen'
    while it clears every latched stop (estop, stall, lost drive) the robot's state showed, or all of them with
    --clear-all; `goto` said a single camera creeps 'up to 0.3 m' (vslam.goto.blind_distance_m, 0.3 m by
    default only); every -c promised that 'send' signs, also monitor's (it sends nothing) and not teleop's, which
    signs as send does."""
    from vbnav.control.cli import build_parser, main
    parsers = dict(_subparsers(build_parser()))

    def option_help(path, option):
        return " ".join(next(a.help for a in parsers[path]._actions if option in a.option_strings).split())
    assert "default" not in option_help(("route", "list"), "--config")
    assert main(["route", "list"]) == 2          # no DIR, no -c: refused, as the help now says
    resume = next(a for a in parsers[("send",)]._actions if a.dest == "what")._choices_actions
    said = " ".join(next(c.help for c in resume if c.dest == "resume").split())
    assert "latched stops" in said and "--clear-all" in said, said
    assert "vslam.goto.blind_distance_m" in " ".join(parsers[("goto",)].description.split())
    assert "sign" not in option_help(("monitor",), "--config")
    for path in (("teleop",), ("send", "estop")):
        assert "signed with its telemetry.shared_secret_file" in option_help(path, "--config"), path
