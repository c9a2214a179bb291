"""The zenoh sessions built from the ``telemetry:`` section (see config/telemetry.py)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional

from vbnav.control.config.base import ConfigError
from vbnav.control.config.telemetry import TelemetryConfig, UsrPwdAuth


def access_control_rules(robot: str, operators: Optional[list[str]]) -> dict[str, Any]:
    """zenoh 1.x ``access_control`` of the robot's session (default deny).

    Everyone may subscribe to and receive ``state``, ``events`` and ``image`` and query the event
    history, and sees that the robot subscribes to ``cmd/**`` (so ``vbnav send`` can tell a robot that
    is not there from one that refuses it). Only ``operators`` may put on ``cmd/**``; ``None`` (no
    authentication: nobody is identified) lets everyone. Nobody may put on the robot's telemetry keys:
    another process cannot publish a fake ``state`` through the robot's session.
    """
    prefix = f"vbnav/{robot}"
    telemetry_keys = [f"{prefix}/state", f"{prefix}/events", f"{prefix}/image"]
    commanders = ["everyone"] if operators is None else ["operators", "operators-tls"]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "telemetry-out", "permission": "allow", "flows": ["egress"],
             "messages": ["put"], "key_exprs": telemetry_keys},
            {"id": "telemetry-subscribe", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_subscriber"], "key_exprs": telemetry_keys + [f"{prefix}/**"]},
            {"id": "events-history", "permission": "allow", "flows": ["ingress", "egress"],
             "messages": ["query", "reply", "declare_queryable"],
             "key_exprs": [f"{prefix}/events/recent", "vbnav/*/events/recent"]},
            {"id": "commands-subscribe", "permission": "allow", "flows": ["egress"],
             "messages": ["declare_subscriber"], "key_exprs": [f"{prefix}/cmd/**"]},
            {"id": "commands-in", "permission": "allow", "flows": ["ingress"],
             "messages": ["put"], "key_exprs": [f"{prefix}/cmd/**"]},
        ],
        "subjects": [{"id": "everyone"}] + ([] if operators is None else [
            {"id": "operators", "usernames": list(operators)},
            {"id": "operators-tls", "cert_common_names": list(operators)},
        ]),
        "policies": [
            {"id": "read-telemetry", "rules": ["telemetry-out", "telemetry-subscribe", "events-history",
                                               "commands-subscribe"],
             "subjects": ["everyone"]},
            {"id": "operators-command", "rules": ["commands-in"], "subjects": commanders},
        ],
    }



# The robot receives only commands (<= 4 KiB) and small queries: zenoh drops any message larger than
# this before reassembling it, so an oversized payload never reaches Python. Shared memory is off in the
# robot's session because a same-host sender could otherwise pass a large buffer around this limit.
RX_MESSAGE_LIMIT = 65536


def robot_session_config(tcfg: TelemetryConfig, robot: str) -> dict[str, Any]:
    """The zenoh configuration (as a dict) of the robot's own session."""
    conf: dict[str, Any] = {
        "mode": "peer",
        "listen": {"endpoints": list(tcfg.listen)},
        "connect": {"endpoints": list(tcfg.connect)},
        "scouting": {"multicast": {"enabled": tcfg.scouting}, "gossip": {"enabled": tcfg.scouting}},
    }
    transport: dict[str, Any] = {"link": {"rx": {"max_message_size": RX_MESSAGE_LIMIT}},
                                 "shared_memory": {"enabled": False}}
    if tcfg.auth.usrpwd is not None:
        transport["auth"] = {"usrpwd": _usrpwd_dict(tcfg.auth.usrpwd)}
    if tcfg.auth.tls is not None:
        tls = tcfg.auth.tls
        transport["link"]["tls"] = {
            "root_ca_certificate": _existing(tls.root_ca_certificate, "auth.tls.root_ca_certificate"),
            "listen_certificate": _existing(tls.listen_certificate, "auth.tls.listen_certificate"),
            "listen_private_key": _existing(tls.listen_private_key, "auth.tls.listen_private_key"),
            "connect_certificate": tls.listen_certificate,
            "connect_private_key": tls.listen_private_key,
            "enable_mtls": True,
        }
    conf["transport"] = transport
    # Always: the policy also keeps other processes from publishing on the robot's telemetry keys. With
    # authentication, on any listener, commands are limited to operators (config/telemetry.py requires them,
    # except behind a trusted router, which cannot be told apart from its clients).
    limited = tcfg.authenticated and not tcfg.trust_router
    conf["access_control"] = access_control_rules(robot, list(tcfg.operators) if limited else None)
    return conf



def client_session_config(connect: list[str], user: Optional[str] = None, password: Optional[str] = None,
                          tls: Optional[dict[str, str]] = None) -> dict[str, Any]:
    """A zenoh client (monitor, send, tests) that connects only where told and never scouts."""
    conf: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    if user is not None:
        conf.setdefault("transport", {})["auth"] = {"usrpwd": {"user": user, "password": password or ""}}
    if tls:
        conf.setdefault("transport", {})["link"] = {"tls": dict(tls)}
    return conf



def open_session(conf: dict[str, Any]):
    """Open a zenoh session from a config dict (imports zenoh lazily: config checks need no zenoh)."""
    import zenoh
    return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))



def _usrpwd_dict(u: UsrPwdAuth) -> dict[str, str]:
    return {"user": u.user, "password": u.password,
            "dictionary_file": _existing(u.dictionary_file, "auth.usrpwd.dictionary_file")}



def _existing(path: str, key: str) -> str:
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"telemetry.{key}: file not found: {p}")
    return str(p.resolve())
