"""The operator's page in a real browser against a real gateway (its peers mocked over real
Zenoh): the gateway's validation messages next to their fields, the token prompt, keyboard
use, the phone layout, and the page's own endpoints (state, e-stop, map) over HTTP."""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import httpx
import pytest
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys

from ovamos.services.gateway.client import GatewayClient
from ovamos.services.gateway.page import STATIC
from ovamos.shared import keys
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config
from ovamos.shared.messages import Goal, ObjectInstance, TaskStatus, TraceOption
from tests.browser import (
    PHONE,
    by_id,
    chromium,
    console_errors,
    row,
    screenshot,
    set_viewport,
    task_rows,
    text_of,
    wait_text,
)
from tests.gateway_mocks import (
    ODOM_SESSION,
    ROBOT,
    MockDriver,
    MockMapping,
    MockPlanner,
    RunningGateway,
    gateway_config,
    small_map,
)
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all


@pytest.fixture(scope="module")
def chromium_session() -> Iterator:
    with chromium() as session:
        yield session


@pytest.fixture
def browser(chromium_session):
    """The module's browser on a blank page with an empty console (the last test's page, polling
    a gateway that is gone, logged errors of its own)."""
    chromium_session.get("about:blank")
    chromium_session.get_log("browser")
    return chromium_session


def test_the_page_and_its_files_are_served_without_a_token_and_fetch_nothing_from_elsewhere(
        inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(tmp_path, token="s3cret"))
    try:
        page = httpx.get(f"{running.url}/", timeout=10)
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        for name in ("app.js", "style.css"):
            assert httpx.get(f"{running.url}/static/{name}", timeout=10).status_code == 200
        assert httpx.get(f"{running.url}/v1/tasks", timeout=10).status_code == 401  # the data is guarded
    finally:
        running.close()
    for path in STATIC.iterdir():  # every asset is local: no CDN, no web font, no absolute URL
        text = path.read_text()
        assert "http://" not in text and "https://" not in text and "@import" not in text, path


def test_estop_endpoints_are_confirmed_by_the_driver_and_work_without_a_task(
        inproc_router: str, gateway: RunningGateway) -> None:
    url = f"{gateway.url}/v1/robots/{ROBOT}"
    assert httpx.get(url, timeout=10).json()["driver"] is None
    driver = MockDriver(inproc_router)
    try:
        wait_for(lambda: httpx.get(url, timeout=10).json()["driver"], what="the driver state")
        engaged = httpx.post(f"{url}/estop", json={"reason": "test"}, timeout=10)
        assert engaged.status_code == 200, engaged.text
        assert engaged.json()["driver"]["estop_latched"] is True and engaged.json()["active_task"] is None
        assert driver.requests[-1].engage and driver.requests[-1].source == "gateway"
        assert driver.requests[-1].reason == "test"
        assert httpx.post(f"{url}/estop", timeout=10).status_code == 200  # no body: still latches
        refused = httpx.post(f"{url}/estop/clear", json={"confirm": False}, timeout=10)
        assert refused.status_code == 422 and refused.json()["errors"][0]["field"] == "confirm"
        missing = httpx.post(f"{url}/estop/clear", timeout=10)  # confirm is required
        assert missing.status_code == 422 and 'send a JSON object like {"confirm": true}' in missing.json()["detail"]
        assert driver.latched
        cleared = httpx.post(f"{url}/estop/clear", json={"confirm": True}, timeout=10)
        assert cleared.status_code == 200 and cleared.json()["driver"]["estop_latched"] is False
        assert cleared.json()["pose"] == {"x": 0.5, "y": 0.5, "yaw": 1.0}
        assert httpx.post(f"{gateway.url}/v1/robots/nope/estop", timeout=10).status_code == 404
    finally:
        driver.close()


def test_an_estop_the_driver_does_not_confirm_is_a_504_that_says_so(
        inproc_router: str, tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(tmp_path, estop_confirm_s=0.6))
    deaf = MockDriver(inproc_router, answer=False)  # receives, never reports
    try:
        response = httpx.post(f"{running.url}/v1/robots/{ROBOT}/estop", timeout=10)
        assert response.status_code == 504
        detail = response.json()["detail"]
        assert "did not confirm" in detail and "no driver state" in detail and "hardware stop" in detail
        wait_for(lambda: len(deaf.requests) >= 2, what="the e-stop re-sent until the deadline")
        assert all(r.engage for r in deaf.requests)
    finally:
        deaf.close()
        running.close()


