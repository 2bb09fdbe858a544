"""The gateway through a real uvicorn server: event streams, the map picture, health, auth,
the client helpers, and start-up refusals."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from ovamos.services.gateway import client as gw_client
from ovamos.services.gateway.client import GatewayClient, GatewayError
from ovamos.services.gateway.config import TOKEN_ENV, GatewayConfig
from ovamos.services.gateway.models import TaskView
from ovamos.services.gateway.service import GatewayService
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import FoundObject, TaskStatus
from ovamos.shared.service import ServiceConfigError, load_config, run_service
from tests.gateway_mocks import ODOM_SESSION, ROBOT, MockMapping, MockPlanner, RunningGateway, gateway_config
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

CHAIR = FoundObject(label="chair", x=0.6, y=1.4, step=2)


class Follower:
    """Reads a task's event stream on a thread, as a browser or ``curl -N`` would."""

    def __init__(self, url: str, task_id: str) -> None:
        self.views: list[TaskView] = []
        self.error: Exception | None = None
        self._thread = threading.Thread(target=self._run, args=(url, task_id), daemon=True)
        self._thread.start()

    def _run(self, url: str, task_id: str) -> None:
        try:
            with GatewayClient(url) as client:
                self.views.extend(client.follow(task_id))
        except Exception as exc:  # surfaced by the test
            self.error = exc

    def finished(self, timeout: float = 20.0) -> bool:
        self._thread.join(timeout)
        return not self._thread.is_alive()


def test_the_event_stream_delivers_progress_and_ends(gateway: RunningGateway, api: GatewayClient,
                                                     planner: MockPlanner) -> None:
    task = api.submit(["chair", "fridge"])
    follower = Follower(gateway.url, task.id)
    wait_for(lambda: follower.views, what="the stream's first event")
    assert follower.views[0].status is TaskStatus.SEARCHING and follower.views[0].steps == 0
    wait_for(lambda: planner.report(task.id, TaskStatus.SEARCHING, ["chair", "fridge"], steps=2,
                                    found=(CHAIR,)) or any(v.steps == 2 for v in follower.views),
             what="progress on the stream")
    seen = next(v for v in follower.views if v.steps == 2)
    assert seen.found == [CHAIR] and seen.remaining == ["fridge"]
    wait_for(lambda: planner.report(task.id, TaskStatus.DONE, ["chair", "fridge"], steps=4,
                                    found=(CHAIR,)) or not follower._thread.is_alive(),
             what="the stream to end")
    assert follower.finished() and follower.error is None
    assert follower.views[-1].status is TaskStatus.DONE and follower.views[-1].steps == 4

    # a finished task's stream gives its final state and ends
    with GatewayClient(gateway.url) as client:
        assert [v.status for v in client.follow(task.id)] == [TaskStatus.DONE]


def test_raw_sse_format_and_keepalive(gateway: RunningGateway, api: GatewayClient) -> None:
    task = api.submit(["cup"])
    with httpx.stream("GET", f"{gateway.url}/v1/tasks/{task.id}/events", timeout=10) as response:
        assert response.headers["content-type"].startswith("text/event-stream")
        lines = response.iter_lines()
        assert next(lines) == "event: task"
        assert next(lines).startswith('data: {"id":"' + task.id)
        assert next(lines) == ""
        assert next(lines) == ": keep-alive"  # the config's 0.5 s heartbeat on a quiet task


def test_map_png_from_the_mapping_service(inproc_router: str, gateway: RunningGateway,
                                          api: GatewayClient, planner: MockPlanner, tmp_path: Path) -> None:
    response = httpx.get(f"{gateway.url}/v1/robots/{ROBOT}/map.png", timeout=10)
    assert response.status_code == 503 and "no mapping service answered" in response.json()["detail"]
    task = api.submit(["chair"])
    wait_for(lambda: planner.report(task.id, TaskStatus.SEARCHING, ["chair"], steps=1, x=0.5, y=0.5)
             or api.get(task.id).position, what="a reported position (the path drawn on the map)")
    mapping = MockMapping(inproc_router)
    try:
        png = wait_for(lambda: (r := httpx.get(f"{gateway.url}/v1/robots/{ROBOT}/map.png", timeout=10))
                       .status_code == 200 and r, what="the map")
        assert png.headers["content-type"] == "image/png" and png.content[:8] == b"\x89PNG\r\n\x1a\n"
        assert png.headers["x-ovamos-odom-session"] == ODOM_SESSION  # which odometry frame it is in
        assert api.get(task.id).odom_session == ODOM_SESSION          # the planner's latest report's
        image = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 20 and image.shape[1] > 20
        layer = httpx.get(f"{gateway.url}/v1/robots/{ROBOT}/map.png", params={"layer": "chair"})
        assert layer.status_code == 200
        bad = httpx.get(f"{gateway.url}/v1/robots/{ROBOT}/map.png", params={"layer": "piano"})
        assert bad.status_code == 422 and "unknown value layer 'piano'" in bad.json()["detail"]
        # `ovamos map` draws what the page's picture draws (the task's path and targets), for the
        # gateway's one robot unless told which
        drawn = _ovamos("map", "--gateway", gateway.url, "--out", str(tmp_path / "map.png"))
        assert drawn.returncode == 0, drawn.stderr
        assert (tmp_path / "map.png").read_bytes() == httpx.get(f"{gateway.url}/v1/robots/{ROBOT}/map.png").content
        piano = _ovamos("map", "--gateway", gateway.url, "--layer", "piano", "--out", str(tmp_path / "x.png"))
        assert piano.returncode == 2 and "unknown value layer 'piano'" in " ".join(piano.stderr.split())
    finally:
        mapping.close()


