"""Bearer-token check for every API route (see :mod:`ovamos.services.gateway.config` for when it applies)."""

from __future__ import annotations

import base64
import binascii
import hmac
import math
import threading
import time
from collections import deque
from collections.abc import Callable

from fastapi import HTTPException, Request, status

DOCS_REALM = 'Basic realm="OVAMOS gateway docs", charset="UTF-8"'
"""The challenge of the docs' 401: a browser can send no bearer token to a page it navigates to,
so ``/docs`` and ``/openapi.json`` also take the token as an HTTP Basic password (any user name),
which makes the browser ask for it."""


class AuthFailures:
    """Wrong tokens per client address in a sliding window, so a guesser is slowed to
    ``limit`` tries per ``window_s`` (429 with Retry-After meanwhile) instead of trying at line
    rate. Bounded: at most ``max_addresses`` addresses are remembered (the stalest go first).
    Called from FastAPI's worker threads, hence the lock (held for no I/O)."""

    def __init__(self, limit: int, window_s: float, max_addresses: int = 4096) -> None:
        self.limit, self.window_s, self.max_addresses = limit, window_s, max_addresses
        self._lock = threading.Lock()
        self._failures: dict[str, deque[float]] = {}

    def retry_after(self, address: str) -> int | None:
        """Seconds until ``address`` may try again, None when it may now."""
        now = time.monotonic()
        with self._lock:
            times = self._failures.get(address)
            if times is None:
                return None
            while times and times[0] <= now - self.window_s:
                times.popleft()
            if len(times) < self.limit:
                return None
            return max(1, math.ceil(times[-self.limit] + self.window_s - now))

    def record(self, address: str) -> None:
        now = time.monotonic()
        with self._lock:
            times = self._failures.pop(address, None) or deque(maxlen=self.limit)
            self._failures[address] = times  # re-inserted: the dict's order is staleness
            times.append(now)
            while len(self._failures) > self.max_addresses:
                del self._failures[next(iter(self._failures))]


def bearer_guard(token: str | None, failures: AuthFailures, *,
                 basic_realm: str | None = None) -> Callable[[Request], None]:
    """A FastAPI dependency: no-op without a token, else 401 unless ``Authorization: Bearer
    <token>`` (or, with ``basic_realm``, HTTP Basic with the token as password); 429 for an
    address that sent too many wrong tokens (``failures``), whatever it sends now."""
    challenge = basic_realm or "Bearer"

    def check(request: Request) -> None:
        if token is None:
            return
        address = request.client.host if request.client else "unknown"
        wait = failures.retry_after(address)
        if wait is not None:
            raise HTTPException(status.HTTP_429_TOO_MANY_REQUESTS,
                                f"too many wrong tokens from {address}: try again in {wait} s",
                                headers={"Retry-After": str(wait)})
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if basic_realm is not None and scheme.lower() == "basic":
            given = _basic_password(given)
        elif scheme.lower() != "bearer":
            given = ""
        if not given.strip():
            raise _unauthorized("missing bearer token: send 'Authorization: Bearer <token>'", challenge)
        # constant-time comparison: response timing must not reveal how much of a guess matched
        if not hmac.compare_digest(given.strip().encode(), token.encode()):
            failures.record(address)
            raise _unauthorized("wrong bearer token", challenge)

    return check


def _basic_password(credentials: str) -> str:
    try:
        decoded = base64.b64decode(credentials.strip(), validate=True).decode()
    except (binascii.Error, UnicodeDecodeError):
        return ""
    return decoded.partition(":")[2]


def _unauthorized(message: str, challenge: str) -> HTTPException:
    return HTTPException(status.HTTP_401_UNAUTHORIZED, message, headers={"WWW-Authenticate": challenge})
