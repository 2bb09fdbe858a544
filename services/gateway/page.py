"""The operator's page: ``GET /`` and its files under ``/static``, shipped in the package.

Plain HTML, CSS and JavaScript with no build step and nothing fetched from elsewhere (the
robot's network has no internet): the page talks only to the ``/v1`` API. Its files need no
token (they hold no data); the page asks for the token when the API answers 401.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).with_name("static")


def mount_page(app: FastAPI) -> None:
    """Serve the page at ``/`` and its scripts and styles at ``/static``."""
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})
