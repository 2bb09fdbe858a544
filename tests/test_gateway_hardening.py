"""The gateway against a hostile web page and a token guesser (issue 33, findings 2 and 8), through a
real uvicorn server on 127.0.0.1 with its peers mocked over real Zenoh.

Each attack is reproduced first as it was sent (a forged ``Host`` after DNS rebinding, a
cross-origin write, a flood of wrong tokens) and the test checks that it is refused and that
nothing happened; then that the legitimate request still works."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from ovamos.services.gateway.config import TOKEN_ENV, GatewayConfig
from ovamos.services.gateway.service import GatewayService
from ovamos.shared.service import ServiceConfigError, load_config
from tests.gateway_mocks import ROBOT, MockDriver, MockPlanner, RunningGateway, gateway_config
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

FORGED = {"Host": "attacker.example:8080"}  # what the rebound page's requests carry
TOKEN = "a-token-of-24-characters"


@pytest.fixture
def driver(inproc_router: str) -> Iterator[MockDriver]:
    mock = MockDriver(inproc_router)
    yield mock
    mock.close()


def _counter(url: str, name: str, headers: dict[str, str] | None = None) -> int:
    return httpx.get(f"{url}/v1/health", headers=headers, timeout=10).json()["counters"].get(name, 0)


def test_a_forged_host_can_neither_clear_nor_engage_the_estop(gateway: RunningGateway,
                                                              driver: MockDriver) -> None:
    url = f"{gateway.url}/v1/robots/{ROBOT}"
    wait_for(lambda: httpx.get(url, timeout=10).json()["driver"] is not None, what="the driver's state")
    engaged = httpx.post(f"{url}/estop", json={"reason": "operator"}, timeout=10)
    assert engaged.status_code == 200 and engaged.json()["driver"]["estop_latched"] is True
    before = _counter(gateway.url, "http_403")

    # the rebound page clears the e-stop: refused, and the driver is told nothing
    cleared = httpx.post(f"{url}/estop/clear", json={"confirm": True}, headers=FORGED, timeout=10)
    assert cleared.status_code == 403
    assert "'attacker.example:8080' is not a name this gateway serves" in cleared.json()["detail"]
    assert "allowed_hosts" in cleared.json()["detail"]
    forged_engage = httpx.post(f"{url}/estop", json={"reason": "attacker"}, headers=FORGED, timeout=10)
    assert forged_engage.status_code == 403
    # a request after them reaches the driver (same publisher, in order): had the forged ones been
    # sent, they would have arrived before it
    assert httpx.post(f"{url}/estop", json={"reason": "sentinel"}, timeout=10).status_code == 200
    wait_for(lambda: any(r.reason == "sentinel" for r in driver.requests), what="the sentinel request")
    assert [r for r in driver.requests if r.reason == "attacker" or not r.engage] == []
    assert driver.latched and httpx.get(url, timeout=10).json()["driver"]["estop_latched"] is True
    assert _counter(gateway.url, "http_403") == before + 2  # counted like other refusals

    # the same requests by the names the gateway serves still work
    for host in (f"localhost:{gateway.config.port}", f"127.0.0.1:{gateway.config.port}", "localhost"):
        response = httpx.post(f"{url}/estop/clear", json={"confirm": True}, headers={"Host": host},
                              timeout=10)
        assert response.status_code == 200 and response.json()["driver"]["estop_latched"] is False


def test_a_forged_host_cannot_submit_or_read(gateway: RunningGateway, planner: MockPlanner) -> None:
    submitted = httpx.post(f"{gateway.url}/v1/tasks", json={"targets": ["chair"]}, headers=FORGED, timeout=10)
    assert submitted.status_code == 403
    assert httpx.get(f"{gateway.url}/v1/tasks", headers=FORGED, timeout=10).status_code == 403
    assert httpx.get(f"{gateway.url}/", headers=FORGED, timeout=10).status_code == 403  # nor the page
    assert httpx.get(f"{gateway.url}/v1/tasks", timeout=10).json()["tasks"] == []
    task = httpx.post(f"{gateway.url}/v1/tasks", json={"targets": ["sofa"]}, timeout=10)
    assert task.status_code == 202
    wait_for(lambda: planner.specs(task.json()["id"]), what="the legitimate task's TaskSpec")
    assert {s.task_id for s in planner.specs()} == {task.json()["id"]}  # the forged one never went out
    # an IP address literal cannot be rebound: accepted, as a tunnel or port forward would send it
    assert httpx.get(f"{gateway.url}/v1/tasks", headers={"Host": "10.1.2.3:9000"}).status_code == 200
    assert httpx.get(f"{gateway.url}/v1/tasks", headers={"Host": "[::1]:9000"}).status_code == 200
    assert httpx.get(f"{gateway.url}/v1/tasks", headers={"Host": "localhost.:1"}).status_code == 200
    for host in ("localhost.attacker.example", "127.0.0.1.nip.io", "[::1"):
        assert httpx.get(f"{gateway.url}/v1/tasks", headers={"Host": host}).status_code == 403, host


def test_cross_origin_writes_are_refused_and_same_origin_ones_are_not(gateway: RunningGateway) -> None:
    url, own = f"{gateway.url}/v1/tasks", f"http://127.0.0.1:{gateway.config.port}"
    for origin in ("http://attacker.example", "http://127.0.0.1:9999", "null", f"ftp://127.0.0.1:{gateway.config.port}"):
        refused = httpx.post(url, json={"targets": ["chair"]}, headers={"Origin": origin}, timeout=10)
        assert refused.status_code == 403, origin
        assert "may not change anything here" in refused.json()["detail"]
    assert httpx.get(url, timeout=10).json()["tasks"] == []
    # the page's own writes (the browser sends its origin), and clients that send none
    own_write = httpx.post(url, json={"targets": ["chair"]}, headers={"Origin": own}, timeout=10)
    assert own_write.status_code == 202
    task_id = own_write.json()["id"]
    assert httpx.delete(f"{url}/{task_id}", headers={"Origin": "http://attacker.example"}).status_code == 403
    assert httpx.get(f"{url}/{task_id}").json()["status"] == "searching"
    assert httpx.delete(f"{url}/{task_id}", headers={"Origin": own}).status_code == 200
    assert httpx.post(url, json={"targets": ["cup"]}, timeout=10).status_code == 202  # no Origin: curl
    # reads carry no state change: a foreign Origin on a GET is the browser's business (CORS)
    assert httpx.get(url, headers={"Origin": "http://attacker.example"}, timeout=10).status_code == 200


def test_configured_names_and_origins_are_accepted(inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(
        tmp_path, allowed_hosts=["Laptop.LAN"], allowed_origins=["http://tools.lan:3000"]))
    try:
        url = f"{running.url}/v1/tasks"
        assert httpx.get(url, headers={"Host": "laptop.lan:8080"}, timeout=10).status_code == 200
        assert httpx.post(url, json={"targets": ["chair"]}, headers={"Host": "laptop.lan:8080",
                          "Origin": "http://laptop.lan:8080"}, timeout=10).status_code == 202
        assert httpx.post(url, json={"targets": ["cup"]}, headers={"Origin": "http://tools.lan:3000"},
                          timeout=10).status_code == 202
        assert httpx.get(url, headers={"Host": "other.lan"}, timeout=10).status_code == 403
    finally:
        running.close()
    with pytest.raises(ValueError, match="not an origin like"):
        GatewayConfig(allowed_origins=["http://tools.lan/path"])
    with pytest.raises(ValueError, match="not a host name"):
        GatewayConfig(allowed_hosts=["http://laptop"])


def test_every_answer_carries_the_security_headers(gateway: RunningGateway) -> None:
    answers = {
        "page": httpx.get(f"{gateway.url}/"),
        "script": httpx.get(f"{gateway.url}/static/app.js"),
        "api": httpx.get(f"{gateway.url}/v1/tasks"),
        "404": httpx.get(f"{gateway.url}/v1/tasks/nope"),
        "422": httpx.post(f"{gateway.url}/v1/tasks", json={"targets": []}),
        "403": httpx.get(f"{gateway.url}/v1/tasks", headers=FORGED),
        "docs": httpx.get(f"{gateway.url}/docs"),
    }
    assert answers["404"].status_code == 404 and answers["422"].status_code == 422
    for what, response in answers.items():
        headers = response.headers
        assert headers["x-frame-options"] == "DENY", what
        assert headers["x-content-type-options"] == "nosniff", what
        assert headers["referrer-policy"] == "no-referrer", what
        csp = headers["content-security-policy"]
        assert "frame-ancestors 'none'" in csp and "default-src 'self'" in csp, what
        assert "unsafe-inline" not in csp and "unsafe-eval" not in csp, what
    with httpx.stream("GET", f"{gateway.url}/v1/tasks/x/events") as stream:  # a 404 stream answer
        assert stream.headers["x-frame-options"] == "DENY"


def test_the_page_has_no_inline_script_or_style_for_the_policy_to_block() -> None:
    from ovamos.services.gateway.page import STATIC
    from ovamos.services.gateway.security import DOCS_PAGE
    for text in [*(p.read_text() for p in STATIC.glob("*.html")), DOCS_PAGE]:
        assert "<style" not in text and " style=" not in text and not re.search(r"\son[a-z]+=", text)
        scripts = text.split("<script")[1:]
        assert scripts and all(s.lstrip().startswith("src=") for s in scripts)


def test_the_docs_come_from_the_package_and_need_the_token(inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(tmp_path, token=TOKEN))
    try:
        docs = f"{running.url}/docs"
        refused = httpx.get(docs, timeout=10)
        assert refused.status_code == 401 and refused.headers["www-authenticate"].startswith("Basic realm=")
        assert httpx.get(f"{running.url}/openapi.json", timeout=10).status_code == 401
        assert httpx.get(docs, auth=("operator", "wrong"), timeout=10).status_code == 401
        page = httpx.get(docs, auth=("operator", TOKEN), timeout=10)  # a browser's prompt
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert httpx.get(docs, headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
        assert "http://" not in page.text and "https://" not in page.text and "//" not in page.text
        for asset in ("/docs/assets/swagger-ui-bundle.js", "/docs/assets/swagger-ui.css", "/static/docs.js"):
            assert f'"{asset}"' in page.text
            loaded = httpx.get(f"{running.url}{asset}", timeout=10)  # code, no data: no token
            assert loaded.status_code == 200 and len(loaded.content) > 200, asset
        spec = httpx.get(f"{running.url}/openapi.json", auth=("", TOKEN), timeout=10)
        assert spec.status_code == 200 and "/v1/tasks" in spec.json()["paths"]
        assert "validatorUrl: null" in httpx.get(f"{running.url}/static/docs.js").text  # no outside call
        # the /v1 API itself takes the bearer token only, as before
        assert httpx.get(f"{running.url}/v1/tasks", auth=("operator", TOKEN), timeout=10).status_code == 401
    finally:
        running.close()


def test_a_flood_of_wrong_tokens_gets_429(inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(
        tmp_path, token=TOKEN, auth_failures_max=5, auth_failure_window_s=30.0))
    try:
        url, good = f"{running.url}/v1/tasks", {"Authorization": f"Bearer {TOKEN}"}
        for _ in range(3):  # a missing token is no guess (the page's first call): not counted
            assert httpx.get(url, timeout=10).status_code == 401
        statuses = [httpx.get(url, headers={"Authorization": f"Bearer guess{i}"}, timeout=10).status_code
                    for i in range(8)]
        assert statuses == [401] * 5 + [429] * 3
        limited = httpx.get(url, headers={"Authorization": "Bearer guess"}, timeout=10)
        assert limited.status_code == 429 and "too many wrong tokens from 127.0.0.1" in limited.json()["detail"]
        assert 1 <= int(limited.headers["retry-after"]) <= 30
        # while limited, even the right token is refused: a guess must not be confirmed meanwhile
        assert httpx.get(url, headers=good, timeout=10).status_code == 429
        counters = httpx.get(f"{running.url}/v1/health", headers=good, timeout=10)
        assert counters.status_code == 429
    finally:
        running.close()
    # a window that runs out lets the address try again
    running = RunningGateway(inproc_router, gateway_config(
        tmp_path / "again", token=TOKEN, auth_failures_max=2, auth_failure_window_s=1.0))
    try:
        url = f"{running.url}/v1/tasks"
        for _ in range(2):
            assert httpx.get(url, headers={"Authorization": "Bearer guess"}).status_code == 401
        assert httpx.get(url, headers={"Authorization": "Bearer guess"}).status_code == 429
        wait_for(lambda: httpx.get(url, headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200,
                 what="the window to let the address in again")
        counters = httpx.get(f"{running.url}/v1/health", headers={"Authorization": f"Bearer {TOKEN}"}).json()
        assert counters["counters"]["http_401"] == 2 and counters["counters"]["http_429"] >= 1
    finally:
        running.close()


def test_a_short_token_off_loopback_is_refused_at_start(monkeypatch: pytest.MonkeyPatch,
                                                        tmp_path: Path) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with pytest.raises(ServiceConfigError, match="has 1 characters: a gateway on non-loopback host "
                                                 "'0.0.0.0' needs at least 16"):
        load_config(GatewayService, None, {"host": "0.0.0.0", "token": "x"})
    monkeypatch.setenv(TOKEN_ENV, "fifteen-chars-x")
    with pytest.raises(ServiceConfigError, match="has 15 characters"):
        load_config(GatewayService, None, {"host": "10.0.0.5"})
    monkeypatch.setenv(TOKEN_ENV, "sixteen-chars-xx")
    assert load_config(GatewayService, None, {"host": "10.0.0.5"}).resolved_token() == "sixteen-chars-xx"
    monkeypatch.delenv(TOKEN_ENV)
    assert load_config(GatewayService, None, {"token": "x"}).resolved_token() == "x"  # loopback: the owner's call

    # `ovamos run gateway` refuses with the reason, before it serves anything
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
    proc = subprocess.run([sys.executable, "-m", "ovamos.cli", "run", "gateway", "--set", 'host="0.0.0.0"',
                           "--set", 'token="short"', "--set", f'state_dir="{tmp_path}"'],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode != 0
    assert "has 5 characters" in proc.stderr and "at least 16" in proc.stderr
    assert not (tmp_path / "tasks.sqlite3").exists()


@pytest.mark.parametrize("token,message", [("   ", "is blank"), ("\t", "is blank"),
                                           (" padded-token-of-20 ", "starts or ends with whitespace")])
def test_a_whitespace_token_is_refused(monkeypatch: pytest.MonkeyPatch, token: str, message: str) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with pytest.raises(ServiceConfigError, match=message):
        load_config(GatewayService, None, {"token": token})
    monkeypatch.setenv(TOKEN_ENV, token)
    with pytest.raises(ServiceConfigError, match=message):
        load_config(GatewayService, None, {})
