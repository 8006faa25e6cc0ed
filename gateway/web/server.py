"""The web console: an aiohttp server in the gateway's own event loop.

Handlers only read the live board (kept by a sink that stores one record per
cycle) or hand work to the plot process, so a browser never delays a cycle.
Every page needs a login; see :mod:`gateway.web.auth` for the security and
docs/console.md for what each page shows.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aiohttp import web

from gateway.config import login_limits
from gateway.live.record import CycleRecord
from gateway.scada.login_throttle import ThrottlePolicy
from gateway.scada.server import ScadaUser
from gateway.web.auth import SESSION, Auth
from gateway.web.backend import Backend, GatewayLike
from gateway.web.live import LiveBoard
from gateway.web.pages import Pages
from gateway.web.plots import PlotRenderer

log = logging.getLogger(__name__)

STATIC = Path(__file__).with_name("static")
FAVICON = STATIC / "favicon.svg"
OPEN_PATHS = ("/login", "/static/", "/favicon.ico")
#: Sent with every response: pages, redirects, 404s, refusals, errors and static files.
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'",
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
}


@dataclass(frozen=True, kw_only=True)
class WebSettings:
    host: str
    port: int
    users: Sequence[ScadaUser]
    throttle: ThrottlePolicy
    session_s: float = 12 * 3600.0
    tls_cert: Path | None = None
    tls_key: Path | None = None
    reports_dir: Path | None = None
    tick_s: float = 1.0


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class WebConsole:
    """Start with :meth:`start`, feed :meth:`record` every cycle, end with :meth:`stop`."""

    def __init__(self, settings: WebSettings, gateway: GatewayLike) -> None:
        if not settings.users:
            raise ValueError("web: no users to log in with (give web.users or scada.users)")
        self.settings = settings
        self.backend = Backend(gateway)
        self.board = LiveBoard(self.backend.machines, self.backend.facts, settings.tick_s)
        self.auth = Auth(settings.users, settings.throttle, settings.session_s)
        self.renderer = PlotRenderer()
        self.pages = Pages(
            self.backend,
            self.board,
            self.auth,
            self.renderer,
            settings.reports_dir,
            secure=settings.tls_cert is not None,
        )
        self._runner: web.AppRunner | None = None
        self._stop = asyncio.Event()
        self._ticker: asyncio.Task[None] | None = None

    @property
    def url(self) -> str:
        scheme = "https" if self.settings.tls_cert else "http"
        return f"{scheme}://{self.settings.host}:{self.settings.port}/"

    def record(self, record: CycleRecord) -> None:
        """The gateway's sink (cheap: the board keeps the record for its next tick)."""
        self.board.record(record)

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._session_middleware], client_max_size=64 * 1024)
        app.on_response_prepare.append(_security_headers)
        p = self.pages
        app.add_routes(
            [
                web.get("/login", p.login_form),
                web.post("/login", p.login),
                web.post("/logout", p.logout),
                web.get("/", p.overview),
                web.get("/rows.json", p.rows_json),
                web.get("/events", p.events_stream),
                web.get("/machines/{machine}", p.machine),
                web.get("/machines/{machine}/plot.svg", p.machine_plot),
                web.get("/machines/{machine}/proposals", p.proposals),
                web.get("/machines/{machine}/proposals/{proposal}/plot.svg", p.proposal_plot),
                web.post("/machines/{machine}/{action}", p.action),
                web.get("/reports", p.reports),
                web.get("/reports/{path:.+}", p.report_file),
                web.get("/favicon.ico", _favicon),
                web.static("/static", STATIC),
            ]
        )
        return app

    @web.middleware
    async def _session_middleware(
        self, request: web.Request, handler: Handler
    ) -> web.StreamResponse:
        session = self.auth.session(request)
        request[SESSION] = session
        if session is None and not request.path.startswith(OPEN_PATHS):
            if request.method == "GET":
                raise web.HTTPSeeOther(f"/login?next={request.path}")
            raise web.HTTPUnauthorized(text="log in first")
        return await handler(request)

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app(), access_log=None, shutdown_timeout=1.0)
        await self._runner.setup()
        site = web.TCPSite(
            self._runner, self.settings.host, self.settings.port, ssl_context=self._tls()
        )
        await site.start()
        self._ticker = asyncio.create_task(self.board.run(self._stop), name="web console ticker")
        log.info("web console at %s", self.url)

    def _tls(self) -> ssl.SSLContext | None:
        if self.settings.tls_cert is None or self.settings.tls_key is None:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.settings.tls_cert, self.settings.tls_key)
        return context

    async def stop(self) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._ticker
        if self._runner is not None:
            await self._runner.cleanup()
        self.renderer.close()


async def _security_headers(request: web.Request, response: web.StreamResponse) -> None:
    """Every response gets the headers, whoever made it: a handler, a redirect or refusal
    raised as an HTTPException, the router's 404/405, the static files, or aiohttp's own
    500 after an unexpected exception (a middleware sees none of the last)."""
    for name, value in SECURITY_HEADERS.items():
        response.headers.setdefault(name, value)


async def _favicon(request: web.Request) -> web.FileResponse:
    """The tab icon at the address browsers ask for first (an SVG: Chromium and Firefox
    take it from here too), so no page's load ends in a 404."""
    return web.FileResponse(FAVICON, headers={"Content-Type": "image/svg+xml"})


def build_web(config: Any, gateway: GatewayLike) -> WebConsole:
    """The console of ``config.web`` (users: its own, else the SCADA server's)."""
    section = config.web
    accounts = section.users if section.users is not None else getattr(config.scada, "users", [])
    users = tuple(ScadaUser(u.username, u.password() or "", u.role) for u in accounts)
    settings = WebSettings(
        host=section.host,
        port=section.port,
        users=users,
        throttle=login_limits(section),
        session_s=section.session_hours * 3600.0,
        tls_cert=section.tls_cert,
        tls_key=section.tls_key,
        reports_dir=section.reports_dir,
    )
    return WebConsole(settings, gateway)