def _ovamos(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ovamos.cli", *args], capture_output=True, text=True, timeout=60)


def test_health_lists_live_services_per_robot(inproc_router: str, api: GatewayClient,
                                              planner: MockPlanner) -> None:
    mapping = MockMapping(inproc_router)
    try:
        def services() -> set[str]:
            return {s["service"] for s in api.health()["robots"][ROBOT]["services"]}

        wait_for(lambda: {"gateway", "mock-planner", "mock-mapping"} <= services(), what="3 services")
    finally:
        mapping.close()
    wait_for(lambda: "mock-mapping" not in services(), what="a stopped service to disappear")
    assert api.health()["robots"][ROBOT]["active_task"] is None


def test_auth_with_a_token(inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(tmp_path, token="s3cret"))
    try:
        url = f"{running.url}/v1/tasks"
        missing = httpx.post(url, json={"targets": ["chair"]})
        assert missing.status_code == 401 and "missing bearer token" in missing.json()["detail"]
        assert missing.headers["www-authenticate"] == "Bearer"
        wrong = httpx.get(url, headers={"Authorization": "Bearer guess"})
        assert wrong.status_code == 401 and "wrong bearer token" in wrong.json()["detail"]
        assert httpx.get(url, headers={"Authorization": "Basic s3cret"}).status_code == 401
        # a bad body without a token is refused for the token, not validated
        assert httpx.post(url, json={"targets": []}).status_code == 401
        assert httpx.get(f"{running.url}/docs").status_code == 401  # the docs are guarded too
        assert httpx.get(f"{running.url}/openapi.json", auth=("any", "s3cret")).status_code == 200
        accepted = gw_client.submit(["chair"], running.url, token="s3cret")
        assert gw_client.get_task(accepted.id, running.url, token="s3cret").targets == ["chair"]
        with pytest.raises(GatewayError) as info:
            gw_client.get_task(accepted.id, running.url)
        assert info.value.status == 401
    finally:
        running.close()


def test_without_a_token_loopback_needs_none(api: GatewayClient) -> None:
    assert api.submit(["chair"]).status is TaskStatus.SEARCHING


def test_a_token_is_required_off_loopback(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    path = tmp_path / "gw.toml"
    path.write_text('host = "0.0.0.0"\n')
    with pytest.raises(ServiceConfigError, match=f"token is required.*{TOKEN_ENV}"):
        load_config(GatewayService, path)
    with pytest.raises(ServiceConfigError, match="require_token"):
        load_config(GatewayService, None, {"require_token": True})
    monkeypatch.setenv(TOKEN_ENV, "from-env-16-chars")  # off loopback: at least 16 characters
    config = load_config(GatewayService, path)
    assert isinstance(config, GatewayConfig) and config.resolved_token() == "from-env-16-chars"
    assert "from-env" not in repr(load_config(GatewayService, None, {"token": "from-env"}))


@pytest.mark.parametrize("overrides,message", [
    ({"robots": []}, "robots"), ({"robots": ["a/b"]}, "not usable in a Zenoh key"),
    ({"robots": ["a", "a"]}, "unique"), ({"prot": 1}, "prot"), ({"republish_s": 0}, "republish_s"),
])
def test_bad_configs_are_refused(overrides: dict, message: str) -> None:
    with pytest.raises(ServiceConfigError, match=message):
        load_config(GatewayService, None, overrides)


def test_a_taken_port_stops_the_service_with_a_clear_error(inproc_router: str, gateway: RunningGateway,
                                                           tmp_path: Path) -> None:
    taken = gateway_config(tmp_path / "other", port=gateway.config.port)
    with pytest.raises(ServiceConfigError, match=f"cannot serve on 127.0.0.1:{taken.port}: .*in use"):
        run_service(GatewayService, build_config(connect=[inproc_router]), taken, robot_id=ROBOT,
                    instance="1", stop=threading.Event())


def test_submit_and_wait_helpers(gateway: RunningGateway, planner: MockPlanner) -> None:
    accepted = gw_client.submit(["chair"], gateway.url, robot_id=ROBOT, max_steps=20)
    assert accepted.location == f"/v1/tasks/{accepted.id}"
    updates: list[TaskView] = []
    stop = threading.Event()

    def fake_planner_run() -> None:  # steps until the waiter has seen the task end
        step = 0
        while not stop.wait(0.1):
            step += 1
            final = step >= 5
            planner.report(accepted.id, TaskStatus.DONE if final else TaskStatus.SEARCHING, ["chair"],
                           steps=min(step, 5), found=(CHAIR,) if final else ())

    thread = threading.Thread(target=fake_planner_run, daemon=True)
    thread.start()
    try:
        final = gw_client.wait_task(accepted.id, gateway.url, timeout_s=30, on_update=updates.append)
    finally:
        stop.set()
        thread.join(5)
    assert final.status is TaskStatus.DONE and final.found == [CHAIR]
    assert updates[-1].status is TaskStatus.DONE and len(updates) >= 2
    with pytest.raises(TimeoutError, match="still searching"):
        gw_client.wait_task(gw_client.submit(["cup"], gateway.url).id, gateway.url, timeout_s=0.3)
    with pytest.raises(GatewayError, match="must hold 1 to 16 names"):
        gw_client.submit([], gateway.url)


def test_open_event_streams_do_not_hold_up_shutdown(inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(tmp_path, sse_heartbeat_s=60))
    try:
        task = gw_client.submit(["chair"], running.url)
        follower = Follower(running.url, task.id)
        wait_for(lambda: follower.views, what="the stream's first event")
    finally:
        running.close()  # asserts the service thread ended
    assert follower.finished(), "the stream ended with the gateway"
    assert [v.status for v in follower.views] == [TaskStatus.SEARCHING]
