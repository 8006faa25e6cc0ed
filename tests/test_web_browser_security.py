"""The console's login throttle and response headers as headless Chromium meets them.

The console runs in this process (its own event loop in a thread) over a stand-in of
the gateway (no machines cycle); Chromium talks to it over loopback HTTP. Chromium's
performance log (the DevTools network events) shows every response the browser got,
redirects and the tab icon included, with its status and headers.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from selenium.common.exceptions import WebDriverException
from selenium.webdriver.common.by import By
from selenium.webdriver.support.wait import WebDriverWait

from gateway.scada.login_throttle import ThrottlePolicy
from gateway.scada.server import ScadaUser
from gateway.web.server import SECURITY_HEADERS, WebConsole, WebSettings
from tests.browser import chromium
from tests.ports import free_tcp_port
from tests.test_web_auth import gateway_of

OPERATOR = ScadaUser("olga", "op-secret-7", "operator")
VIEWER = ScadaUser("vera", "view-secret-8", "viewer")


class Served:
    """A console started in a thread's event loop; ``url`` without a trailing slash."""

    def __init__(self, tmp_path: Path) -> None:
        settings = WebSettings(
            host="127.0.0.1",
            port=free_tcp_port(),
            users=[OPERATOR, VIEWER],
            throttle=ThrottlePolicy(max_failures=5, window_s=60, lockout_s=30),
        )
        self.console = WebConsole(settings, gateway_of(["m1"], tmp_path))
        self.url = self.console.url.rstrip("/")
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()
        self._call(self.console.start())

    def _call(self, work: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(work, self.loop).result(timeout=60)

    def close(self) -> None:
        self._call(self.console.stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=10)
        self.loop.close()


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    server = Served(tmp_path)
    try:
        yield server
    finally:
        server.close()


@pytest.fixture
def browser() -> Iterator[Any]:
    driver = chromium(capabilities={"goog:loggingPrefs": {"performance": "ALL"}})
    try:
        yield driver
    finally:
        driver.quit()


def submit_login(driver: Any, url: str, user: str, password: str) -> None:
    driver.get(url + "/login")
    driver.find_element(By.ID, "username").send_keys(user)
    driver.find_element(By.ID, "password").send_keys(password)
    button = driver.find_element(By.ID, "login")
    button.click()
    WebDriverWait(driver, 20).until(left_document(button))  # the answer's page has loaded


def left_document(element: Any) -> Callable[[Any], bool]:
    """A wait condition: ``element`` is no longer in the page. Selenium's ``staleness_of``
    expects StaleElementReferenceException; Chrome may instead answer "Node with given id
    does not belong to the document" while the next page replaces it: gone as well."""

    def gone(_driver: Any) -> bool:
        try:
            element.is_enabled()
        except WebDriverException:  # stale, or Chrome's node-not-in-document answer
            return True
        return False

    return gone


def logged_in(driver: Any) -> bool:
    """True once the browser has left the login page for the overview."""
    return not driver.find_elements(By.ID, "login-failed") and "/login" not in (driver.current_url)


def test_one_users_wrong_passwords_do_not_lock_out_another_user_at_that_address(
    served: Served, browser: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Five bad passwords for olga from 127.0.0.1 lock olga, not vera at the same address."""
    caplog.set_level(logging.INFO, logger="gateway.web.auth")
    for k in range(5):
        submit_login(browser, served.url, OPERATOR.username, f"guess-{k}")
        assert browser.find_element(By.ID, "login-failed")
    submit_login(browser, served.url, VIEWER.username, VIEWER.password)
    assert logged_in(browser), browser.page_source[:500]
    assert browser.find_element(By.CSS_SELECTOR, "header .who").text.startswith("vera")
    browser.delete_all_cookies()
    submit_login(browser, served.url, OPERATOR.username, OPERATOR.password)
    assert browser.find_element(By.ID, "login-failed")  # olga herself is locked out
    lines = [r.getMessage() for r in caplog.records]
    assert [line for line in lines if "locked" in line] == [
        "console logins through user olga locked for 30 s after 5 failures",
        "console login refused (locked out) for 'olga' from 127.0.0.1",
    ]
    assert "console login: vera (viewer) from 127.0.0.1" in lines


def responses(driver: Any) -> list[tuple[str, int, dict[str, str]]]:
    """Every HTTP response the browser received since the last call: (url, status,
    headers with lower-case names), redirects included."""
    seen = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        params = message.get("params", {})
        if message["method"] == "Network.responseReceived":
            response = params["response"]
        elif message["method"] == "Network.requestWillBeSent" and "redirectResponse" in params:
            response = params["redirectResponse"]
        else:
            continue
        headers = {name.lower(): value for name, value in response["headers"].items()}
        seen.append((response["url"], int(response["status"]), headers))
    return seen


def test_every_response_carries_the_security_headers_and_the_icon_is_served(
    served: Served, browser: Any
) -> None:
    url = served.url
    browser.get(url + "/machines/m1")  # not logged in: 303 to the login page
    browser.get(url + "/favicon.ico")
    submit_login(browser, url, OPERATOR.username, OPERATOR.password)  # 303 to /
    assert logged_in(browser)
    # The page names its icon, so the browser does not ask for one that is not there.
    icon_link = browser.find_element(By.CSS_SELECTOR, 'link[rel="icon"]')
    assert icon_link.get_attribute("href") == url + "/static/favicon.svg"
    browser.get(url + "/no-such-page")  # the router's 404
    browser.get(url + "/machines/no-such-machine")  # a handler's 404
    # Logged in, the machine page: the stand-in's local store is a file that does not
    # exist, so reading its window raises and aiohttp answers its own 500.
    browser.get(url + "/machines/m1")
    got = responses(browser)
    statuses = {(u.removeprefix(url), s) for u, s, _ in got}
    expected = {
        ("/machines/m1", 303),
        ("/login?next=/machines/m1", 200),
        ("/favicon.ico", 200),
        ("/login", 303),
        ("/", 200),
        ("/no-such-page", 404),
        ("/machines/no-such-machine", 404),
        ("/machines/m1", 500),
        ("/static/console.css", 200),
    }
    assert expected <= statuses, sorted(statuses)
    wanted = {name.lower(): value for name, value in SECURITY_HEADERS.items()}
    for where, status, headers in got:
        if not where.startswith(url):
            continue
        missing = {n: v for n, v in wanted.items() if headers.get(n) != v}
        assert not missing, (where, status, missing)
    icon = next(h for u, s, h in got if u == url + "/favicon.ico")
    assert icon["content-type"] == "image/svg+xml"
    assert not [(u, s) for u, s, _ in got if "favicon" in u and s != 200]


def test_refusals_and_errors_outside_a_browser_carry_the_headers_too(served: Served) -> None:
    """What a browser's navigation does not show: a POST without a session (401), a
    wrong method (405), a cross-site login (403)."""

    async def statuses() -> list[tuple[int, dict[str, str]]]:
        got = []
        async with aiohttp.ClientSession() as client:
            for method, path, headers in (
                ("POST", "/machines/m1/promote", {}),
                ("PUT", "/login", {}),
                ("POST", "/login", {"Origin": "http://attacker.example"}),
            ):
                async with client.request(
                    method, served.url + path, headers=headers, allow_redirects=False
                ) as response:
                    got.append((response.status, dict(response.headers)))
        return got

    got = asyncio.run(statuses())
    assert [status for status, _ in got] == [401, 405, 403]
    for status, headers in got:
        for name, value in SECURITY_HEADERS.items():
            assert headers.get(name) == value, (status, name, headers)
