"""The web console in a real browser: headless Chromium against ``run`` and two
simulated machines, each a ``simulate`` process reached over Modbus TCP.

One gateway serves the whole file (it is slow to start); the tests follow the
commissioning engineer's walk: the overview, a sensor breaking, a machine page,
a viewer who may not promote, an operator who does. Screenshots go to
.cache/screenshots/console; the overview and a machine page are copied to docs/img
only with SPINDLE_UPDATE_DOCS_IMAGES=1 (``make screenshots``), so a run leaves the
checkout as it was.
"""

from __future__ import annotations

import asyncio
import hashlib
import itertools
import os
import shutil
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from selenium.webdriver.common.by import By

from gateway.web.store_window import window_rows
from models.online.proposals import ProposalStore
from tests import gateway_rig as rig
from tests.browser import (
    DOCS_IMG,
    UPDATE_DOCS_IMAGES,
    SensorBreakingProxy,
    assert_not_blank,
    chromium,
    screenshot,
)
from tests.ports import free_tcp_port, wait_for_port
from tests.test_promotion import lag_document, models_dir, publish  # noqa: F401 (fixtures)

ROOT = Path(__file__).resolve().parents[1]
OPERATOR = ("olga", "op-secret-7")
VIEWER = ("vera", "view-secret-8")
CYCLE_S = 1.0
MACHINES = ("mill-a", "mill-b")
DOCS_IMAGES = ("console-overview.png", "console-machine.png")


def _simulator(tmp_path: Path, name: str) -> tuple[subprocess.Popen[str], int, int]:
    bus, cnc = free_tcp_port(), free_tcp_port()
    config = {
        "simulator": {
            "program": "const8000",
            "speedup": 60,
            "probe": {"period_s": 120.0},
            "transmitters": {"tcp": {"port": bus, "devices": rig.DEVICES}},
            "cnc": {"modbus": {"port": cnc}},
        }
    }
    path = tmp_path / f"{name}-sim.yaml"
    path.write_text(yaml.safe_dump(config))
    process = subprocess.Popen(
        [sys.executable, "-m", "gateway", "simulate", "--config", str(path)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    wait_for_port(cnc)
    wait_for_port(bus)
    return process, bus, cnc


def _machine(name: str, bus: int, cnc: int, store: Path) -> dict[str, Any]:
    devices = [rig.DEVICES[0], {"device_id": 2, "channels": ["T9", None]}]
    return {
        "id": name,
        "cycle_s": CYCLE_S,
        "transmitters": [
            {
                "name": "bus1",
                "tcp": {"host": "127.0.0.1", "port": bus},
                "timeout_s": 0.5,
                "devices": devices,
            }
        ],
        "sensors": {s: {"max_rate_C_per_s": 50.0, "stale_s": 10.0} for s in rig.SENSORS},
        "quality": {"max_prediction_rate_um_per_s": 60 * 0.1},
        "cnc": {"modbus": {"host": "127.0.0.1", "port": cnc, "timeout_s": 0.5}},
        "compensation": {"slew_um_per_min": 2000.0, "probe_macro": 600},
        "models": {
            "store": str(store),
            "regimes": {
                "models": {"variable": "mlr-error_um-variable"},
                "fallback_model": "mlr-error_um-all",
            },
        },
    }


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory, models_dir: Path) -> Iterator[dict]:  # noqa: F811
    """``run`` with the console on, two simulated machines, mill-b's bus through a proxy."""
    tmp_path = tmp_path_factory.mktemp("console")
    processes: list[subprocess.Popen[str]] = []
    proxy = None
    try:
        machines = []
        for name in MACHINES:
            process, bus, cnc = _simulator(tmp_path, name)
            processes.append(process)
            if name == "mill-b":
                proxy = SensorBreakingProxy(bus)
                bus = proxy.port
            store = tmp_path / f"{name}-models"
            shutil.copytree(models_dir, store)
            machines.append(_machine(name, bus, cnc, store))
        users = []
        for (user, password), role in ((OPERATOR, "operator"), (VIEWER, "viewer")):
            secret = tmp_path / f"{user}.secret"
            secret.write_text(password + "\n")
            users.append({"username": user, "password_file": str(secret), "role": role})
        web_port = free_tcp_port()
        config = {
            "state_dir": str(tmp_path / "state"),
            "logging": {"local_store": str(tmp_path / "points.sqlite")},
            "scada": {"port": free_tcp_port(), "pki_dir": str(tmp_path / "pki"), "users": users},
            "web": {"port": web_port, "reports_dir": str(tmp_path / "reports")},
            "machines": machines,
        }
        path = tmp_path / "config.yaml"
        path.write_text(yaml.safe_dump(config))
        gateway = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(path)],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        processes.append(gateway)
        wait_for_port(web_port, timeout_s=60)
        yield {
            "url": f"http://127.0.0.1:{web_port}",
            "proxy": proxy,
            "stores": {m["id"]: Path(m["models"]["store"]) for m in machines},
            "gateway": gateway,
            "reports": tmp_path / "reports",
            "points": tmp_path / "points.sqlite",
        }
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in processes:
            try:
                _, err = process.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                _, err = process.communicate()
            print(" ".join(process.args[3:5]), "stderr:", err[-3000:])  # shown on a failure
        if proxy is not None:
            proxy.close()


