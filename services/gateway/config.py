"""The gateway's settings, validated at start-up so a risky or broken setup never serves.

The rules enforced here rather than documented: a gateway reachable from
other machines (a non-loopback bind address) must have a bearer token of at
least ``MIN_EXPOSED_TOKEN_CHARS`` characters, since anyone who can reach it
could otherwise drive the robot (or guess a short token); and no token may be
blank or padded with whitespace, which no client could send (the guard trims
what it receives), so it would lock everyone out.
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path
from typing import Self

from pydantic import Field, SecretStr, field_validator, model_validator

from ovamos.shared import keys
from ovamos.shared.config import ServiceConfig
from ovamos.shared.sessions import SessionSwitch

TOKEN_ENV = "OVAMOS_GATEWAY_TOKEN"
MAX_STEPS_LIMIT = 100_000  # TaskSpec's own bound: a larger value could not be sent
MIN_EXPOSED_TOKEN_CHARS = 16  # a non-loopback gateway's token: ~95 bits and up when random
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable only from this machine (unknown names count as not)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_name(host: str) -> str:
    """``host`` as the Host header writes it, lower case, without port or trailing dot: an IPv6
    address in brackets (``::1`` and ``[::1]:8080`` both give ``[::1]``)."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[:host.find("]") + 1] if "]" in host else host
    if host.count(":") > 1:  # a bare IPv6 address (a config's bind host)
        return f"[{host}]"
    return host.partition(":")[0].rstrip(".")


class GatewayConfig(ServiceConfig):
    host: str = Field(default="127.0.0.1", description="address to bind; non-loopback needs a token")
    port: int = Field(default=8080, ge=0, le=65535, description="0 picks a free port (tests)")
    robots: list[str] = Field(default=["sim"], min_length=1, description="robot ids tasks may name")
    state_dir: Path = Field(default=Path("state/gateway"), description="holds the SQLite task store")
    token: SecretStr | None = Field(default=None, description=f"bearer token; else ${TOKEN_ENV}")
    require_token: bool = Field(default=False, description="require the token on loopback too")
    republish_s: float = Field(default=1.0, gt=0, description="re-send the active TaskSpec this often")
    cancel_linger_s: float = Field(default=5.0, ge=0,
                                   description="keep re-sending a cancelled TaskSpec this long")
    default_max_steps: int = Field(default=500, ge=1, le=MAX_STEPS_LIMIT)
    max_steps_limit: int = Field(default=MAX_STEPS_LIMIT, ge=1, le=MAX_STEPS_LIMIT)
    map_timeout_s: float = Field(default=3.0, gt=0, description="wait this long for a map snapshot")
    health_timeout_s: float = Field(default=1.0, gt=0, description="wait this long for liveliness")
    sse_heartbeat_s: float = Field(default=15.0, gt=0, description="comment line on idle event streams")
    estop_confirm_s: float = Field(default=2.0, gt=0,
                                   description="an e-stop request waits this long for the driver "
                                               "to confirm the latch before answering 504")
    estop_resend_s: float = Field(default=0.2, gt=0, description="re-send an unconfirmed e-stop this often")
    session_switch: SessionSwitch = Field(
        default_factory=SessionSwitch, description="when a robot's driver states and odometry of a new "
        "odometry session are followed (its driver restarted): others are counted, never shown")
    max_body_bytes: int = Field(default=65536, ge=1024,
                                description="larger request bodies get 413 (a task is a short list)")
    allowed_hosts: list[str] = Field(
        default=[], description="names clients may send in the Host header (any port), besides the "
        "loopback names (127.0.0.1, localhost, [::1]) and the bind host, which are always allowed; "
        "IP address literals are always allowed too (DNS rebinding needs a name). Anything else is "
        "a 403, so a web page whose name was rebound to this address cannot drive the robot")
    allowed_origins: list[str] = Field(
        default=[], description="origins (scheme://host[:port]) whose pages may send POST, PUT, "
        "PATCH or DELETE besides the gateway's own (an Origin matching the Host header); other "
        "cross-origin writes are a 403. Requests without Origin (curl, scripts) are not affected")
    auth_failures_max: int = Field(
        default=20, ge=1, description="wrong tokens one client address may send within "
        "auth_failure_window_s; after that every guarded request from it gets 429 with Retry-After "
        "until the oldest failure leaves the window (a missing token does not count: the page "
        "asks for one on its first 401)")
    auth_failure_window_s: float = Field(default=60.0, gt=0,
                                         description="the window auth_failures_max counts in")

    @field_validator("allowed_hosts")
    @classmethod
    def _host_names(cls, names: list[str]) -> list[str]:
        out = []
        for name in names:
            host = host_name(name)
            if not host or any(c in name for c in "/ @"):
                raise ValueError(f"allowed_hosts: {name!r} is not a host name (like 'laptop.lan')")
            out.append(host)
        return out

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, origins: list[str]) -> list[str]:
        for origin in origins:
            scheme, sep, rest = origin.partition("://")
            if scheme not in ("http", "https") or not sep or not rest or "/" in rest:
                raise ValueError(f"allowed_origins: {origin!r} is not an origin like "
                                 "'http://laptop.lan:8080' (scheme, host, optional port, no path)")
        return [o.lower() for o in origins]

    @field_validator("robots")
    @classmethod
    def _robot_ids(cls, robots: list[str]) -> list[str]:
        for robot in robots:
            keys.check_chunk(robot, "robot id")
        if len(set(robots)) != len(robots):
            raise ValueError("robot ids must be unique")
        return robots

    @model_validator(mode="after")
    def _token_when_exposed(self) -> Self:
        if self.default_max_steps > self.max_steps_limit:
            raise ValueError("default_max_steps must not exceed max_steps_limit")
        if self.resolved_token() is None and (self.require_token or not is_loopback(self.host)):
            why = "require_token is set" if self.require_token else f"host {self.host!r} is not loopback"
            raise ValueError(f"a bearer token is required ({why}): set token in the config "
                             f"or the {TOKEN_ENV} environment variable")
        token = self.resolved_token()
        if token is not None:
            where = f"the token (config token or {TOKEN_ENV})"
            if not token.strip():
                raise ValueError(f"{where} is blank: a whitespace-only token could never be sent, "
                                 "so every request would be refused; set a real one or none")
            if token != token.strip():
                raise ValueError(f"{where} starts or ends with whitespace, which clients cannot "
                                 "send in a header; remove it")
            if not is_loopback(self.host) and len(token) < MIN_EXPOSED_TOKEN_CHARS:
                raise ValueError(
                    f"{where} has {len(token)} characters: a gateway on non-loopback host "
                    f"{self.host!r} needs at least {MIN_EXPOSED_TOKEN_CHARS} (e.g. the output of "
                    "`python3 -c 'import secrets; print(secrets.token_urlsafe(24))'`)")
        return self

    def resolved_token(self) -> str | None:
        """The token clients must send: the config's, else the environment's, else none."""
        if self.token is not None and self.token.get_secret_value():
            return self.token.get_secret_value()
        return os.environ.get(TOKEN_ENV) or None

    def host_names(self) -> frozenset[str]:
        """The names the Host header may carry (lower case, no port); see ``allowed_hosts``."""
        return frozenset((*LOOPBACK_NAMES, host_name(self.host), *self.allowed_hosts))

    @property
    def db_path(self) -> Path:
        return self.state_dir / "tasks.sqlite3"
