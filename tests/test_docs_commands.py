"""Documented commands and their promised messages (README.md, docs/*.md), checked cheaply at the CLI."""
from __future__ import annotations

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
