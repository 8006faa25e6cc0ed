"""An HTTP reverse proxy in front of a real InfluxDB that answers some writes itself.

It stands for what sits between a gateway and its database in a plant (a load
balancer, an API gateway, InfluxDB Cloud's rate limits): scripted answers
(``429`` with ``Retry-After``, ``500``, ``503``) for the next writes, and a body
size limit that answers ``413`` like nginx's ``client_max_body_size``. Everything
else — and every write it lets through — goes to the real server unchanged, so
what the test reads back is what InfluxDB stored.

Runs in the test's event loop (aiohttp); the gateway's writer talks to it from its
worker thread over loopback.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import aiohttp
from aiohttp import web

from tests.ports import free_tcp_port

HOP_HEADERS = {"host", "content-length", "transfer-encoding", "connection", "keep-alive"}


@dataclass
class Write:
    """One write request the proxy saw: when, how big, and what it was answered."""

    time_s: float  # time.monotonic() when the answer went out
    body_bytes: int
    lines: int
    status: int


@dataclass
class AnsweringProxy:
    """``url`` forwards to ``upstream``; ``script`` answers the next writes instead."""

    upstream: str
    max_body_bytes: int | None = None
    script: list[tuple[int, dict[str, str]]] = field(default_factory=list)
    writes: list[Write] = field(default_factory=list)
    port: int = field(default_factory=free_tcp_port)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    async def start(self) -> None:
        self._session = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=30))
        app = web.Application(client_max_size=256 * 1024 * 1024)
        app.router.add_route("*", "/{tail:.*}", self._handle)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, "127.0.0.1", self.port).start()

    async def stop(self) -> None:
        await self._runner.cleanup()
        await self._session.close()

    async def __aenter__(self) -> AnsweringProxy:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def statuses(self) -> list[int]:
        return [w.status for w in self.writes]

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        body = await request.read()
        if request.path.endswith("/write"):
            answer = self._own_answer(body)
            if answer is not None:
                return answer
        reply = await self._forward(request, body)
        if request.path.endswith("/write"):
            self._seen(body, reply.status)
        return reply

    def _own_answer(self, body: bytes) -> web.Response | None:
        if self.script:
            status, headers = self.script.pop(0)
            return self._refuse(body, status, headers, "injected by the test proxy")
        if self.max_body_bytes is not None and len(body) > self.max_body_bytes:
            limit = f"request body of {len(body)} bytes over {self.max_body_bytes}"
            return self._refuse(body, 413, {}, limit)
        return None

    def _refuse(self, body: bytes, status: int, headers: dict[str, str], why: str) -> web.Response:
        self._seen(body, status)
        text = json.dumps({"code": "proxy", "message": why})
        return web.Response(
            status=status, text=text, content_type="application/json", headers=headers
        )

    def _seen(self, body: bytes, status: int) -> None:
        lines = body.count(b"\n") + 1 if body else 0
        self.writes.append(Write(time.monotonic(), len(body), lines, status))

    async def _forward(self, request: web.Request, body: bytes) -> web.Response:
        headers = {k: v for k, v in request.headers.items() if k.lower() not in HOP_HEADERS}
        async with self._session.request(
            request.method, self.upstream + request.path_qs, headers=headers, data=body
        ) as reply:
            content = await reply.read()
            out = {k: v for k, v in reply.headers.items() if k.lower() not in HOP_HEADERS}
            out.pop("Content-Encoding", None)  # aiohttp already decoded the body
            return web.Response(status=reply.status, body=content, headers=out)
