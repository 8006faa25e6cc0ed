"""The console's login over real HTTP: the SCADA throttle locks out password guessing,
and its configuration refuses a lone TLS file."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import aiohttp
import pytest
from pydantic import ValidationError

from gateway.config import WebSection
from gateway.scada.login_throttle import ThrottlePolicy
from gateway.scada.server import ScadaUser
from gateway.web.server import WebConsole, WebSettings
from tests.ports import free_tcp_port

OPERATOR = ScadaUser("olga", "op-secret-7", "operator")


def gateway_of(machines: list[str], tmp_path: Path) -> Any:
    """What the console reads of a gateway: its loops' ids and settings (no cycles run)."""
    comp = SimpleNamespace(unit="mm", sign=1, axes=None)
    loops = [
        SimpleNamespace(
            config=SimpleNamespace(id=m, compensation=comp),
            compensation_enabled=True,
            cycles=0,
            promotions=SimpleNamespace(version=0),
        )
        for m in machines
    ]
    logging = SimpleNamespace(influxdb=None, local_store=tmp_path / "points.sqlite")
    return SimpleNamespace(
        loops=loops,
        supervisors={},
        config=SimpleNamespace(logging=logging),
        health=lambda machine: {"cycles": 0},
    )


@contextlib.asynccontextmanager
async def console_of(machines: list[str], tmp_path: Path) -> AsyncIterator[WebConsole]:
    """A console of ``machines`` (their store under ``tmp_path``) with one operator,
    started on a free port and stopped after the block."""
    settings = WebSettings(
        host="127.0.0.1", port=free_tcp_port(), users=[OPERATOR], throttle=ThrottlePolicy()
    )
    console = WebConsole(settings, gateway_of(machines, tmp_path))
    await console.start()
    try:
        yield console
    finally:
        await console.stop()


async def attempt(url: str, password: str) -> int:
    jar = aiohttp.CookieJar(unsafe=True)
    async with aiohttp.ClientSession(cookie_jar=jar) as client:
        form = {"username": OPERATOR.username, "password": password}
        async with client.post(url + "/login", data=form, allow_redirects=False) as response:
            return response.status


def test_guessing_locks_the_account_out_even_for_the_right_password(tmp_path: Path) -> None:
    async def scenario() -> list[int]:
        settings = WebSettings(
            host="127.0.0.1",
            port=free_tcp_port(),
            users=[OPERATOR],
            throttle=ThrottlePolicy(max_failures=3, window_s=60, lockout_s=30),
        )
        console = WebConsole(settings, gateway_of(["m1"], tmp_path))
        await console.start()
        try:
            url = console.url.rstrip("/")
            right = await attempt(url, OPERATOR.password)
            wrong = [await attempt(url, f"guess-{i}") for i in range(3)]
            locked = await attempt(url, OPERATOR.password)
            return [right, *wrong, locked]
        finally:
            await console.stop()

    assert asyncio.run(scenario()) == [303, 401, 401, 401, 401]


def test_pages_need_a_login(tmp_path: Path) -> None:
    async def scenario() -> tuple[int, str, int]:
        settings = WebSettings(
            host="127.0.0.1", port=free_tcp_port(), users=[OPERATOR], throttle=ThrottlePolicy()
        )
        console = WebConsole(settings, gateway_of(["m1"], tmp_path))
        await console.start()
        try:
            async with aiohttp.ClientSession() as client:
                url = console.url.rstrip("/")
                async with client.get(url + "/machines/m1", allow_redirects=False) as page:
                    status, where = page.status, page.headers.get("Location", "")
                async with client.get(url + "/rows.json", allow_redirects=False) as rows:
                    return status, where, rows.status
        finally:
            await console.stop()

    assert asyncio.run(scenario()) == (303, "/login?next=/machines/m1", 303)


def test_a_console_without_accounts_or_with_half_a_tls_pair_is_refused(tmp_path: Path) -> None:
    settings = WebSettings(host="127.0.0.1", port=1, users=[], throttle=ThrottlePolicy())
    with pytest.raises(ValueError, match="no users to log in with"):
        WebConsole(settings, gateway_of(["m1"], tmp_path))
    with pytest.raises(ValidationError, match="tls_cert and tls_key go together"):
        WebSection.model_validate({"tls_cert": str(tmp_path / "c.pem")})


def test_a_login_starts_the_plot_worker_and_a_wrong_password_does_not(tmp_path: Path) -> None:
    """The first plot after a login does not wait for a new interpreter to start: the
    login starts the worker process (and its imports); a failed one starts nothing."""

    async def scenario() -> tuple[bool, bool, bool]:
        settings = WebSettings(
            host="127.0.0.1", port=free_tcp_port(), users=[OPERATOR], throttle=ThrottlePolicy()
        )
        console = WebConsole(settings, gateway_of(["m1"], tmp_path))
        await console.start()
        try:
            url = console.url.rstrip("/")
            assert await attempt(url, "wrong") == 401
            after_failure = console.renderer._pool is not None
            assert await attempt(url, OPERATOR.password) == 303
            pool = console.renderer._pool
            started = pool is not None
            processes = await asyncio.get_running_loop().run_in_executor(
                None, lambda: pool.submit(int).result(timeout=60) == 0 and pool._processes
            )
            return after_failure, started, bool(processes)
        finally:
            await console.stop()

    assert asyncio.run(scenario()) == (False, True, True)
