"""The one kind of error that means "what you gave is wrong", not "the program is wrong".

A configuration, calibration, dataset, route or recording file, a field in one, a command
line argument or a device path the user named is missing, unreadable or out of range.
Every reader raises a subclass of :class:`InputError` whose message names the file and
field (``calib.txt: P0: ...``); ``vbnav`` prints it as ``vbnav <command>: <message>`` and
exits 2. Any other exception reaching the command line is a bug and keeps its traceback.
It lives in drivers/ (the file and device layer) so that drivers/ and control/ share it.
"""
from __future__ import annotations


class InputError(ValueError):
    """A file, field, argument or device the user named is wrong. The message says which and why."""


def yaml_problem(exc: Exception) -> str:
    """A YAML parse error as one line, ``line 2, column 1: not valid YAML: expected the node content ...``
    (PyYAML's own text spans several lines with a drawing of the spot)."""
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
    return f"{where}not valid YAML: " + " ".join(str(getattr(exc, "problem", None) or exc).split())