def test_bad_submissions_show_the_gateways_messages_next_to_their_fields(
        browser, gateway: RunningGateway, tmp_path: Path) -> None:
    browser.get(gateway.url)
    wait_text(browser, "health", "gateway")
    names = by_id(browser, "target-input")
    for i in range(17):  # keyboard only: a name and Enter makes a chip; Enter on an empty field submits
        names.send_keys(f"thing{i}", Keys.ENTER)
    assert text_of(browser, "target-count") == "17 / 16"
    names.send_keys(Keys.ENTER)
    expected = httpx.post(f"{gateway.url}/v1/tasks", json={"targets": [f"thing{i}" for i in range(17)],
                                                           "robot_id": ROBOT}).json()["detail"]
    assert wait_text(browser, "error-targets", expected) == expected  # "targets: must hold 1 to 16 ..."
    assert names.get_attribute("aria-invalid") == "true"

    for _ in range(16):  # Backspace on the empty field removes the last chip
        names.send_keys(Keys.BACKSPACE)
    assert text_of(browser, "target-count") == "1 / 16"
    names.send_keys(" ", Keys.ENTER)  # a blank name
    by_id(browser, "max-steps").send_keys("0")
    by_id(browser, "submit").send_keys(Keys.ENTER)
    wait_text(browser, "error-targets", "target 1 must be 1 to 64 characters after trimming, got 0")
    wait_text(browser, "error-max_steps", "max_steps: Input should be greater than or equal to 1")
    assert task_rows(browser) == []  # nothing was accepted
    screenshot(browser, tmp_path, "bad-submission")
    assert console_errors(browser, expected_statuses=(422,)) == []


def test_with_a_token_the_page_asks_for_it_and_then_works(browser, inproc_router: str,
                                                          tmp_path: Path) -> None:
    running = RunningGateway(inproc_router, gateway_config(tmp_path / "state", token="s3cret"))
    try:
        browser.get(running.url)
        wait_text(browser, "token-message", "This gateway needs a token (401: missing bearer token")
        by_id(browser, "token").send_keys("wrong", Keys.ENTER)
        wait_text(browser, "token-message", "The gateway refused the token (401: wrong bearer token)")
        by_id(browser, "token").send_keys("s3cret", Keys.ENTER)
        wait_text(browser, "health", "gateway")
        assert not by_id(browser, "token-form").is_displayed()
        by_id(browser, "target-input").send_keys("chair", Keys.ENTER, Keys.ENTER)
        task = wait_for(lambda: task_rows(browser), what="the task in the list")[0]
        task_id = task.get_attribute("data-task")
        wait_text(browser, "events", f"task {task_id[:8]} searching")  # the event stream, with the token
        assert browser.execute_script("return sessionStorage.getItem('ovamos.gateway.token')") == "s3cret"
        row(browser, task_id).find_element(By.CSS_SELECTOR, "button.cancel").click()
        wait_text(browser, "events", f"task {task_id[:8]} cancelled")
        # a task started elsewhere (here: over HTTP) is listed and watched
        other = httpx.post(f"{running.url}/v1/tasks", json={"targets": ["sofa"]},
                           headers={"Authorization": "Bearer s3cret"}, timeout=10).json()["id"]
        wait_text(browser, "events", f"task {other[:8]} searching")
        assert "selected" in row(browser, other).get_attribute("class")
        screenshot(browser, tmp_path, "token")
        assert console_errors(browser, expected_statuses=(401,)) == []
    finally:
        running.close()


def test_the_phone_layout_keeps_the_estop_in_view_and_nothing_overflows(
        browser, inproc_router: str, gateway: RunningGateway, tmp_path: Path) -> None:
    mapping = MockMapping(inproc_router, service="mapping")  # the page asks a live "mapping" for maps
    try:
        set_viewport(browser, PHONE)
        browser.get(gateway.url)
        wait_for(lambda: by_id(browser, "map").get_attribute("data-seq"), what="a map drawn")
        for y in (0, 600, 2000):
            browser.execute_script(f"window.scrollTo(0, {y})")
            box = browser.execute_script(
                "const r = document.getElementById('estop').getBoundingClientRect();"
                "return [r.top, r.bottom, r.left, r.right, window.innerHeight, window.innerWidth];")
            top, bottom, left, right, height, width = box
            assert 0 <= top and bottom <= height and 0 <= left and right <= width, box
        assert browser.execute_script("return document.documentElement.scrollWidth") <= PHONE[0]
        screenshot(browser, tmp_path, "phone")
        assert console_errors(browser) == []
    finally:
        mapping.close()
        set_viewport(browser, (1280, 800))


