"""The event loop the gateway's processes run on: uvloop by default, asyncio's own on request.

At fleet scale most of the poll path's CPU that is not the socket calls themselves is
the event loop's own work per request: polling, the transports' reads and writes,
timers and callbacks. uvloop (libuv, the loop Node.js runs on) does that work in C:
measured side by side with Telegraf on 1000 simulated Modbus TCP machines
(benchmarks/poll_vs_telegraf.py), the poll's CPU per request fell from 1.72× to
1.40× Telegraf's. asyncio's own loop stays one config key away (``event_loop:
asyncio``), for a platform uvloop does not build on or a fault to rule out.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from typing import Any, Literal, TypeVar

EventLoopName = Literal["uvloop", "asyncio"]
DEFAULT: EventLoopName = "uvloop"
T = TypeVar("T")


def loop_factory(name: EventLoopName = DEFAULT) -> Callable[[], asyncio.AbstractEventLoop]:
    """A function making a new loop of that kind."""
    if name == "uvloop":
        import uvloop

        return uvloop.new_event_loop
    if name == "asyncio":
        # The class, not asyncio.new_event_loop(): that follows the process's loop policy,
        # which may be uvloop's.
        return asyncio.SelectorEventLoop
    raise ValueError(f"event loop {name!r}: expected 'uvloop' or 'asyncio'")


def run(main: Coroutine[Any, Any, T], name: EventLoopName = DEFAULT) -> T:
    """``asyncio.run(main)`` on a loop of that kind."""
    with asyncio.Runner(loop_factory=loop_factory(name)) as runner:
        return runner.run(main)
