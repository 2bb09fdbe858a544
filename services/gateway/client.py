"""A small client of the gateway's HTTP API, for ``ovamos submit``, the demo and scripts.

Errors come back as :class:`GatewayError` carrying the gateway's own message
(e.g. "targets: must hold 1 to 16 names, got 17"), so a command line can show
it as is.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from typing import Any, Self

import httpx

from ovamos.services.gateway.models import TaskAccepted, TaskList, TaskView

STREAM_READ_TIMEOUT_S = 60.0  # > the gateway's keep-alive period on event streams


class GatewayError(RuntimeError):
    """The gateway answered with an error, or could not be reached."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class GatewayClient:
    """One gateway, one connection pool; use as a context manager."""

    def __init__(self, url: str, token: str | None = None, timeout_s: float = 10.0) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout_s)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _call(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise GatewayError(f"cannot reach the gateway at {self._http.base_url}: {exc}") from None
        if response.is_error:
            raise GatewayError(_detail(response), response.status_code)
        return response

    def submit(self, targets: list[str], robot_id: str | None = None,
               max_steps: int | None = None) -> TaskAccepted:
        body: dict[str, Any] = {"targets": targets}
        if robot_id is not None:
            body["robot_id"] = robot_id
        if max_steps is not None:
            body["max_steps"] = max_steps
        return TaskAccepted.model_validate(self._call("POST", "/v1/tasks", json=body).json())

    def get(self, task_id: str) -> TaskView:
        return TaskView.model_validate(self._call("GET", f"/v1/tasks/{task_id}").json())

    def tasks(self, robot_id: str | None = None, status: str | None = None,
              limit: int = 100) -> list[TaskView]:
        """Tasks, newest first."""
        params: dict[str, Any] = {"limit": limit}
        params.update({k: v for k, v in (("robot_id", robot_id), ("status", status)) if v is not None})
        return TaskList.model_validate(self._call("GET", "/v1/tasks", params=params).json()).tasks

    def cancel(self, task_id: str) -> TaskView:
        return TaskView.model_validate(self._call("DELETE", f"/v1/tasks/{task_id}").json())

    def health(self) -> dict[str, Any]:
        return self._call("GET", "/v1/health").json()

    def map_png(self, robot_id: str, layer: str | None = None) -> bytes:
        params = {"layer": layer} if layer is not None else {}
        return self._call("GET", f"/v1/robots/{robot_id}/map.png", params=params).content

    def wait(self, task_id: str, timeout_s: float, poll_s: float = 0.5,
             on_update: Callable[[TaskView], None] | None = None) -> TaskView:
        """Poll until the task ends; ``on_update`` sees each new state. TimeoutError after ``timeout_s``.

        Polling rather than the event stream: it rides over a gateway restart
        and honours the deadline exactly.
        """
        deadline = time.monotonic() + timeout_s
        last: TaskView | None = None
        while True:
            view = self.get(task_id)
            if on_update is not None and (last is None or view.updated_at != last.updated_at
                                          or view.status != last.status):
                on_update(view)
            last = view
            if view.final:
                return view
            if time.monotonic() > deadline:
                raise TimeoutError(f"task {task_id} still {view.status.value} after {timeout_s} s")
            time.sleep(poll_s)

    def follow(self, task_id: str) -> Iterator[TaskView]:
        """The task's Server-Sent Events, as views, until its final state."""
        timeout = httpx.Timeout(self._http.timeout.connect, read=STREAM_READ_TIMEOUT_S)
        try:
            with self._http.stream("GET", f"/v1/tasks/{task_id}/events", timeout=timeout) as response:
                if response.is_error:
                    response.read()
                    raise GatewayError(_detail(response), response.status_code)
                for event, data in parse_sse(response.iter_lines()):
                    if event == "task":
                        yield TaskView.model_validate_json(data)
        except httpx.HTTPError as exc:
            raise GatewayError(f"event stream of task {task_id} broke: {exc}") from None


def parse_sse(lines: Iterator[str]) -> Iterator[tuple[str, str]]:
    """(event, data) pairs of a text/event-stream; comments and unknown fields are skipped."""
    event, data = "message", []
    for line in lines:
        if not line:
            if data:
                yield event, "\n".join(data)
            event, data = "message", []
        elif line.startswith(":"):
            continue
        else:
            name, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if name == "event":
                event = value
            elif name == "data":
                data.append(value)


def _detail(response: httpx.Response) -> str:
    try:
        detail = response.json().get("detail")
    except (json.JSONDecodeError, AttributeError):
        detail = None
    return f"HTTP {response.status_code}: {detail or response.text[:200] or response.reason_phrase}"


# -- one-call helpers --------------------------------------------------------------------------
def submit(targets: list[str], gateway_url: str, token: str | None = None, robot_id: str | None = None,
           max_steps: int | None = None) -> TaskAccepted:
    with GatewayClient(gateway_url, token) as client:
        return client.submit(targets, robot_id, max_steps)


def get_task(task_id: str, gateway_url: str, token: str | None = None) -> TaskView:
    with GatewayClient(gateway_url, token) as client:
        return client.get(task_id)


def wait_task(task_id: str, gateway_url: str, token: str | None = None, timeout_s: float = 600.0,
              on_update: Callable[[TaskView], None] | None = None) -> TaskView:
    with GatewayClient(gateway_url, token) as client:
        return client.wait(task_id, timeout_s, on_update=on_update)
