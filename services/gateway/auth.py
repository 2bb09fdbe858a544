"""Bearer-token check for every API route (see :mod:`services.gateway.config` for when it applies)."""

from __future__ import annotations

import hmac
from collections.abc import Callable

from fastapi import HTTPException, Request, status


def bearer_guard(token: str | None) -> Callable[[Request], None]:
    """A FastAPI dependency: no-op without a token, else 401 unless ``Authorization: Bearer <token>``."""

    def check(request: Request) -> None:
        if token is None:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not given:
            raise _unauthorized("missing bearer token: send 'Authorization: Bearer <token>'")
        # constant-time comparison: response timing must not reveal how much of a guess matched
        if not hmac.compare_digest(given.strip().encode(), token.encode()):
            raise _unauthorized("wrong bearer token")

    return check


def _unauthorized(message: str) -> HTTPException:
    return HTTPException(status.HTTP_401_UNAUTHORIZED, message, headers={"WWW-Authenticate": "Bearer"})
