"""The HTTP surface of the gateway: ``http_app(config, lifespan)``, its routes, guards and errors.

The lifespan (:func:`ovamos.services.gateway.service.create_app`'s) puts the
:class:`~ovamos.services.gateway.routes.Gateway` the routes use in ``app.state.gateway``;
this module adds what every request goes through: the bearer token, the Host guard, the
body limit, the security headers, and one readable error shape for every 4xx.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractAsyncContextManager

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ovamos.services.gateway.auth import DOCS_REALM, AuthFailures, bearer_guard
from ovamos.services.gateway.config import GatewayConfig
from ovamos.services.gateway.page import mount_page
from ovamos.services.gateway.robot_routes import router as robot_router
from ovamos.services.gateway.routes import router
from ovamos.services.gateway.security import HostGuard, SecurityHeaders, mount_docs

Lifespan = Callable[[FastAPI], AbstractAsyncContextManager[None]]

DESCRIPTION = """Submit multi-object search tasks to a robot and follow them.

One task per robot runs at a time; further submissions for that robot are queued
and start, in order, when the running one ends (done, failed or cancelled).
When a token is configured, every `/v1` route needs `Authorization: Bearer <token>`.
`GET /` is the operator's page (submit, watch the map, E-STOP); it asks for the token when
one is needed. These docs and `/openapi.json` need the token too (a browser asks for it: any user
name, the token as password). Requests must name the gateway in `Host`, and a browser's writes
must come from the gateway's own page (else 403).
"""


def http_app(config: GatewayConfig, lifespan: Lifespan) -> FastAPI:
    """The routes serving ``config``, guarded; ``lifespan`` sets ``app.state.gateway`` up."""
    app = FastAPI(title="OVAMOS gateway", version="1", description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None, openapi_url=None)  # mount_docs serves them
    failures = AuthFailures(config.auth_failures_max, config.auth_failure_window_s)
    guard = [Depends(bearer_guard(config.resolved_token(), failures))]
    app.include_router(router, dependencies=guard)
    app.include_router(robot_router, dependencies=guard)
    mount_page(app)
    mount_docs(app, bearer_guard(config.resolved_token(), failures, basic_realm=DOCS_REALM))
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    app.add_middleware(BodyLimit, limit=config.max_body_bytes)
    # outermost last: every answer gets the headers, and a forged Host is refused before anything
    app.add_middleware(HostGuard, config=config, on_refused=lambda scope: _count_rejected(scope["app"], 403))
    app.add_middleware(SecurityHeaders)
    return app


class BodyLimit:
    """413 for a request body over ``limit`` bytes, declared or streamed.

    Without it a client could make the gateway read any amount into memory before validation
    rejects it. A pure ASGI middleware, so event streams pass through untouched; a streamed
    body that runs over raises an HTTPException, which the app's handler answers like any
    other error."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length", b"0")
        if not declared.isdigit() or int(declared) > self.limit:
            _count_rejected(scope["app"], 413)
            await JSONResponse({"detail": self._message(), "errors": []}, status_code=413)(scope, receive, send)
            return
        received = 0

        async def limited() -> Message:
            nonlocal received
            message = await receive()
            received += len(message.get("body", b""))
            if received > self.limit:
                raise StarletteHTTPException(413, self._message())
            return message

        await self.app(scope, limited, send)

    def _message(self) -> str:
        return f"request body too large or of unknown length: at most {self.limit} bytes"


def _where(loc: tuple[object, ...]) -> str:
    """``("body", "targets", 2)`` -> ``targets[2]``; the body itself is ``body``."""
    parts = list(loc[1:] if loc and loc[0] == "body" and len(loc) > 1 else loc)
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "body"


# what to send, by route: a body-level error says it (the task body unless another is named)
BODY_EXAMPLES = {"/v1/robots/{robot_id}/estop/clear": '{"confirm": true}'}
BODY_EXAMPLE = '{"targets": ["chair", "fridge"]}'


def _problem(error: dict, sent_json: bool, example: str = BODY_EXAMPLE) -> dict[str, str]:
    """One validation error as ``{"field", "message"}``; the body-level ones say what to send."""
    kind, loc = error.get("type"), tuple(error.get("loc", ()))
    if kind == "json_invalid":
        detail = (error.get("ctx") or {}).get("error")
        return {"field": "body", "message": f"body is not valid JSON{f' ({detail})' if detail else ''}"}
    if loc == ("body",):
        what = ("missing" if kind == "missing" else "not a JSON object" if sent_json
                else "not sent as JSON (Content-Type: application/json)")
        return {"field": "body", "message": f"body is {what}: send a JSON object like {example}"}
    msg = str(error.get("msg", "invalid")).removeprefix("Value error, ")
    return {"field": _where(loc), "message": f"{_where(loc)}: {msg}"}


def _count_rejected(app: FastAPI, status_code: int) -> None:
    gateway = getattr(app.state, "gateway", None)  # None only while starting or stopping
    if gateway is not None:
        gateway.manager.count_rejected_request(status_code)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with one readable sentence (``detail``) and one entry per problem (``errors``)."""
    _count_rejected(request.app, 422)
    sent_json = "json" in request.headers.get("content-type", "")
    route = request.scope.get("route")
    example = BODY_EXAMPLES.get(getattr(route, "path", ""), BODY_EXAMPLE)
    errors = [_problem(e, sent_json, example) for e in exc.errors()]
    detail = "; ".join(e["message"] for e in errors) or "invalid request"
    return JSONResponse({"detail": detail, "errors": errors}, status_code=422)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    _count_rejected(request.app, exc.status_code)
    return JSONResponse({"detail": str(exc.detail), "errors": []}, status_code=exc.status_code,
                        headers=getattr(exc, "headers", None))
