"""The operator's page in a real browser against the whole system: the demo's processes (router,
mapping, perception, planner, simulated robot, gateway) under the supervisor on free loopback
ports. A person's session: submit two targets, watch the steps rise and an object be found (in
the list and on the map), E-STOP (the driver latches, the robot stops), clear (the search
resumes), cancel. Screenshots are saved as test artifacts."""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx
import pytest
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys

from ovamos.demo import DEMO_EPISODE, DEMO_SEED, SERVICES, demo_entries, write_configs
from ovamos.services.gateway.client import GatewayClient, GatewayError
from ovamos.shared.procs import free_port
from ovamos.supervisor import Supervisor, port_open
from ovamos.world.episodes import make_episode
from tests.browser import LAPTOP, by_id, chromium, console_errors, row, screenshot, text_of, wait_text
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes, routers, browsers or real-time devices: make test-all

ROBOT = "sim"
FOUND_GREEN = (22, 163, 74)  # the page's found-object marker (#16a34a)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The demo's processes; the gateway's URL once every service is alive."""
    folder = tmp_path_factory.mktemp("dashboard-stack")
    http_port, zenoh_port = free_port(), free_port()
    configs = write_configs(folder / "config", seed=DEMO_SEED, episode=DEMO_EPISODE, robot_id=ROBOT,
                            http_port=http_port)
    url = f"http://127.0.0.1:{http_port}"
    with Supervisor(demo_entries(configs, robot_id=ROBOT, zenoh_port=zenoh_port), log_dir=folder / "logs"), \
            GatewayClient(url) as client:
        wait_for(lambda: port_open("127.0.0.1", http_port), timeout=90, what="the gateway")

        def alive() -> bool:
            try:
                return {s["service"] for s in client.health()["robots"][ROBOT]["services"]} >= set(SERVICES)
            except (GatewayError, OSError):
                return False

        wait_for(alive, timeout=120, what="every service alive")
        yield url


def _steps(browser, task_id: str) -> int:
    tr = row(browser, task_id)
    return int(tr.get_attribute("data-steps")) if tr is not None else -1


def _robot_state(url: str) -> dict:
    return httpx.get(f"{url}/v1/robots/{ROBOT}", timeout=10).json()


def _pixel(browser, x: int, y: int) -> tuple[int, int, int]:
    r, g, b = browser.execute_script(
        "return Array.from(document.getElementById('map').getContext('2d')"
        f".getImageData({x}, {y}, 1, 1).data.slice(0, 3));")
    return r, g, b


def test_an_operator_searches_stops_resumes_and_cancels_from_the_page(
        stack: str, tmp_path_factory: pytest.TempPathFactory) -> None:
    shots = tmp_path_factory.mktemp("dashboard-screenshots")
    targets = list(make_episode(DEMO_SEED, DEMO_EPISODE)[0].targets[:2])
    with chromium(LAPTOP) as browser:
        browser.get(stack)
        for service in SERVICES:
            wait_text(browser, "health", service)
        wait_for(lambda: by_id(browser, "driver-state").get_attribute("data-mode") == "ready",
                 what="the driver's state next to the E-STOP")

        # submit two targets, as chips
        names = by_id(browser, "target-input")
        for name in targets:
            names.send_keys(name + ",")
        assert text_of(browser, "target-count") == "2 / 16"
        by_id(browser, "submit").click()
        task_id = wait_for(lambda: (rows := browser.find_elements(By.CSS_SELECTOR, "#tasks tbody tr"))
                           and rows[0].get_attribute("data-task"), what="the task in the list")
        wait_for(lambda: row(browser, task_id).get_attribute("data-status") == "searching", what="searching")
        first = wait_for(lambda: (n := _steps(browser, task_id)) > 0 and n, timeout=60, what="a first step")
        wait_for(lambda: _steps(browser, task_id) > first, timeout=60, what="the step counter rising")

        # a found object: in the list, in the events, and drawn on the map
        found = wait_text(browser, "events", "found ", timeout=240)
        label = next(t for t in targets if f"found {t} at step" in found)
        assert f"✓ {label}" in row(browser, task_id).find_element(By.CSS_SELECTOR, "td.found").text
        marker = wait_for(lambda: next((m for m in (by_id(browser, "map").get_attribute("data-found") or "")
                                        .split() if m.startswith(label + "@")), None),
                          what=f"{label} drawn on the map")
        u, v = (int(n) for n in marker.split("@")[1].split(","))
        assert _pixel(browser, u, v) == FOUND_GREEN, "no found marker at the object's place"
        assert label in text_of(browser, "found-list")
        view = wait_for(lambda: (v := httpx.get(f"{stack}/v1/robots/{ROBOT}/map", timeout=10).json())["goal"]
                        and v, what="the planner's goal in the map the page draws")
        assert view["task_id"] == task_id and len(view["path"]) > 1 and view["robot"] is not None
        screenshot(browser, shots, "searching")

        assert browser.execute_script("return document.documentElement.scrollWidth") <= LAPTOP[0]

        # E-STOP (from the keyboard): the driver reports the latch, the robot stops, the planner
        # says why it waits
        by_id(browser, "estop").send_keys(Keys.ENTER)
        wait_for(lambda: by_id(browser, "driver-state").get_attribute("data-latched") == "true",
                 what="the driver reporting the latched e-stop")
        assert "estop" in text_of(browser, "driver-state")
        wait_text(browser, "events", f"task {task_id[:8]} waiting: e-stop latched")
        stopped_at, pose = _steps(browser, task_id), _robot_state(stack)["pose"]
        time.sleep(2.0)  # the planner ticks at 20 Hz and the kinematic robot steps in ~0.2 s
        assert _steps(browser, task_id) == stopped_at and _robot_state(stack)["pose"] == pose
        screenshot(browser, shots, "estop")

        # clear, confirmed in a dialog: the search resumes
        by_id(browser, "clear-estop").click()
        assert by_id(browser, "clear-dialog").is_displayed()
        focused = browser.switch_to.active_element
        assert focused.text == "Keep it latched"  # Enter right away keeps it latched
        focused.send_keys(Keys.TAB)
        browser.switch_to.active_element.send_keys(Keys.ENTER)  # "Clear e-stop"
        wait_for(lambda: by_id(browser, "driver-state").get_attribute("data-latched") == "false",
                 what="the e-stop released")
        wait_text(browser, "events", f"task {task_id[:8]} resumed")
        wait_for(lambda: _steps(browser, task_id) > stopped_at, timeout=60, what="the search resuming")

        # cancel
        row(browser, task_id).find_element(By.CSS_SELECTOR, "button.cancel").click()
        wait_for(lambda: row(browser, task_id).get_attribute("data-status") == "cancelled",
                 what="the task cancelled")
        wait_text(browser, "events", f"task {task_id[:8]} cancelled")
        screenshot(browser, shots, "cancelled")
        assert console_errors(browser) == []