@pytest.fixture(scope="module")
def viewer(console: dict) -> Iterator[Any]:
    """One Chromium for the file's viewer (a browser costs seconds to start), logged in."""
    driver = chromium()
    try:
        log_in(driver, console["url"], VIEWER)
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def operator(console: dict) -> Iterator[Any]:
    driver = chromium()
    try:
        log_in(driver, console["url"], OPERATOR)
        yield driver
    finally:
        driver.quit()


def session() -> aiohttp.ClientSession:
    """An HTTP client keeping the console's cookie (aiohttp drops cookies of IP hosts)."""
    return aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))


def css(driver: Any, selector: str) -> Any:
    return driver.find_element(By.CSS_SELECTOR, selector)


def log_in(driver: Any, url: str, user: tuple[str, str]) -> None:
    driver.get(url + "/login")
    driver.find_element(By.ID, "username").send_keys(user[0])
    driver.find_element(By.ID, "password").send_keys(user[1])
    driver.find_element(By.ID, "login").click()
    wait(lambda: "/login" not in driver.current_url, 20, "login")


def wait(condition: Any, timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            value = condition()
        except Exception:  # an element replaced while read: try again
            value = None
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"not within {timeout_s} s: {what}")


def updates(driver: Any, machine: str) -> int:
    row = driver.find_element(By.ID, f"row-{machine}")
    return int(row.get_attribute("data-updates") or 0)


def test_overview_shows_every_machine_and_updates_within_two_cycles(
    console: dict, viewer: Any
) -> None:
    viewer.get(console["url"] + "/")
    for machine in MACHINES:
        wait(lambda m=machine: updates(viewer, m) >= 1, 30, f"first live update of {machine}")
    for machine in MACHINES:
        seen, started = updates(viewer, machine), time.monotonic()
        wait(lambda m=machine, s=seen: updates(viewer, m) > s, 2 * CYCLE_S + 1.0, "next update")
        assert time.monotonic() - started <= 2 * CYCLE_S + 1.0
        model = css(viewer, f'#row-{machine} [data-f="model_id"]').text
        assert model.startswith("mlr-error_um"), model
        sensors = viewer.find_elements(By.CSS_SELECTOR, f"#row-{machine} .sensor")
        assert {s.get_attribute("data-sensor") for s in sensors} == set(rig.SENSORS)
    applied = '#row-mill-a [data-f="applied_um"]'
    wait(lambda: "–" not in css(viewer, applied).text, 30, "an applied compensation")
    before = _digest(DOCS_IMG / "console-overview.png")
    screenshot(viewer, "overview", "console-overview.png")
    if os.environ.get(UPDATE_DOCS_IMAGES) != "1":
        assert _digest(DOCS_IMG / "console-overview.png") == before, "docs/img changed by a test"


def test_a_sensor_broken_on_the_bus_turns_its_cell_bad(console: dict, viewer: Any) -> None:
    viewer.get(console["url"] + "/")
    cell = '#row-mill-b .sensor[data-sensor="T3"]'
    wait(lambda: "good" in css(viewer, cell).get_attribute("class"), 30, "T3 good")
    console["proxy"].broken.set()
    try:
        wait(lambda: "bad" in css(viewer, cell).get_attribute("class"), 2 * CYCLE_S + 2, "T3 bad")
        title = css(viewer, cell).get_attribute("title")
        assert "open circuit" in title, title
        other = '#row-mill-a .sensor[data-sensor="T3"]'
        assert "good" in css(viewer, other).get_attribute("class")
        screenshot(viewer, "overview-sensor-bad")
    finally:
        console["proxy"].broken.clear()


