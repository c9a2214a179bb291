"""One file a command: no command imports another command, nor the demo scenario (except `vbnav demo`).

Logic two commands need lives in the package (runtime/factory.py builds the robot, session.py runs teach and
repeat); the shared argument helpers `_common.py` and `_net.py` are the only modules commands share.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

COMMANDS = Path(__file__).resolve().parents[1] / "control" / "commands"
PACKAGE = "vbnav.control.commands"
SHARED = {"_common", "_net"}
DEMO = "vbnav.control.demo"


def imported_modules(path: Path) -> set[str]:
    """Every module a file imports, at top level or inside functions, as absolute dotted names."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:      # relative: resolve against vbnav.control.commands
                parts = PACKAGE.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            out.add(module)
            out.update(f"{module}.{a.name}" for a in node.names)   # `from pkg import module`
    return out


def command_files() -> list[Path]:
    return sorted(p for p in COMMANDS.glob("*.py") if p.stem != "__init__")


def test_the_commands_are_found():
    names = {p.stem for p in command_files()}
    assert {"teach", "repeat", "goto", "demo", "run"} <= names, names


@pytest.mark.parametrize("path", command_files(), ids=lambda p: p.stem)
def test_a_command_imports_no_other_command_and_not_the_demo(path):
    modules = imported_modules(path)
    others = {m for m in modules if m.startswith(PACKAGE + ".")
              and m.split(".")[3] not in SHARED | {path.stem}}
    assert not others, f"{path.name} imports other commands: {sorted(others)}"
    if path.stem != "demo":
        demo = {m for m in modules if m == DEMO or m.startswith(DEMO + ".")}
        assert not demo, f"{path.name} imports the demo scenario: {sorted(demo)}"


def test_only_vbnav_demo_imports_the_demo_scenario():
    """The demo is a scenario, not a library: the package reaches it only through `vbnav demo`."""
    root = COMMANDS.parents[1]
    users = sorted(str(p.relative_to(root)) for d in ("control", "drivers", "vision") for p in (root / d).rglob("*.py")
                   if p != COMMANDS / "demo.py" and p != root / "control" / "demo.py"
                   and any(m == DEMO or m.startswith(DEMO + ".") for m in imported_modules(p)))
    assert not users, f"modules importing {DEMO}: {users}"
