"""The console's pages: request handlers that render templates (no logic of their own
beyond choosing what to show)."""

from __future__ import annotations

import asyncio
import logging
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import jinja2
from aiohttp import web

from gateway.web import plots
from gateway.web.auth import COOKIE, SESSION, Auth, Session, csrf_ok, same_origin
from gateway.web.backend import Backend
from gateway.web.live import LiveBoard
from gateway.web.series import MachineView

log = logging.getLogger(__name__)

#: The machine page's windows (h): 720 is 30 days, drawn from the per-minute history.
WINDOWS_H = (1, 8, 24, 720)
LONGEST_RAW_H = 24
TEMPLATES = jinja2.Environment(
    loader=jinja2.PackageLoader("gateway.web", "templates"),
    autoescape=jinja2.select_autoescape(default=True),
)
TEMPLATES.filters["um"] = lambda v: f"{v:.1f}" if isinstance(v, int | float) else "–"
TEMPLATES.filters["clock"] = lambda t: datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


class Pages:
    """Every page and action; ``request["session"]`` is set by the server's middleware."""

    def __init__(
        self,
        backend: Backend,
        board: LiveBoard,
        auth: Auth,
        renderer: plots.PlotRenderer,
        reports_dir: Path | None,
        secure: bool,
    ) -> None:
        self.backend = backend
        self.board = board
        self.auth = auth
        self.renderer = renderer
        self.reports_dir = reports_dir
        self.secure = secure
        self._drawing: set[asyncio.Task[str]] = set()

    def page(self, name: str, request: web.Request, **context: Any) -> web.Response:
        session: Session | None = request.get(SESSION)
        html = TEMPLATES.get_template(name).render(
            session=session, machines=self.backend.machines, **context
        )
        return web.Response(text=html, content_type="text/html")

    # -- login ----------------------------------------------------------------------

    async def login_form(self, request: web.Request) -> web.Response:
        return self.page("login.html", request, failed=False, next=request.query.get("next", "/"))

    async def login(self, request: web.Request) -> web.Response:
        if not same_origin(request):
            raise web.HTTPForbidden(text="cross-site login refused")
        form = await request.post()
        address = request.remote or "unknown"
        sid = self.auth.login(str(form.get("username", "")), str(form.get("password", "")), address)
        if sid is None:
            response = self.page("login.html", request, failed=True, next="/")
            response.set_status(401)
            return response
        self.renderer.warm()
        target = str(form.get("next", "/"))
        response = web.HTTPSeeOther(target if target.startswith("/") else "/")
        response.set_cookie(
            COOKIE, sid, httponly=True, samesite="Strict", secure=self.secure, path="/"
        )
        raise response

    async def logout(self, request: web.Request) -> web.Response:
        self._check_post(request, await request.post())
        self.auth.logout(request.cookies.get(COOKIE, ""))
        response = web.HTTPSeeOther("/login")
        response.del_cookie(COOKIE, path="/")
        raise response

    # -- overview -------------------------------------------------------------------

    async def overview(self, request: web.Request) -> web.Response:
        return self.page("overview.html", request, rows=self.board.rows())

    async def rows_json(self, request: web.Request) -> web.Response:
        return web.json_response(self.board.rows())

    async def events_stream(self, request: web.Request) -> web.StreamResponse:
        """Server-sent events: the changed rows once per tick, until the browser leaves."""
        response = web.StreamResponse(
            headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store"}
        )
        await response.prepare(request)
        serial = self.board.serial  # the page just rendered holds the rows until now
        try:
            while True:
                serial, event = await self.board.next_event(serial)
                await response.write(event)
        except (ConnectionResetError, RuntimeError):
            pass
        return response

    # -- machine page ---------------------------------------------------------------

    def _machine(self, request: web.Request) -> str:
        machine = request.match_info["machine"]
        if machine not in self.backend.machines:
            raise web.HTTPNotFound(text=f"no machine {machine!r}")
        return machine

    def _window_h(self, request: web.Request) -> int:
        try:
            hours = int(request.query.get("h", "1"))
        except ValueError:
            hours = 0
        if hours not in self._windows_h():
            raise web.HTTPBadRequest(text=f"h must be one of {self._windows_h()}")
        return hours

    def _windows_h(self) -> tuple[int, ...]:
        """The windows offered: 30 days only from the local store (its per-minute
        history); from InfluxDB every row would be read."""
        local = self.backend.source()[0] == "local"
        return WINDOWS_H if local else tuple(h for h in WINDOWS_H if h <= LONGEST_RAW_H)

    async def _view(self, machine: str, hours: int) -> MachineView:
        """The window as the page shows it, read once in the plot process."""
        return await self.renderer.render(
            ("machine", machine, hours),
            plots.read_machine_view,
            self.backend.source(),
            machine,
            hours * 3600.0,
            self.backend.cnc_um_per_unit(machine),
            self.backend.axes(machine),
            max_age_s=self._max_age_s(hours),
        )

    async def _plot(self, machine: str, hours: int) -> str:
        """The window's SVG, drawn from the cached view in the plot process."""
        view = await self._view(machine, hours)
        return await self.renderer.render(
            ("machine-plot", machine, hours),
            plots.draw_machine,
            view,
            machine,
            max_age_s=self._max_age_s(hours),
        )

    def _draw_ahead(self, machine: str, hours: int) -> None:
        """Start drawing the plot now: the browser asks for it once it has the page."""
        task = asyncio.create_task(self._plot(machine, hours))
        self._drawing.add(task)
        task.add_done_callback(self._drawn)

    def _drawn(self, task: asyncio.Task[str]) -> None:
        """A drawing ahead is done; its failure, if any, is the plot request's to report."""
        self._drawing.discard(task)
        if not task.cancelled():
            task.exception()

    def _max_age_s(self, hours: int) -> float:
        """A longer window may be older: 15 s for 1 h, 2 min for 8 h, 6 min for 24 h,
        15 min for 30 days."""
        return self.renderer.cache_s * min(hours, 60)

    async def machine(self, request: web.Request) -> web.Response:
        machine, hours = self._machine(request), self._window_h(request)
        view = await self._view(machine, hours)
        self._draw_ahead(machine, hours)
        return self.page(
            "machine.html",
            request,
            machine=machine,
            hours=hours,
            windows=self._windows_h(),
            row=self.board.row(machine),
            events=view.events,
            stamp=int(time.time() // self._max_age_s(hours)),
        )

    async def machine_plot(self, request: web.Request) -> web.Response:
        machine, hours = self._machine(request), self._window_h(request)
        svg = await self._plot(machine, hours)
        return web.Response(text=svg, content_type="image/svg+xml")

    # -- proposals ------------------------------------------------------------------

    async def proposals(self, request: web.Request) -> web.Response:
        machine = self._machine(request)
        return self.page(
            "proposals.html",
            request,
            machine=machine,
            proposals=list(reversed(self.backend.proposals(machine))),
            version=self.backend.loop(machine).promotions.version,
            message=request.query.get("msg", ""),
        )

    async def proposal_plot(self, request: web.Request) -> web.Response:
        machine = self._machine(request)
        pid = request.match_info["proposal"]
        proposal = next((p for p in self.backend.proposals(machine) if p.id == pid), None)
        if proposal is None:
            raise web.HTTPNotFound(text=f"no proposal {pid!r} for {machine}")
        svg = await self.renderer.render(
            ("proposal", machine, pid),
            plots.render_proposal,
            self.backend.source(),
            machine,
            24 * 3600.0,
            proposal.before_rmse_um,
            proposal.after_rmse_um,
            list(self.backend.axes(machine)),
        )
        return web.Response(text=svg, content_type="image/svg+xml")

    async def action(self, request: web.Request) -> web.Response:
        """Promote, reject or roll back: operators only, same-origin, with the CSRF token."""
        form = await request.post()
        session = self._check_post(request, form)
        if not session.operator:
            raise web.HTTPForbidden(text="operators only")
        machine, what = self._machine(request), request.match_info["action"]
        pid = str(form.get("proposal", ""))
        by = f"console, {session.user}"
        try:
            if what == "promote":
                text = self.backend.promote(machine, pid, by)
            elif what == "reject":
                text = self.backend.reject(machine, pid, by)
            elif what == "rollback":
                text = self.backend.rollback(machine, by)
            else:
                raise web.HTTPNotFound(text=f"no action {what!r}")
        except (KeyError, ValueError) as exc:
            text = f"{what} refused: {exc.args[0] if exc.args else exc}"
        log.warning("console operator %s on %s: %s", session.user, machine, text)
        raise web.HTTPSeeOther(f"/machines/{machine}/proposals?" + _query(msg=text))

    def _check_post(self, request: web.Request, form: Any) -> Session:
        session: Session | None = request.get(SESSION)
        if session is None:
            raise web.HTTPUnauthorized(text="log in first")
        if not same_origin(request):
            raise web.HTTPForbidden(text="cross-site request refused (Origin/Referer)")
        if not csrf_ok(session, str(form.get("csrf", ""))):
            raise web.HTTPForbidden(text="missing or wrong CSRF token")
        return session

    # -- reports --------------------------------------------------------------------

    async def reports(self, request: web.Request) -> web.Response:
        found = []
        if self.reports_dir is not None and self.reports_dir.is_dir():
            found = sorted(p.parent.name for p in self.reports_dir.glob("*/index.html"))
        return self.page("reports.html", request, reports=found, folder=self.reports_dir)

    async def report_file(self, request: web.Request) -> web.FileResponse:
        if self.reports_dir is None:
            raise web.HTTPNotFound()
        root = self.reports_dir.resolve()
        path = (root / request.match_info["path"]).resolve()
        if not path.is_relative_to(root) or not path.is_file():
            raise web.HTTPNotFound()
        return web.FileResponse(path)


def _query(**values: str) -> str:
    from urllib.parse import urlencode

    return urlencode(values)
