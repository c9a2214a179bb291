"""Settings files give numbers as numbers and switches as true/false: nothing is guessed.

pydantic's lax mode turns ``max_linear_speed: true`` into 1.0 m/s (twice a 0.5 default), ``rate_hz:
"15"`` into 15 and ``enabled: "no"`` into False. A YAML slip (``yes`` is a bool in YAML 1.1, a quoted
number is a string) then runs the robot on a value nobody wrote. Full strict mode would also refuse
what YAML cannot give otherwise (lists for tuples, strings for paths and enums), so this mixin refuses
only the two silent conversions: a bool or a string for a number, a string or a number for a bool.
Integers stay accepted for floats (``fx: 400``). A number must be finite: no setting means anything
by .inf or .nan, and .inf slips past a lower bound to switch off what it sets.

``load_yaml`` and ``load_json`` read settings, calibration and recorded files refusing a key given twice
(YAML and JSON readers keep the last one: the first, often a whole section, was silently not used).
"""
from __future__ import annotations

import json
import math
import re
import types
import typing

import yaml
from pydantic import BaseModel, ValidationInfo, field_validator


class _UniqueKeys(yaml.SafeLoader):
    """yaml.SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last: the first
    value, often a whole section, was silently not used)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            first: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    seen = first.get(key)
                except TypeError:           # an unhashable key: the base class says so
                    continue
                if seen is not None:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"found duplicate key {key!r} (first on line {seen + 1}); the later one would "
                                    f"silently replace it", key_node.start_mark)
                first[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


# YAML 1.1 (PyYAML) reads an exponent without a dot, ``baseline: 1e-12``, as the text "1e-12", and the
# check below then asked to write it "without quotes" when it had none. YAML 1.2 and every other reader
# take it as the number it is; so do vbnav's files. (Quoted, it is still text and still refused.)
_UniqueKeys.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"),
                                  list("-+0123456789"))


def load_json(text: str | bytes):
    """``json.loads`` for the files vbnav records (route manifests, maps), refusing a key given twice in one
    object (a ValueError ``duplicate key 'complete'``: JSON readers keep the last, the first is lost)."""
    def unique(pairs):
        out = {}
        for k, v in pairs:
            if k in out:
                raise ValueError(f"duplicate key {k!r}")
            out[k] = v
        return out
    return json.loads(text, object_pairs_hook=unique)


def load_yaml(text: str):
    """``yaml.safe_load`` for settings and calibration files, refusing duplicate keys (a yaml.YAMLError
    with the line, as ``errors.yaml_problem`` formats it)."""
    return yaml.load(text, Loader=_UniqueKeys)


def _kinds(annotation) -> set:
    """The plain types an annotation admits: Optional[float] -> {float, NoneType}."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _kinds(typing.get_args(annotation)[0])
    if origin is typing.Union or origin is types.UnionType:
        return set().union(*(_kinds(a) for a in typing.get_args(annotation)))
    return {annotation}


def _number_text(value) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


def refused_conversion(annotation, value) -> str | None:
    """Why ``value`` must not be converted to ``annotation``, or None when it may be validated (text
    that is no number is left to pydantic, which refuses it with its own words)."""
    kinds = _kinds(annotation)
    if str in kinds or typing.Any in kinds:
        return None
    numeric = bool(kinds & {int, float})
    if numeric and isinstance(value, float) and not math.isfinite(value):
        # .inf passes a lower bound and disables what it sets (obstacles.obstacle_height: .inf, no obstacle
        # is ever tall enough; vbc.fix_gate_m: .inf, no gate); .nan passes no bound but reads as a number
        return f"expected a finite number, not {value}"
    if numeric and bool not in kinds:
        if isinstance(value, bool):
            return "expected a number, not true/false"
        if isinstance(value, str) and _number_text(value):
            return f"expected a number, not the text {value!r} (write it without quotes)"
    if bool in kinds and not numeric and not isinstance(value, bool) and isinstance(value, (int, float, str)):
        return "expected true or false"
    return None


class PlainValues(BaseModel):
    """Base of settings models whose values come from files or the network: see the module docstring."""

    @field_validator("*", mode="before")
    @classmethod
    def _no_silent_conversion(cls, value, info: ValidationInfo):
        field = cls.model_fields.get(info.field_name) if info.field_name else None
        why = refused_conversion(field.annotation, value) if field is not None else None
        if why:
            raise ValueError(why)
        return value
