"""The gateway's settings, validated at start-up so a risky or broken setup never serves.

The one rule enforced here rather than documented: a gateway reachable from
other machines (a non-loopback bind address) must have a bearer token, since
anyone who can reach it could otherwise drive the robot.
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path
from typing import Self

from pydantic import Field, SecretStr, field_validator, model_validator

from shared import keys
from shared.config import ServiceConfig

TOKEN_ENV = "OVAMOS_GATEWAY_TOKEN"
MAX_STEPS_LIMIT = 100_000  # TaskSpec's own bound: a larger value could not be sent


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable only from this machine (unknown names count as not)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


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
    max_body_bytes: int = Field(default=65536, ge=1024,
                                description="larger request bodies get 413 (a task is a short list)")

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
        return self

    def resolved_token(self) -> str | None:
        """The token clients must send: the config's, else the environment's, else none."""
        if self.token is not None and self.token.get_secret_value():
            return self.token.get_secret_value()
        return os.environ.get(TOKEN_ENV) or None

    @property
    def db_path(self) -> Path:
        return self.state_dir / "tasks.sqlite3"