def test_the_map_view_holds_what_the_page_draws(inproc_router: str, gateway: RunningGateway,
                                                planner: MockPlanner) -> None:
    mapping, driver = MockMapping(inproc_router), MockDriver(inproc_router)
    url = f"{gateway.url}/v1/robots/{ROBOT}/map"
    try:
        with GatewayClient(gateway.url) as api:
            task = api.submit(["chair", "sofa"])
            goal = Goal(kind="candidate", x=0.6, y=1.3)
            for step, (x, y) in enumerate([(0.4, 0.4), (0.5, 0.6)], start=1):
                wait_for(lambda: planner.report(task.id, TaskStatus.SEARCHING, ["chair", "sofa"], steps=step,
                                                x=x, y=y, goal=goal) or api.get(task.id).steps == step,
                         what=f"step {step} applied")
        view = wait_for(lambda: (r := httpx.get(url, timeout=10)).status_code == 200 and r.json()
                        and r.json()["robot"] and r.json(), what="the map view with the robot")
        assert view["task_id"] == task.id and view["path"] == [[0.4, 0.4], [0.5, 0.6]]
        assert view["odom_session"] == ODOM_SESSION
        assert view["goal"] == {"kind": "candidate", "x": 0.6, "y": 1.3, "label": None}
        assert view["robot"] == {"x": 0.5, "y": 0.5, "yaw": 1.0}  # the driver's odometry
        assert view["layers"] == ["chair"] and view["frontiers"] == [[1.7, 1.0]]
        assert [o["label"] for o in view["objects"]] == ["chair"]
        assert view["candidates"] == []  # no decision traced yet: nothing the planner weighed
        # the planner's candidates are the page's, whatever a default planner would find on this map
        # (the chair layer's hot patch at rows 25-29, columns 10-14): issue 49
        weighed = (TraceOption(kind="candidate", x=1.2, y=0.3, value=0.4),
                   TraceOption(kind="frontier", x=1.7, y=1.0, value=0.1))
        planner.decide(task.id, weighed)
        view = wait_for(lambda: (v := httpx.get(url, timeout=10).json())["candidates"] and v, what="the traced candidates")
        assert view["candidates"] == [{"x": 1.2, "y": 0.3, "value": 0.4}]
        planner.decide("another-task", (TraceOption(kind="candidate", x=0.1, y=0.1, value=0.9),))
        wait_for(lambda: httpx.get(url, timeout=10).json()["candidates"] == [], what="another task's trace not drawn")
        # the raster covers the window it says, and everything drawn lies inside it
        assert view["image"].startswith("data:image/png;base64,")
        right, top = view["x0"] + view["width"] * view["resolution"], view["y0"] + view["height"] * view["resolution"]
        for x, y in [*view["path"], *view["frontiers"], (0.6, 1.4)]:
            assert view["x0"] <= x <= right and view["y0"] <= y <= top
        assert httpx.get(url, params={"layer": "chair"}, timeout=10).json()["layer"] == "chair"
        bad = httpx.get(url, params={"layer": "piano"}, timeout=10)
        assert bad.status_code == 422 and "unknown value layer 'piano'" in bad.json()["detail"]
        api_cancel = httpx.delete(f"{gateway.url}/v1/tasks/{task.id}", timeout=10)
        assert api_cancel.status_code == 200
        after = httpx.get(url, timeout=10).json()
        assert after["goal"] is None and after["candidates"] == []  # no search: no goal, no candidates
        assert httpx.get(f"{gateway.url}/v1/robots/nope/map", timeout=10).status_code == 404
    finally:
        driver.close()
        mapping.close()


# -- issue 32: the phone's task table, the map's legend, labels and the task's own detections --------
LONG_NAME = "a_very_long_target_name_that_has_no_space_to_wrap_at_all"