def test_the_machine_page_plots_the_logged_window_with_its_events(
    console: dict, viewer: Any
) -> None:
    """T3 of mill-b breaks (open circuit) and recovers; once both are in the local store,
    the page lists the break and then the recovery at the times they were logged.

    The page of this window is not opened before in this file, so it is read afresh
    (the console keeps a window's read 15 s per hour of window)."""
    started_ns = time.time_ns()
    flips = lambda: _t3_flips(console["points"], started_ns)  # noqa: E731
    good_now = lambda: _t3_points(console["points"], started_ns)[-1][1] == "good"  # noqa: E731
    wait(good_now, 30, "T3 of mill-b logged good")
    console["proxy"].broken.set()
    try:
        wait(lambda: any(q == "bad" for _, q, _ in flips()), 2 * CYCLE_S + 10, "T3's break logged")
    finally:
        console["proxy"].broken.clear()
    wait(lambda: flips() and flips()[-1][1] == "good", 30, "T3's recovery logged")
    logged = flips()
    broke = next(f for f in logged if f[1] == "bad")
    assert "open circuit" in broke[2], broke  # logged with its reason, though it had no value

    viewer.get(console["url"] + "/machines/mill-b?h=1")
    plot = viewer.find_element(By.ID, "plot")
    loaded = "return arguments[0].complete && arguments[0].naturalWidth"
    assert wait(lambda: viewer.execute_script(loaded, plot), 60, "the plot") > 300
    svg = asyncio.run(_get(console["url"], VIEWER, "/machines/mill-b/plot.svg?h=1"))
    for label in ("temperature (°C)", "speed (r/min)", "Z compensation (µm)", "probe error (µm)"):
        assert label in svg, label
    rows = viewer.find_elements(By.CSS_SELECTOR, "#events tbody tr")
    shown = [r.text for r in rows if "T3: " in r.text]
    expected = [
        f"{_clock(t_ns)} sensor flag T3: {'good → bad' if q == 'bad' else 'bad → good'}"
        for t_ns, q, _ in reversed(logged)
    ]
    assert shown[: len(expected)] == expected, (shown, logged)
    screenshot(viewer, "machine", "console-machine.png")


def _t3_points(store: Path, after_ns: int) -> list[tuple[int, str, str]]:
    """mill-b's logged T3 points after ``after_ns``: (time_ns, quality, reason), by time."""
    rows = window_rows(
        store,
        "spindle_temperature",
        "mill-b",
        (after_ns + 1, 2**62),
        "time_ns, sensor, quality, coalesce(reason, '')",
        "time_ns",
    )
    return [(t, quality, reason) for t, sensor, quality, reason in rows if sensor == "T3"]


def _t3_flips(store: Path, after_ns: int) -> list[tuple[int, str, str]]:
    """The logged T3 points after ``after_ns`` whose quality differs from the one before."""
    points = _t3_points(store, after_ns)
    return [now for before, now in itertools.pairwise(points) if now[1] != before[1]]


