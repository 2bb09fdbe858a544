"""A real headless browser for the operator page's tests: Debian's chromium through its
chromedriver, driven by selenium (``make`` installs both packages).

Nothing is fetched from the internet: the browser runs with its background networking off and
talks only to the gateway under test on 127.0.0.1.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webelement import WebElement

from tests.polling import wait_for

LAPTOP = (1280, 800)
PHONE = (390, 844)
# what Chromium logs for a response it got with an error status: expected when a test provokes one
_HTTP_ERROR = re.compile(r"Failed to load resource: the server responded with a status of (\d+)")


@contextmanager
def chromium(size: tuple[int, int] = LAPTOP) -> Iterator[webdriver.Chrome]:
    """A headless Chromium of ``size`` (CSS pixels), closed on exit."""
    browser, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.fail("chromium and chromedriver are needed (Debian: chromium chromium-driver; "
                    "`make syslibs` installs them)")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                 "--no-first-run", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-default-apps", "--disable-extensions",
                 "--force-device-scale-factor=1", f"--window-size={size[0]},{size[1]}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    session = webdriver.Chrome(options=options, service=Service(executable_path=driver))
    try:
        set_viewport(session, size)
        yield session
    finally:
        session.quit()


def set_viewport(browser: webdriver.Chrome, size: tuple[int, int]) -> None:
    """Make the page's viewport (not the window) ``size`` CSS pixels."""
    browser.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
        "width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": size[0] < 600})


def console_errors(browser: webdriver.Chrome, expected_statuses: tuple[int, ...] = ()) -> list[str]:
    """The console's errors since the last call, less the HTTP errors the test provoked."""
    errors = []
    for entry in browser.get_log("browser"):
        if entry["level"] != "SEVERE":
            continue
        status = _HTTP_ERROR.search(entry["message"])
        if status and int(status.group(1)) in expected_statuses:
            continue
        errors.append(entry["message"])
    return errors


def by_id(browser: webdriver.Chrome, element_id: str) -> WebElement:
    return browser.find_element(By.ID, element_id)


def text_of(browser: webdriver.Chrome, element_id: str) -> str:
    return by_id(browser, element_id).text


def wait_text(browser: webdriver.Chrome, element_id: str, wanted: str, timeout: float = 20.0) -> str:
    """Wait until the element's text contains ``wanted``; its text."""
    return wait_for(lambda: wanted in (t := text_of(browser, element_id)) and t, timeout,
                    f"{wanted!r} in #{element_id}")


def task_rows(browser: webdriver.Chrome) -> list[WebElement]:
    return browser.find_elements(By.CSS_SELECTOR, "#tasks tbody tr")


def row(browser: webdriver.Chrome, task_id: str) -> WebElement | None:
    rows = browser.find_elements(By.CSS_SELECTOR, f'#tasks tbody tr[data-task="{task_id}"]')
    return rows[0] if rows else None


def screenshot(browser: webdriver.Chrome, folder: Path, name: str) -> Path:
    """Save the viewport as ``folder/name.png`` (a test artifact)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.png"
    assert browser.save_screenshot(str(path)), f"no screenshot {path}"
    return path
