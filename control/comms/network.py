"""The zenoh sessions built from the ``telemetry:`` section (see config/telemetry.py)."""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Optional

from vbnav.control.config.base import ConfigError
from vbnav.control.config.telemetry import TelemetryConfig, UsrPwdAuth


def access_control_rules(robot: str, operators: Optional[list[str]]) -> dict[str, Any]:
    """zenoh 1.x ``access_control`` of the robot's session (default deny).

    Everyone may subscribe to and receive ``state``, ``events`` and ``image`` and query the event
    history and the robot's taught routes (``routes/**``, comms/route_transfer.py), and sees that the robot
    subscribes to ``cmd/**`` (so ``vbnav send`` can tell a robot that is not there from one that refuses it).
    Only ``operators`` may put on ``cmd/**`` and push routes (query ``routes/push/**``); ``None`` (no
    authentication: nobody is identified) lets everyone. Nobody may put on the robot's telemetry keys:
    another process cannot publish a fake ``state`` through the robot's session.
    """
    prefix = f"vbnav/{robot}"
    telemetry_keys = [f"{prefix}/state", f"{prefix}/events", f"{prefix}/image"]
    # A fleet view (vbnav monitor --all) subscribes to and asks every robot at once: zenoh checks the
    # declared key expression itself, so the wildcard forms must be allowed as such.
    fleet_reads = ["vbnav/*/state", "vbnav/*/events", "vbnav/*/image"]
    commanders = ["everyone"] if operators is None else ["operators", "operators-tls"]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "telemetry-out", "permission": "allow", "flows": ["egress"],
             "messages": ["put"], "key_exprs": telemetry_keys},
            # vbnav/*/state and vbnav/*/events: `vbnav monitor --all` watches every robot behind a router.
            {"id": "telemetry-subscribe", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_subscriber"], "key_exprs": telemetry_keys + fleet_reads + [f"{prefix}/**"]},
            {"id": "events-history", "permission": "allow", "flows": ["ingress", "egress"],
             "messages": ["query", "reply", "declare_queryable"],
             "key_exprs": [f"{prefix}/events/recent", "vbnav/*/events/recent"]},
            {"id": "commands-subscribe", "permission": "allow", "flows": ["egress"],
             "messages": ["declare_subscriber"], "key_exprs": [f"{prefix}/cmd/**"]},
            {"id": "commands-in", "permission": "allow", "flows": ["ingress"],
             "messages": ["put"], "key_exprs": [f"{prefix}/cmd/**"]},
            # Taught routes (comms/route_transfer.py): reading them is like reading telemetry; a push is a
            # write to the robot, like a command.
            {"id": "routes-served", "permission": "allow", "flows": ["egress"],
             "messages": ["declare_queryable", "reply"], "key_exprs": [f"{prefix}/routes/**"]},
            {"id": "routes-read", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
             "key_exprs": [f"{prefix}/routes/list", "vbnav/*/routes/list", f"{prefix}/routes/files/*",
                           f"{prefix}/routes/chunk/**"]},
            {"id": "routes-push", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
             "key_exprs": [f"{prefix}/routes/push/**"]},
        ],
        "subjects": [{"id": "everyone"}] + ([] if operators is None else [
            {"id": "operators", "usernames": list(operators)},
            {"id": "operators-tls", "cert_common_names": list(operators)},
        ]),
        "policies": [
            {"id": "read-telemetry", "rules": ["telemetry-out", "telemetry-subscribe", "events-history",
                                               "commands-subscribe", "routes-served", "routes-read"],
             "subjects": ["everyone"]},
            {"id": "operators-command", "rules": ["commands-in", "routes-push"], "subjects": commanders},
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



#: where in zenoh's Rust sources an error was raised (" at /root/.cargo/.../orchestrator.rs:447."): no help to a user
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")


def open_session(conf: dict[str, Any]):
    """Open a zenoh session from a config dict (imports zenoh lazily: config checks need no zenoh).
    Failing, raises ConnectionError with zenoh's reason, less the Rust source locations."""
    import zenoh
    try:
        return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
    except zenoh.ZError as exc:
        raise ConnectionError(_RUST_LOCATION.sub("", str(exc)).strip()) from exc



def _usrpwd_dict(u: UsrPwdAuth) -> dict[str, str]:
    return {"user": u.user, "password": u.password,
            "dictionary_file": _existing(u.dictionary_file, "auth.usrpwd.dictionary_file")}



def _existing(path: str, key: str) -> str:
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"telemetry.{key}: file not found: {p}")
    return str(p.resolve())


