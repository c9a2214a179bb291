"""The strict base of every configuration model, and errors that say where.

Every model of a robot configuration derives from :class:`Strict`: unknown keys
are errors (a typo must not silently fall back to a default) and assignments
are validated like loaded values. Validation errors become one
:class:`ConfigError` whose lines name the file, the key path and what was
expected, e.g. ``configs/sim.yaml: robot.wheel_radius: Input should be
greater than 0 (got -0.05)``.
"""
from __future__ import annotations

from pydantic import ConfigDict, ValidationError

from vbnav.drivers.errors import InputError
from vbnav.drivers.plain_values import PlainValues


class ConfigError(InputError):
    """A configuration file is missing, malformed or invalid. The message says where."""


class Strict(PlainValues):
    """Base of every configuration model: unknown keys are errors, assignments are validated, and no
    value is converted from another kind (``true`` or ``"15"`` for a number: drivers/plain_values.py)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


def written(model, name: str) -> bool:
    """Whether a configuration wrote ``name`` with a value other than its default. The refusals of settings
    written where they do not apply use it: ``vbnav config show`` prints every field, defaults included, and
    what it prints must load back (a default is what the setting does anyway, wherever it is written)."""
    if name not in model.model_fields_set:
        return False
    value = model.model_dump(include={name})[name]        # a field by name, not a probe of a capability
    return value != type(model).model_fields[name].get_default(call_default_factory=True)


def format_loc(loc) -> str:
    """A pydantic error location as a key path: ('vbc', 'max_features') -> 'vbc.max_features'."""
    return ".".join(str(p) for p in loc) or "<top level>"


def format_errors(source: str, exc: ValidationError, prefix: str = "") -> str:
    """One line per error: ``SOURCE: KEY.PATH: message (got VALUE)``; ``prefix`` is the path of the
    validated block within the file (e.g. 'drive.options')."""
    lines = []
    for err in exc.errors():
        loc = format_loc(((prefix,) if prefix else ()) + tuple(err["loc"]))
        msg = err["msg"]
        if err["type"] == "value_error":    # our own validators' messages are whole sentences
            msg = msg.removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key (check the spelling; see docs/configuration.md or 'vbnav config reference')"
        got = err.get("input")
        got_s = "" if err["type"] in ("missing", "extra_forbidden") or isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"{source}: {loc}: {msg}{got_s}")
    return "\n".join(lines)