def _clock(time_ns: int) -> str:
    """A time as the page's event table shows it (local time, whole seconds)."""
    return datetime.fromtimestamp(time_ns / 1e9).strftime("%Y-%m-%d %H:%M:%S")


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_documented_screenshots_are_real_pictures_shown_in_the_docs() -> None:
    """docs/img holds the overview and a machine page (``make screenshots`` remakes them):
    PNGs of the browser's width, not blank, shown by the README and the manual."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    manual = (ROOT / "docs" / "console.md").read_text(encoding="utf-8")
    for name in DOCS_IMAGES:
        path = DOCS_IMG / name
        data = path.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR", path
        width, height = struct.unpack(">II", data[16:24])
        assert width == 1500 and 400 <= height <= 4000, (path, width, height)
        assert 20_000 <= len(data) <= 3_000_000, (path, len(data))
        assert_not_blank(path)
        assert f"](docs/img/{name})" in readme, f"README.md does not show docs/img/{name}"
        assert f"](img/{name})" in manual, f"docs/console.md does not show img/{name}"


def test_a_viewer_sees_no_promote_button_and_forged_posts_are_refused(
    console: dict,
    viewer: Any,
    lag_document: dict,  # noqa: F811
) -> None:
    store = console["stores"]["mill-a"]
    proposal = publish(store, lag_document, machine="mill-a")
    viewer.get(console["url"] + "/machines/mill-a/proposals")
    assert viewer.find_element(By.ID, f"proposal-{proposal.id}")
    assert not viewer.find_elements(By.CSS_SELECTOR, "button.promote")
    assert not viewer.find_elements(By.ID, "rollback")
    screenshot(viewer, "proposals-viewer")
    statuses = asyncio.run(_forgeries(console["url"], proposal.id))
    assert statuses == {"viewer": 403, "no token": 403, "other site": 403, "no session": 401}
    assert ProposalStore(store).get(proposal.id).status == "proposed"


def test_an_operator_promotes_and_the_model_in_force_changes(
    console: dict,
    operator: Any,
    lag_document: dict,  # noqa: F811
) -> None:
    store = console["stores"]["mill-a"]
    opened = [p for p in ProposalStore(store).list(machine_id="mill-a") if p.open]
    proposal = opened[0] if opened else publish(store, lag_document, machine="mill-a")
    operator.get(console["url"] + "/machines/mill-a/proposals")
    screenshot(operator, "proposals-operator")
    operator.find_element(By.ID, f"promote-{proposal.id}").click()
    message = wait(lambda: operator.find_element(By.ID, "message").text, 20, "the outcome")
    assert "version 1" in message, message
    assert ProposalStore(store).get(proposal.id).status == "promoted"
    operator.get(console["url"] + "/")
    model = '#row-mill-a [data-f="model_id"]'
    wait(lambda: lag_document["model_id"] in css(operator, model).text, 10, "the model in force")


def test_reports_are_browsable_and_nothing_outside(console: dict, viewer: Any) -> None:
    folder = console["reports"]
    (folder / "ch5").mkdir(parents=True)
    (folder / "ch5" / "index.html").write_text("<h1>Residual analysis ch5</h1>")
    viewer.get(console["url"] + "/reports")
    viewer.find_element(By.LINK_TEXT, "ch5").click()
    assert "Residual analysis ch5" in viewer.find_element(By.TAG_NAME, "h1").text
    outside = "/reports/..%2Fconfig.yaml"
    assert asyncio.run(_status(console["url"], VIEWER, outside)) == 404


async def _login(session: aiohttp.ClientSession, url: str, user: tuple[str, str]) -> str:
    """Log in; the CSRF token of the session (read from a page, as a browser would)."""
    form = {"username": user[0], "password": user[1], "next": "/"}
    async with session.post(url + "/login", data=form) as response:
        assert response.status == 200, await response.text()
        page = await response.text()
    return page.split('name="csrf" value="', 1)[1].split('"', 1)[0]


async def _get(url: str, user: tuple[str, str], path: str) -> str:
    async with session() as client:
        await _login(client, url, user)
        async with client.get(url + path) as response:
            assert response.status == 200
            return await response.text()


async def _status(url: str, user: tuple[str, str], path: str) -> int:
    async with session() as client:
        await _login(client, url, user)
        async with client.get(url + path) as response:
            return response.status


async def _forgeries(url: str, proposal_id: str) -> dict[str, int]:
    """A viewer's POST with a valid token, and an operator's without a token or from
    another site's page: each must be refused."""
    target = url + "/machines/mill-a/promote"
    statuses = {}
    async with session() as viewer:
        token = await _login(viewer, url, VIEWER)
        data = {"csrf": token, "proposal": proposal_id}
        async with viewer.post(target, data=data, allow_redirects=False) as response:
            statuses["viewer"] = response.status
    async with session() as operator:
        token = await _login(operator, url, OPERATOR)
        data = {"proposal": proposal_id}
        async with operator.post(target, data=data, allow_redirects=False) as response:
            statuses["no token"] = response.status
        evil = {"Origin": "http://attacker.example"}
        data = {"csrf": token, "proposal": proposal_id}
        async with operator.post(
            target, data=data, headers=evil, allow_redirects=False
        ) as response:
            statuses["other site"] = response.status
    nobody = session()
    async with nobody, nobody.post(target, data={"proposal": proposal_id}) as response:
        statuses["no session"] = response.status
    return statuses
