"""The ``telemetry:`` configuration section and the zenoh session built from it.

Safe by default: the robot's zenoh session listens only on
``tcp/127.0.0.1:7447``, with multicast scouting and gossip off, so nothing is
reachable from another machine and nothing is discovered by accident.

Remote access is explicit. A listener on any non-loopback address is refused
unless the section also configures

- authentication: zenoh user/password (``auth.usrpwd`` with a dictionary file of
  accepted peers) or mutual TLS (``auth.tls`` with CA, certificate and key), and
- ``operators``: the user names (or certificate common names) allowed to publish
  on ``vbnav/<robot>/cmd/**``. An access-control policy is generated from it:
  everyone authenticated may read ``state``, ``events`` and ``image``; only
  operators may command. Everything else is denied.

The zenoh config keys used here are those of zenoh 1.x (``listen/endpoints``,
``scouting/multicast/enabled``, ``scouting/gossip/enabled``,
``transport/auth/usrpwd``, ``transport/link/tls``, ``access_control``).
"""
from __future__ import annotations

import ipaddress
from typing import Literal, Optional

from pydantic import Field, model_validator
from vbnav.control.config.base import Strict

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"



LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")



NAME_PATTERN = r"^[A-Za-z0-9_\-.@]+$"



class UsrPwdAuth(Strict):
    user: str = Field(..., min_length=1, pattern=NAME_PATTERN, description="this robot's own user name")
    password: str = Field(..., min_length=8, description="this robot's own password")
    dictionary_file: str = Field(..., min_length=1,
                                 description="file of accepted 'user:password' lines (plain or sha256)")



class TlsAuth(Strict):
    root_ca_certificate: str = Field(..., description="CA that signed every peer's certificate (PEM)")
    listen_certificate: str = Field(..., description="this robot's certificate (PEM)")
    listen_private_key: str = Field(..., description="this robot's private key (PEM)")
    enable_mtls: Literal[True] = Field(True, description="peers must present a certificate too (required)")



class AuthConfig(Strict):
    usrpwd: Optional[UsrPwdAuth] = Field(None, description="zenoh user/password authentication")
    tls: Optional[TlsAuth] = Field(None, description="mutual TLS authentication (listeners use tls/ or quic/)")



class TelemetryConfig(Strict):
    """The ``telemetry:`` section of a robot configuration."""

    enabled: bool = Field(True, description="open a zenoh session, publish telemetry, accept commands")
    state_rate_hz: float = Field(20.0, gt=0, le=1000, description="rate of vbnav/<robot>/state")
    image_rate_hz: float = Field(2.0, ge=0, le=60, description="rate of vbnav/<robot>/image JPEGs (and in "
                                                                "recordings); 0 = off")
    image_width: int = Field(320, ge=16, le=4096, description="JPEG frames are scaled to this width, px")
    jpeg_quality: int = Field(70, ge=10, le=100, description="JPEG quality of those images")
    listen: list[str] = Field(default_factory=lambda: [DEFAULT_ENDPOINT], max_length=8,
                              description="zenoh endpoints the robot listens on")
    connect: list[str] = Field(default_factory=list, max_length=8,
                               description="zenoh endpoints the robot connects to (e.g. a base-station router)")
    scouting: bool = Field(False, description="multicast scouting and gossip (discovery); off by default")
    auth: AuthConfig = Field(default_factory=AuthConfig, description="authentication of peers; needed (with "
                             "operators) as soon as listen, connect or scouting reach beyond this machine")
    operators: list[str] = Field(default_factory=list,
                                 description="user names / certificate common names allowed on cmd/**")

    @model_validator(mode="after")
    def _remote_access_needs_auth(self):
        remote = [e for e in self.listen + self.connect if not is_loopback_endpoint(e)]
        if self.scouting:
            remote.append("multicast scouting")
        if remote and self.enabled:
            missing = []
            if self.auth.usrpwd is None and self.auth.tls is None:
                missing.append("authentication (telemetry.auth.usrpwd with a dictionary_file, or telemetry.auth.tls "
                               "with certificates)")
            if not self.operators:
                missing.append("telemetry.operators (the user names or certificate common names allowed to send "
                               "commands; an access-control rule limits cmd/** to them)")
            if missing:
                raise ValueError(
                    f"remote access ({', '.join(remote)}) makes the robot reachable from other machines and needs "
                    + " and ".join(missing)
                    + f"; for local use only, listen on {DEFAULT_ENDPOINT}")
        for ep in self.listen + self.connect:
            _split_endpoint(ep)  # raises on malformed endpoints
        if self.auth.tls is not None:
            for ep in self.listen:
                if not ep.startswith(("tls/", "quic/")) and not is_loopback_endpoint(ep):
                    raise ValueError(f"telemetry.listen: {ep!r}: with auth.tls, remote listeners must use tls/ "
                                     f"(or quic/) so certificates are checked")
        return self

    @property
    def remote(self) -> bool:
        return self.scouting or any(not is_loopback_endpoint(e) for e in self.listen + self.connect)



def _split_endpoint(endpoint: str) -> tuple[str, str]:
    """'tcp/127.0.0.1:7447#iface=lo' -> ('tcp', '127.0.0.1'). Raises ValueError on malformed input."""
    if "/" not in endpoint:
        raise ValueError(f"zenoh endpoint {endpoint!r}: expected PROTOCOL/ADDRESS, e.g. {DEFAULT_ENDPOINT}")
    proto, rest = endpoint.split("/", 1)
    rest = rest.split("?", 1)[0].split("#", 1)[0]
    if proto in LOCAL_PROTOCOLS:
        return proto, rest
    if rest.startswith("["):
        host, sep, _ = rest[1:].partition("]")
        if not sep:
            raise ValueError(f"zenoh endpoint {endpoint!r}: unclosed '[' in IPv6 address")
    else:
        host, sep, port = rest.rpartition(":")
        if not sep or not port.isdigit():
            raise ValueError(f"zenoh endpoint {endpoint!r}: expected HOST:PORT after {proto}/")
    return proto, host



def is_loopback_endpoint(endpoint: str) -> bool:
    """True if the endpoint can only be reached from this machine."""
    proto, host = _split_endpoint(endpoint)
    if proto in LOCAL_PROTOCOLS:
        return proto != "vsock"
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: may resolve anywhere