def router_access_control(robots: list[str], operators: list[str]) -> dict[str, Any]:
    """zenoh 1.x ``access_control`` of a fleet's router (zenohd), default deny (docs/fleet.md).

    Robots connect with ``telemetry.trust_router: true``, so the router is where the operator rule holds:
    everyone it admits may read every robot (subscribe to state, events and image, ask the event history,
    list and pull routes); robot ``R`` (zenoh user name ``R``, its ``robot.name``) may publish and serve only
    under ``vbnav/R/**``; only ``operators`` may put on ``vbnav/*/cmd/**`` and push routes.
    """
    reads = ["vbnav/*/state", "vbnav/*/events", "vbnav/*/image", "vbnav/*/events/recent", "vbnav/*/routes/list",
             "vbnav/*/routes/files/*", "vbnav/*/routes/chunk/**"]
    writes = ["vbnav/*/cmd/**", "vbnav/*/routes/push/**"]
    rules: list[dict[str, Any]] = [
        {"id": "read", "permission": "allow", "flows": ["ingress"], "messages": ["declare_subscriber", "query"],
         "key_exprs": reads},
        {"id": "read-back", "permission": "allow", "flows": ["egress"], "messages": ["put", "reply"],
         "key_exprs": reads},
        {"id": "see-robots", "permission": "allow", "flows": ["egress"],
         "messages": ["declare_subscriber", "declare_queryable"], "key_exprs": ["vbnav/**"]},
        {"id": "write", "permission": "allow", "flows": ["ingress"], "messages": ["put", "query"],
         "key_exprs": writes},
        {"id": "write-answer", "permission": "allow", "flows": ["egress"], "messages": ["reply"],
         "key_exprs": ["vbnav/*/routes/push/**"]},
    ]
    subjects: list[dict[str, Any]] = [{"id": "everyone"}, {"id": "operators", "usernames": list(operators)}]
    policies: list[dict[str, Any]] = [
        {"id": "everyone-reads", "rules": ["read", "read-back", "see-robots"], "subjects": ["everyone"]},
        {"id": "operators-write", "rules": ["write", "write-answer"], "subjects": ["operators"]},
    ]
    for robot in robots:
        prefix = f"vbnav/{robot}"
        rid = f"robot-{robot}"
        rules += [
            {"id": f"{rid}-in", "permission": "allow", "flows": ["ingress"],
             "messages": ["put", "reply", "declare_subscriber", "declare_queryable"], "key_exprs": [f"{prefix}/**"]},
            {"id": f"{rid}-out", "permission": "allow", "flows": ["egress"], "messages": ["put", "query"],
             "key_exprs": [f"{prefix}/cmd/**", f"{prefix}/routes/**", f"{prefix}/events/recent",
                           "vbnav/*/events/recent", "vbnav/*/routes/list"]},
        ]
        subjects.append({"id": rid, "usernames": [robot]})
        policies.append({"id": rid, "rules": [f"{rid}-in", f"{rid}-out"], "subjects": [rid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_session_config(listen: list[str], user: str, password: str, dictionary_file: str,
                          robots: list[str], operators: list[str]) -> dict[str, Any]:
    """A fleet router's configuration: what ``zenohd -c`` reads (as JSON5), or a router-mode session in tests."""
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": password, "dictionary_file": dictionary_file}}},
        "access_control": router_access_control(robots, operators),
    }
