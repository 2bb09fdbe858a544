"""Bad requests get a 4xx that says what is wrong, never a 5xx, and never cost an accepted task.

These run against the ASGI app in-process (the HTTP server adds nothing to
validation) with the Zenoh bus opened by the app's lifespan, over a real
router on loopback.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from ovamos.services.gateway.service import create_app
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from tests.gateway_mocks import ROBOT, gateway_config

JSON = {"content-type": "application/json"}


@pytest.fixture
def http(inproc_router: str, tmp_path) -> Iterator[TestClient]:
    config = gateway_config(tmp_path, robots=[ROBOT, "r2"], max_steps_limit=1000)
    app = create_app(config, lambda: Bus.open(build_config(connect=[inproc_router]), ROBOT, "gateway"))
    # runs the lifespan (opens and closes the bus); a loopback name, which the Host guard serves
    with TestClient(app, base_url="http://127.0.0.1") as client:
        yield client


BAD_BODIES = [
    ({"targets": []}, "must hold 1 to 16 names, got 0"),
    ({"targets": [f"t{i}" for i in range(17)]}, "must hold 1 to 16 names, got 17"),
    ({"targets": ["x" * 65]}, "must be 1 to 64 characters after trimming, got 65"),
    ({"targets": ["   "]}, "must be 1 to 64 characters after trimming, got 0"),
    ({"targets": ["chair", "tab\tle"]}, "target 1 ('tab\\tle') contains non-printable"),
    ({"targets": ["Chair", " chair "]}, "target 1 ('chair') duplicates 'Chair'"),
    ({"targets": ["Straße", "STRASSE"]}, "duplicates"),  # case folding, not just lower()
    ({"targets": "chair"}, "targets: Input should be a valid list"),
    ({"targets": ["chair", 3]}, "targets[1]: Input should be a valid string"),
    ({"targets": None}, "targets: Input should be a valid list"),
    ({}, "targets: Field required"),
    ({"targets": ["chair"], "robot_id": "mars"}, "unknown robot 'mars'; known: sim, r2"),
    ({"targets": ["chair"], "robot_id": 7}, "robot_id: Input should be a valid string"),
    ({"targets": ["chair"], "max_steps": 0}, "max_steps: Input should be greater than or equal to 1"),
    ({"targets": ["chair"], "max_steps": 1001}, "max_steps: must be at most 1000"),
    ({"targets": ["chair"], "max_steps": "500"}, "max_steps: Input should be a valid integer"),
    ({"targets": ["chair"], "max_steps": 2.5}, "max_steps: Input should be a valid integer"),
    ({"targets": ["chair"], "colour": "red"}, "colour: Extra inputs are not permitted"),
    (["chair"], "body is not a JSON object"),
    ("chair", "body is not a JSON object"),
]


@pytest.mark.parametrize("body,message", BAD_BODIES, ids=[str(i) for i in range(len(BAD_BODIES))])
def test_bad_bodies_are_422_with_a_message(http: TestClient, body: object, message: str) -> None:
    response = http.post("/v1/tasks", json=body)
    assert response.status_code == 422, response.text
    assert message in response.json()["detail"]
    assert response.json()["errors"], "each problem is listed"


@pytest.mark.parametrize("content,headers,message", [
    (b'{"targets": ["chair",', JSON, "body is not valid JSON"),
    (b"\xff\xfe not utf-8", JSON, "body is not valid JSON"),
    (b"", JSON, "body is missing"),
    (b"targets=chair", {"content-type": "application/x-www-form-urlencoded"}, "not sent as JSON"),
    (b'{"targets": ["chair"]}', {"content-type": "text/plain"}, "Content-Type: application/json"),
])
def test_malformed_payloads_are_4xx(http: TestClient, content: bytes, headers: dict[str, str],
                                    message: str) -> None:
    response = http.post("/v1/tasks", content=content, headers=headers)
    assert response.status_code == 422, response.text
    assert message in response.json()["detail"]


def test_oversized_bodies_are_413_declared_or_streamed(http: TestClient) -> None:
    huge = b'{"targets": ["' + b"x" * 70_000 + b'"]}'
    response = http.post("/v1/tasks", content=huge, headers=JSON)
    assert response.status_code == 413 and "at most 65536 bytes" in response.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: the limit applies as it streams in
        yield huge[:40_000]
        yield huge[40_000:]
    streamed = http.post("/v1/tasks", content=chunks(), headers=JSON)
    assert streamed.status_code == 413 and "at most 65536 bytes" in streamed.json()["detail"]
    assert http.post("/v1/tasks", json={"targets": ["chair"]}).status_code == 202


def test_refused_requests_are_counted_by_status(http: TestClient) -> None:
    def counters() -> dict[str, int]:
        return http.get("/v1/health").json()["counters"]
    before = counters()
    http.post("/v1/tasks", json={"targets": []})
    http.post("/v1/tasks", json={"targets": []})
    http.get("/v1/tasks/nope")
    http.post("/v1/tasks", content=b"x" * 70_000, headers=JSON)
    after = counters()
    for name, more in (("http_422", 2), ("http_404", 1), ("http_413", 1)):
        assert after[name] - before.get(name, 0) == more, name


def test_other_bad_requests(http: TestClient) -> None:
    assert http.get("/v1/tasks/nope").status_code == 404
    assert "no task 'nope'" in http.get("/v1/tasks/nope").json()["detail"]
    assert http.delete("/v1/tasks/nope").status_code == 404
    assert http.get("/v1/tasks/nope/events").status_code == 404
    bad_status = http.get("/v1/tasks", params={"status": "sleeping"})
    assert bad_status.status_code == 422 and "status" in bad_status.json()["detail"]
    assert http.get("/v1/tasks", params={"limit": 0}).status_code == 422
    assert http.get("/v1/robots/mars/map.png").status_code == 404
    assert http.put("/v1/tasks").status_code == 405
    assert http.get("/v1/nothing").status_code == 404


def test_the_gateway_keeps_serving_and_loses_no_accepted_task(http: TestClient) -> None:
    accepted = []
    for i, (body, _) in enumerate(BAD_BODIES * 2):
        assert http.post("/v1/tasks", json=body).status_code == 422
        if i % 5 == 0:
            response = http.post("/v1/tasks", json={"targets": [f"thing {i}"], "robot_id": "r2"})
            assert response.status_code == 202
            assert response.headers["location"] == f"/v1/tasks/{response.json()['id']}"
            accepted.append(response.json()["id"])
    listed = [t["id"] for t in http.get("/v1/tasks", params={"robot_id": "r2"}).json()["tasks"]]
    assert listed == accepted[::-1]  # newest first, none missing
    first = http.get(f"/v1/tasks/{accepted[0]}").json()
    assert first["status"] == "searching" and first["targets"] == ["thing 0"]
    second = http.get(f"/v1/tasks/{accepted[1]}").json()
    assert second["status"] == "queued" and second["queue_position"] == 1


def test_targets_are_trimmed_and_defaults_applied(http: TestClient) -> None:
    response = http.post("/v1/tasks", json={"targets": ["  potted plant ", "TV"]})
    assert response.status_code == 202
    task = http.get(response.headers["location"]).json()
    assert task["targets"] == ["potted plant", "TV"]
    assert task["robot_id"] == ROBOT and task["max_steps"] == 500
    assert task["remaining"] == task["targets"] and task["found"] == []
