"""What keeps a web page the operator happens to open from driving the robot through the gateway,
and the API docs served from the package.

- :class:`HostGuard`: DNS rebinding. A page at ``http://attacker.example:8080`` can rebind its
  name to 127.0.0.1; the browser then sends that page's requests to the gateway, same-origin as
  far as it knows, with ``Host: attacker.example:8080``. So the ``Host`` name (any port: an SSH
  tunnel or a port forward changes it) must be one the gateway serves
  (:meth:`~ovamos.services.gateway.config.GatewayConfig.host_names`) or an IP address literal (which
  cannot be rebound). A state-changing request (POST, PUT, PATCH, DELETE) that carries an
  ``Origin`` must also come from the gateway's own origin (the Origin's host and port are the
  Host header's) or from ``allowed_origins``: another site, or another local server on another
  port, cannot send the operator's browser to clear the e-stop. No Origin (curl, the CLI, a
  script) is no browser, and passes. Refusals are 403 with a JSON ``detail`` and counted.
- :class:`SecurityHeaders`: every answer says it may not be framed (clickjacking the E-STOP),
  may run only this origin's own scripts and styles (the page has no inline ones), must not be
  content-sniffed and must send no referrer.
- :func:`mount_docs`: Swagger UI from the ``fastapi-offline`` package's files, not a CDN (the
  robot's network has no internet, and a CDN script would run with the gateway's origin).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Callable
from importlib.resources import files
from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ovamos.services.gateway.config import GatewayConfig, host_name

UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
CONTENT_SECURITY_POLICY = ("default-src 'self'; img-src 'self' data:; object-src 'none'; "
                           "base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
"""Scripts, styles, fetches and fonts from this origin only, no inline script or style, no
eval; images also as ``data:`` URLs (the map raster and the page's empty favicon are)."""
SECURITY_HEADERS = [(b"x-frame-options", b"DENY"),
                    (b"content-security-policy", CONTENT_SECURITY_POLICY.encode()),
                    (b"x-content-type-options", b"nosniff"),
                    (b"referrer-policy", b"no-referrer")]
SWAGGER_UI = Path(str(files("fastapi_offline") / "static"))
"""Swagger UI's bundle and stylesheet, shipped in the fastapi-offline wheel."""


def _is_ip_literal(name: str) -> bool:
    """An IPv4 address, or an IPv6 one in brackets (as a Host header writes it)."""
    bracketed = name.startswith("[") and name.endswith("]")
    try:
        address = ipaddress.ip_address(name[1:-1] if bracketed else name)
    except ValueError:
        return False
    return bracketed == (address.version == 6)


class HostGuard:
    """403 for a request whose Host, or (for a write) whose Origin, is not this gateway's.

    A pure ASGI middleware: event streams pass through untouched. ``on_refused(scope)`` is
    called for each refusal (the app counts it)."""

    def __init__(self, app: ASGIApp, config: GatewayConfig, on_refused: Callable[[Scope], None]) -> None:
        self.app, self.on_refused = app, on_refused
        self.names = config.host_names()
        self.origins = frozenset(config.allowed_origins)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        host = headers.get(b"host", b"").decode("latin-1").strip().lower()
        problem = self._host_problem(host)
        if problem is None and scope["method"] in UNSAFE_METHODS and b"origin" in headers:
            problem = self._origin_problem(headers[b"origin"].decode("latin-1").strip().lower(), host)
        if problem is None:
            await self.app(scope, receive, send)
            return
        self.on_refused(scope)
        await JSONResponse({"detail": problem, "errors": []}, status_code=403)(scope, receive, send)

    def _host_problem(self, host: str) -> str | None:
        if not host:
            return "no Host header: send the gateway's address as Host (HTTP/1.1 requires it)"
        name = host_name(host)
        if name in self.names or _is_ip_literal(name):
            return None
        return (f"Host {host!r} is not a name this gateway serves (it serves "
                f"{', '.join(sorted(self.names))} and IP addresses); if clients really use that "
                "name, add it to allowed_hosts in the gateway's config")

    def _origin_problem(self, origin: str, host: str) -> str | None:
        scheme, _, netloc = origin.partition("://")
        if (scheme in ("http", "https") and netloc == host) or origin in self.origins:
            return None
        return (f"cross-origin {origin!r} may not change anything here: only the gateway's own page "
                f"(origin http://{host}) or allowed_origins in the gateway's config may; clients "
                "that are not browsers send no Origin")


class SecurityHeaders:
    """Adds :data:`SECURITY_HEADERS` to every HTTP answer (the page, its files, the API, errors),
    keeping any the route set itself. A pure ASGI middleware, so streams are not buffered."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []),
                                      *(h for h in SECURITY_HEADERS if h[0] not in present)]
            await send(message)

        await self.app(scope, receive, with_headers)


DOCS_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>OVAMOS gateway - API</title>
<link rel="icon" href="data:,">
<link rel="stylesheet" href="/docs/assets/swagger-ui.css">
<script src="/docs/assets/swagger-ui-bundle.js" defer></script>
<script src="/static/docs.js" defer></script>
</head>
<body><div id="swagger-ui"></div></body>
</html>
"""
"""Swagger UI without its usual inline start-up script (the CSP allows none): ``static/docs.js``
starts it, from ``/openapi.json``."""


def mount_docs(app: FastAPI, guard: Callable[..., Any]) -> None:
    """``/docs`` (Swagger UI) and ``/openapi.json`` behind ``guard``; Swagger UI's own files,
    which hold no data, at ``/docs/assets`` without it, like the page's."""
    app.mount("/docs/assets", StaticFiles(directory=SWAGGER_UI), name="docs-assets")

    @app.get("/docs", include_in_schema=False, dependencies=[Depends(guard)])
    def docs() -> HTMLResponse:
        return HTMLResponse(DOCS_PAGE, headers={"Cache-Control": "no-cache"})

    @app.get("/openapi.json", include_in_schema=False, dependencies=[Depends(guard)])
    def openapi() -> JSONResponse:
        return JSONResponse(app.openapi())
