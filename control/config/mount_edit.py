"""Writing the camera mounting (``camera.mount``) into a config file, keeping the rest of the file as it is.

``vbnav calibrate mount`` measures height, pitch and roll; this puts them into the user's YAML without a
YAML round trip (which would drop every comment and reorder keys): only the ``mount:`` entry of the
``camera:`` section is rewritten (a one-line flow mapping replaced by a new one, a block mapping's lines
edited in place, a missing entry added at the end of the section). The edited text is parsed again and must
equal the original data with the new mount (and be a valid configuration) before it is written, through a
temporary file renamed over the original. A file this cannot edit safely (a flow-style ``camera: {...}``) is
refused with the values to set by hand; nothing is written then.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import yaml

from vbnav.control.config.base import ConfigError
from vbnav.drivers.atomic_file import write_atomic
from vbnav.drivers.plain_values import load_yaml

_TOP_KEY = re.compile(r"^([A-Za-z_][\w-]*)\s*:(.*)$")
_KEY = re.compile(r"^(\s+)([A-Za-z_][\w-]*)\s*:(\s*)(.*?)(\s+#.*)?$")


def _flow(values: dict) -> str:
    return "{" + ", ".join(f"{k}: {_num(v)}" for k, v in values.items()) + "}"


def _num(v) -> str:
    return repr(v) if isinstance(v, float) else yaml.safe_dump(v, default_flow_style=True).strip()


def set_camera_mount(path, values: dict, write: bool = True) -> str:
    """Set ``camera.mount.<key>`` to ``values`` (e.g. height, pitch_deg, roll_deg) in the YAML file ``path``,
    keeping every other line. Returns the new text (written atomically; with ``write`` False only checked, as
    it would be written). Raises ConfigError naming the file."""
    from vbnav.control.config import parse_config
    p = Path(path)
    values = {k: round(float(v), 4) for k, v in values.items()}     # 0.1 mm, 1e-4 deg: far below what is measured
    try:
        raw = p.read_bytes().decode()
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a UTF-8 text file ({exc})") from None
    newline = "\r\n" if "\r\n" in raw else "\n"        # kept: every line not edited stays as it was
    text = raw.replace("\r\n", "\n")
    try:
        data = load_yaml(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({exc})") from None
    old_mount = dict(((data.get("camera") or {}).get("mount") or {}))
    new_mount = {**old_mount, **values}
    new_text = _edited(text, new_mount, values)
    if new_text is None:
        raise ConfigError(f"{p}: cannot edit camera.mount in place (camera is not a block mapping); set it by "
                          f"hand: camera: mount: {_flow(new_mount)}")
    expected = dict(data)
    expected["camera"] = {**(data.get("camera") or {}), "mount": new_mount}
    got = load_yaml(new_text)
    if got != expected:
        raise ConfigError(f"{p}: editing camera.mount in place would change other keys; set it by hand: "
                          f"camera: mount: {_flow(new_mount)}")
    parse_config(got, str(p))      # the result must be a valid configuration (the file is not written else)
    if not write:
        return new_text
    # A config that is a symbolic link (robot.yaml -> configs/robot-v2.yaml) stays one: the file it points to
    # is edited (renaming over the link would replace it with an edited copy, the linked file unchanged).
    write_atomic(Path(os.path.realpath(p)), new_text.replace("\n", newline))
    return new_text


def _edited(text: str, new_mount: dict, values: dict):
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if (m := _TOP_KEY.match(ln)) and m.group(1) == "camera"), None)
    if start is None:
        sep = "" if not text or text.endswith("\n") else "\n"
        return f"{text}{sep}camera:\n  mount: {_flow(new_mount)}\n"
    rest = _TOP_KEY.match(lines[start]).group(2).split("#")[0].strip()
    if rest:
        return None                                   # camera: {...} on one line
    end = start + 1
    while end < len(lines) and (not lines[end].strip() or lines[end].startswith((" ", "\t", "#"))):
        end += 1
    body = range(start + 1, end)
    children = [(i, m) for i in body if (m := _KEY.match(lines[i].rstrip("\n")))]
    if not children:
        return None
    indent = min(len(m.group(1)) for _, m in children)
    mount = next(((i, m) for i, m in children if m.group(2) == "mount" and len(m.group(1)) == indent), None)
    if mount is None:
        last = max(i for i in body if lines[i].strip() and not lines[i].lstrip().startswith("#"))
        lines.insert(last + 1, f"{' ' * indent}mount: {_flow(new_mount)}\n")
        return "".join(lines)
    i, m = mount
    if m.group(4).strip():                            # mount: {height: ..., ...}  (flow, one line)
        if not m.group(4).strip().startswith("{") or not m.group(4).strip().endswith("}"):
            return None
        lines[i] = f"{m.group(1)}mount: {_flow(new_mount)}{m.group(5) or ''}\n"
        return "".join(lines)
    j, seen = i + 1, set()                            # block mapping: edit the child lines in place
    sub = None
    while j < end:
        mm = _KEY.match(lines[j].rstrip("\n"))
        if lines[j].strip() and not lines[j].lstrip().startswith("#"):
            if mm is None or len(mm.group(1)) <= indent:
                break
            sub = len(mm.group(1))
            if mm.group(2) in values:
                lines[j] = f"{mm.group(1)}{mm.group(2)}: {_num(values[mm.group(2)])}{mm.group(5) or ''}\n"
                seen.add(mm.group(2))
            last_child = j
        j += 1
    if sub is None:
        return None
    missing = [f"{' ' * sub}{k}: {_num(v)}\n" for k, v in values.items() if k not in seen]
    lines[last_child + 1:last_child + 1] = missing
    return "".join(lines)