def test_on_a_phone_every_button_of_the_task_table_is_in_view(
        browser, gateway: RunningGateway, planner: MockPlanner, tmp_path: Path) -> None:
    with GatewayClient(gateway.url) as api:
        first = api.submit([LONG_NAME, "chair"])
        wait_for(lambda: planner.report(first.id, TaskStatus.SEARCHING, [LONG_NAME, "chair"], steps=3)
                 or api.get(first.id).steps == 3, what="a step with the planner's message")
        api.submit(["sofa", "television_set_in_the_living_room"])
        api.submit(["cup"])
    try:
        set_viewport(browser, PHONE)
        browser.get(gateway.url)
        wait_for(lambda: len(task_rows(browser)) == 3, what="the three tasks listed")
        buttons = browser.find_elements(By.CSS_SELECTOR, "#tasks button")
        visible = [b for b in buttons if b.is_displayed()]
        assert len(visible) == 6  # Watch and Cancel on each (none is over)
        for button in visible:
            box = browser.execute_script(
                "const b = arguments[0]; b.scrollIntoView({block: 'center'});"
                "const r = b.getBoundingClientRect();"
                "const hit = document.elementFromPoint((r.left + r.right) / 2, (r.top + r.bottom) / 2);"
                "return [r.left, r.right, r.top, r.bottom, innerWidth, innerHeight, hit === b];", button)
            left, right, top, bottom, width, height, on_top = box
            assert 0 <= left and right <= width and 0 <= top and bottom <= height, (button.text, box)
            assert on_top, f"{button.text}: hidden behind something (a scroll box's edge?) {box}"
        card = browser.execute_script("const t = document.getElementById('tasks');"
                                      "return [t.scrollWidth, t.parentElement.clientWidth];")
        assert card[0] <= card[1], card  # the table fits its card: nothing to scroll sideways
        assert browser.execute_script("return document.documentElement.scrollWidth") <= PHONE[0]
        browser.execute_script("document.getElementById('tasks').scrollIntoView()")
        screenshot(browser, tmp_path, "phone-tasks")
        assert console_errors(browser) == []
    finally:
        set_viewport(browser, (1280, 800))


