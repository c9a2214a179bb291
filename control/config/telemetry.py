"""The ``telemetry:`` configuration section (control/comms/network.py builds the zenoh sessions from it).

Safe by default: the robot's zenoh session listens only on
``tcp/127.0.0.1:7447``, with multicast scouting and gossip off, so nothing is
reachable from another machine and nothing is discovered by accident.

Remote access is explicit. A listener on any non-loopback address, any
``connect`` endpoint (a router may expose the robot on any of its interfaces)
or scouting is refused unless the section also configures

- authentication: zenoh user/password (``auth.usrpwd`` with a dictionary file of
  accepted peers) or mutual TLS (``auth.tls`` with CA, certificate and key), and
- ``operators``: the user names (or certificate common names) allowed to publish
  on ``vbnav/<robot>/cmd/**``.

or, for ``connect``, ``trust_router: true`` (the router decides who may command).
Whenever authentication is configured, on any listener, ``operators`` is
required and enforced (network.py builds the access-control policy). On a
loopback-only robot without authentication any local user can command it;
``shared_secret_file`` closes that (commands must be signed, see
comms/command_auth.py). docs/telemetry.md has the table of who can command the
robot in each configuration.

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



class LiveViewConfig(Strict):
    """``telemetry.live_view``: the Foxglove WebSocket server (control/comms/live_view.py)."""

    enabled: bool = Field(False, description="serve the live view to the Foxglove app (ws://HOST:PORT); off by "
                          "default. Opens with the zenoh session (real-time runs, not --no-telemetry); a run "
                          "that could not serve it (simulated clock, telemetry closed) is refused")
    host: str = Field("127.0.0.1", description="address the WebSocket server binds to; beyond loopback only "
                      "when the telemetry section allows remote access (auth and operators) and with tls_* set")
    port: int = Field(8765, ge=0, le=65535, description="WebSocket port (0: any free port, printed at start)")
    operator_token_file: Optional[str] = Field(
        None, description="file (mode 600) whose content a Foxglove client sets as the parameter "
                          "'vbnav.operator_token' to become an operator (teleop from the Teleop panel). Without "
                          "it, Foxglove teleop is accepted only where any local user may command the robot "
                          "(loopback-only, no shared_secret_file)")
    tls_certificate: Optional[str] = Field(None, description="PEM certificate: serve wss:// (required off loopback)")
    tls_private_key: Optional[str] = Field(None, description="PEM PKCS#8 key of tls_certificate")
    scene_rate_hz: float = Field(1.0, gt=0, le=10, description="rate of the taught route and VSLAM landmarks "
                                 "(3D scene), re-sent so a client that connects late sees them")


class TelemetryConfig(Strict):
    """The ``telemetry:`` section of a robot configuration."""

    enabled: bool = Field(True, description="open a zenoh session, publish telemetry, accept commands")
    state_rate_hz: float = Field(20.0, gt=0, le=1000, description="rate of vbnav/<robot>/state, at most loop.rate_hz "
                                 "(one a cycle: the default is cut to it, a value written above it is refused)")
    image_rate_hz: float = Field(2.0, ge=0, le=60, description="rate of vbnav/<robot>/image JPEGs (and in "
                                                                "recordings); 0 = off; at most the camera's frame "
                                                                "rate (one a frame: the default is cut to it, a "
                                                                "value written above it is refused)")
    image_width: int = Field(320, ge=16, le=4096, description="JPEG frames are scaled down to this width, px, at most "
                             "camera.width (never up: the default is cut to it, a value written above it is "
                             "refused)")
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
    trust_router: bool = Field(False, description="accept the commands that the routers in `connect` forward "
                               "without checking who sent them. Risk: anyone the router admits, on any interface "
                               "it listens on, can command this robot; the router's own access control must "
                               "limit cmd/** to operators")
    shared_secret_file: Optional[str] = Field(None, description="loopback-only robots: a file (mode 600, owned by "
                                              "the robot's user) with a secret of >= 16 bytes; commands must carry "
                                              "its HMAC (vbnav send --secret-file), so other local users cannot "
                                              "command the robot")
    live_view: LiveViewConfig = Field(default_factory=LiveViewConfig,
                                      description="live view in Foxglove (WebSocket server), off by default")

    @model_validator(mode="after")
    def _remote_access_needs_auth(self):
        for ep in self.listen + self.connect:
            _split_endpoint(ep)  # raises on malformed endpoints
        if self.enabled:
            _check_access(self)
            _check_live_view(self)
        if self.auth.tls is not None:
            for ep in self.listen:
                if not ep.startswith(("tls/", "quic/")) and not is_loopback_endpoint(ep):
                    raise ValueError(f"telemetry.listen: {ep!r}: with auth.tls, remote listeners must use tls/ "
                                     f"(or quic/) so certificates are checked")
        return self

    @property
    def authenticated(self) -> bool:
        """Peers must authenticate: ``operators`` is enforced on every listener."""
        return self.auth.usrpwd is not None or self.auth.tls is not None

    @property
    def remote(self) -> bool:
        return bool(_remote_reasons(self))



def _remote_reasons(t: TelemetryConfig) -> list[str]:
    """What makes the robot reachable from beyond this machine (empty: loopback only)."""
    reasons = [e for e in t.listen if not is_loopback_endpoint(e)]
    if not t.trust_router:
        reasons += [f"connect {e}" for e in t.connect]
    if t.scouting:
        reasons.append("multicast scouting")
    return reasons



def _check_access(t: TelemetryConfig) -> None:
    """Who may command the robot must follow from the section (docs/telemetry.md); raises ValueError."""
    if t.trust_router:
        if not t.connect:
            raise ValueError("telemetry.trust_router: true trusts the routers in telemetry.connect, which is empty")
        exposed = [e for e in t.listen if not is_loopback_endpoint(e)] + (["multicast scouting"] if t.scouting else [])
        if exposed:
            raise ValueError(f"telemetry.trust_router: a robot that accepts whatever its router forwards must not be "
                             f"reachable otherwise; found {', '.join(exposed)}: listen on loopback only, "
                             f"scouting off")
        if t.operators:
            raise ValueError("telemetry.operators cannot be enforced with telemetry.trust_router: the robot opens the "
                             "link to the router, so its access control cannot tell who sent a command through it; "
                             "limit cmd/** to operators in the router's access_control and remove "
                             "telemetry.operators")
    remote = _remote_reasons(t)
    if remote:
        missing = []
        if not t.authenticated:
            missing.append("authentication (telemetry.auth.usrpwd with a dictionary_file, or telemetry.auth.tls "
                           "with certificates)")
        if not t.operators:
            missing.append("telemetry.operators (the user names or certificate common names allowed to send "
                           "commands; an access-control rule limits cmd/** to them)")
        if missing:
            hint = " (a router may expose the robot on any interface; telemetry.trust_router: true hands the " \
                   "decision to the router)" if any(r.startswith("connect ") for r in remote) else ""
            raise ValueError(
                f"remote access ({', '.join(remote)}) makes the robot reachable from other machines and needs "
                + " and ".join(missing)
                + f"; for local use only, listen on {DEFAULT_ENDPOINT}{hint}")
    if t.authenticated and not t.operators and not t.trust_router:
        raise ValueError("telemetry.operators: authentication is configured, so only operators may command the "
                         "robot (on every listener), and the list is empty: nobody could")
    if t.operators and not t.authenticated:
        raise ValueError("telemetry.operators: without telemetry.auth no peer is identified, so the list cannot be "
                         "enforced and anyone who connects could command the robot; configure telemetry.auth.usrpwd "
                         "or telemetry.auth.tls, or remove telemetry.operators")
    if t.shared_secret_file is not None:
        beyond = remote + [f"connect {e}" for e in t.connect if t.trust_router]
        if beyond:
            raise ValueError(f"telemetry.shared_secret_file: signed commands are for a robot reachable from this "
                             f"machine only (sender and robot must share its monotonic clock for the replay "
                             f"check); found {', '.join(beyond)}: use telemetry.auth and telemetry.operators instead")
        from vbnav.control.comms.command_auth import read_secret
        try:
            read_secret(t.shared_secret_file, check_owner=False)   # the owner: when the robot starts
        except ValueError as exc:
            raise ValueError(f"telemetry.shared_secret_file: {exc}") from None



def _check_live_view(t: TelemetryConfig) -> None:
    """The live view leaves this machine only where the zenoh side may (authenticated, with operators), over
    TLS, and with a way to tell operators apart (the WebSocket protocol carries no identity)."""
    lv = t.live_view
    if not lv.enabled:
        return
    if (lv.tls_certificate is None) != (lv.tls_private_key is None):
        raise ValueError("telemetry.live_view: tls_certificate and tls_private_key go together")
    if _is_loopback_host(lv.host):
        return
    missing = []
    if not (t.authenticated and t.operators):
        missing.append("remote access allowed by the telemetry section (telemetry.auth and telemetry.operators)")
    if lv.tls_certificate is None:
        missing.append("telemetry.live_view.tls_certificate and tls_private_key (wss://)")
    if lv.operator_token_file is None:
        missing.append("telemetry.live_view.operator_token_file (who may teleoperate)")
    if missing:
        raise ValueError(f"telemetry.live_view.host {lv.host!r} makes the live view reachable from other machines "
                         f"and needs " + " and ".join(missing) + "; for local use, keep host 127.0.0.1")


def _is_loopback_host(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


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