class CrowdedMapping:
    """A "mapping" service (mock) whose map holds this task's detections, an earlier task's lamp,
    and a crowd of objects in one spot (to label without overlaps)."""

    def __init__(self, endpoint: str) -> None:
        base = small_map()
        crowd = tuple(ObjectInstance(label=("chair", "sofa", "lamp")[i % 3], x=0.9 + 0.01 * (i % 5),
                                     y=0.9 + 0.01 * (i // 5), score=0.5, hits=i + 1, confirmed=i % 2 == 0)
                      for i in range(30))
        lamp = ObjectInstance(label="lamp", x=1.3, y=0.5, score=0.9, hits=7, confirmed=True)  # not a target
        sofa = ObjectInstance(label="sofa", x=0.4, y=0.5, score=0.4, hits=1, confirmed=False)
        self.snapshot = base.model_copy(update={"objects": (*base.objects, sofa, lamp, *crowd)})
        self.bus = Bus.open(build_config(connect=[endpoint]), ROBOT, "mapping")
        self.bus.queryable(keys.map_snapshot(ROBOT), lambda: self.snapshot)

    def close(self) -> None:
        self.bus.close()


def _css_colour(browser, selector: str, prop: str) -> tuple[int, int, int]:
    value = browser.execute_script(
        "return getComputedStyle(document.querySelector(arguments[0]))[arguments[1]]", selector, prop)
    r, g, b = (int(float(n)) for n in value[value.index("(") + 1:value.index(")")].split(",")[:3])
    return r, g, b


def _near(browser, u: float, v: float, reach: int, colour: tuple[int, int, int], tolerance: int = 12) -> bool:
    """Whether a canvas pixel within ``reach`` of (u, v) has ``colour``."""
    return browser.execute_script(
        "const [u, v, n, c, tol] = arguments;"
        "const d = document.getElementById('map').getContext('2d')"
        "  .getImageData(Math.round(u) - n, Math.round(v) - n, 2 * n + 1, 2 * n + 1).data;"
        "for (let i = 0; i < d.length; i += 4)"
        "  if (Math.abs(d[i] - c[0]) <= tol && Math.abs(d[i + 1] - c[1]) <= tol && Math.abs(d[i + 2] - c[2]) <= tol)"
        "    return true;"
        "return false;", u, v, reach, list(colour), tolerance)


def test_the_map_draws_only_the_tasks_detections_in_colour_labels_them_apart_and_its_legend_says_so(
        browser, inproc_router: str, gateway: RunningGateway, tmp_path: Path) -> None:
    mapping, driver = CrowdedMapping(inproc_router), MockDriver(inproc_router)
    try:
        targets = ["chair", "sofa"]
        with GatewayClient(gateway.url) as api:
            api.submit(targets)
        browser.get(gateway.url)
        # the targets come with the task list: wait until the map has been drawn with them
        marks = wait_for(lambda: (m := by_id(browser, "map").get_attribute("data-marks"))
                         and any(k["kind"] != "other" for k in json.loads(m)) and json.loads(m),
                         what="the map's marks drawn for the task")
        screenshot(browser, tmp_path, "map-labels")
        kinds = {(m["label"], m["kind"]) for m in marks}
        assert {("chair", "confirmed"), ("sofa", "unconfirmed"), ("lamp", "other")} <= kinds
        assert all(kind == "other" for label, kind in kinds if label == "lamp")  # an earlier task's
        assert all(kind != "other" for label, kind in kinds if label in targets)

        # the legend names every mark, in the colours the map draws them
        legend = browser.find_element(By.CSS_SELECTOR, ".legend").text
        for words in ("unexplored", "explored", "obstacle", "value", "frontier", "candidate", "goal", "path",
                      "robot", "detection, confirmed", "detection, unconfirmed", "found", "other task"):
            assert words in legend, words
        for kind in ("confirmed", "unconfirmed", "other"):
            colour = _css_colour(browser, f".sw.{kind}", "borderTopColor")
            drawn = [m for m in marks if m["kind"] == kind]
            assert any(_near(browser, m["u"] + m["r"], m["v"], 2, colour) for m in drawn), (kind, colour)
        assert _css_colour(browser, ".sw.robot", "backgroundColor") == (20, 60, 200) and _css_colour(browser, ".sw.found", "backgroundColor") == (22, 163, 74)

        # labels: none overlaps another, all inside the canvas; the crowd's are labelled or numbered
        labels = json.loads(by_id(browser, "map").get_attribute("data-labels"))
        width, height = browser.execute_script("const c = document.getElementById('map'); return [c.width, c.height];")
        rects = [tuple(label["rect"]) for label in labels]
        for i, (x0, y0, x1, y1) in enumerate(rects):
            assert 0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height, labels[i]
            for a0, b0, a1, b1 in rects[i + 1:]:
                assert not (x0 < a1 and a0 < x1 and y0 < b1 and b0 < y1), (labels[i], (a0, b0, a1, b1))
        texts = [label["text"] for label in labels]
        listed = text_of(browser, "map-labels")
        for o in mapping.snapshot.objects:
            if o.label in targets:
                text = f"{o.label} ×{o.hits}"
                assert text in texts or text in listed, text
        assert listed.startswith("Labels by number: 1 ")  # the crowd does not all fit beside its marks
        assert "1" in texts
        assert console_errors(browser) == []
    finally:
        driver.close()
        mapping.close()


def test_a_task_that_ended_before_the_page_opened_is_listed_at_its_own_time(
        browser, gateway: RunningGateway, planner: MockPlanner) -> None:
    with GatewayClient(gateway.url) as api:
        task = api.submit(["chair"])
        wait_for(lambda: planner.report(task.id, TaskStatus.DONE, ["chair"], steps=2) or api.get(task.id).final,
                 what="the task done")
        ended = api.get(task.id).updated_at
    browser.get(gateway.url)
    line = f"task {task.id[:8]} done"
    stamp = wait_for(lambda: browser.execute_script(
        "const li = [...document.querySelectorAll('#events li')].find((l) => l.textContent.includes(arguments[0]));"
        "return li && li.querySelector('time').dateTime;", line), what="the task's end in the events")
    assert datetime.fromisoformat(stamp.replace("Z", "+00:00")) == ended.replace(
        microsecond=ended.microsecond // 1000 * 1000)  # the gateway's time, to the millisecond JS keeps
    assert console_errors(browser) == []
