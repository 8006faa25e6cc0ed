"""A transmitter module on RS-485 that answers "slave device busy" (Modbus exception 06).

A real RS-485 temperature module answers exception 06 while it converts. The
simulator's pymodbus transmitter server, on one end of a socat pty pair, answers a
chosen module's first reads busy; the gateway's RTU bus, on the other end, asks again
after 5, 15 and 30 ms, through the bus hub (its inter-frame silence kept), counts the
resends, and reads the other modules on the line while the busy one waits.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymodbus.constants import ExcCodes

from drivers.modbus_tcp import BUSY_BACKOFF_S
from drivers.transmitters import ChannelResult, ModbusConnection, TransmitterBus
from simulator.link import FixedLink
from simulator.servers import modbus_transmitters
from simulator.servers.modbus_transmitters import TransmitterServer
from tests.serial_pty import socat_pty_pair
from tests.test_drivers_transmitters import (
    DEVICE_1,
    DEVICE_2,
    EXPECTED,
    SERVED,
    SNAPSHOT,
    TIMEOUT_S,
    assert_expected,
    run,
)

DEVICE_1_SENSORS = ["T1", "T2", "T3", "T4", "T5"]
DEVICE_2_SENSORS = ["T9", "ambient"]


class BusyServer(TransmitterServer):
    """Transmitter modules of which some answer their first ``busy_replies[id]`` reads busy.

    ``log`` is every read the modules received, in order: (device id, answered busy).
    """

    def __init__(self, *args: Any, busy_replies: dict[int, float], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.busy_replies = dict(busy_replies)
        self.log: list[tuple[int, bool]] = []

    def _busy_action(self, device_id: int, action: Callable[..., Any]) -> Callable[..., Any]:
        async def busy_first(*request: Any) -> ExcCodes | None:
            if request[-1] is not None:  # a write (the server's own updates): no reply
                return await action(*request)
            busy = self.busy_replies.get(device_id, 0) > 0
            self.log.append((device_id, busy))
            if busy:
                self.busy_replies[device_id] -= 1
                return ExcCodes.DEVICE_BUSY
            return await action(*request)

        return busy_first

    def _make_server(self) -> Any:
        original = modbus_transmitters._module_action
        ids = iter([device.device_id for device in self.devices])  # one action per device

        def busy_action(layout: Any) -> Any:
            return self._busy_action(next(ids), original(layout))

        modbus_transmitters._module_action = busy_action
        try:
            return super()._make_server()
        finally:
            modbus_transmitters._module_action = original


def read_once(
    tmp_path: Path, busy_replies: dict[int, float]
) -> tuple[dict[str, ChannelResult], int, list[tuple[int, bool]], float]:
    """One cycle of both modules over a pty pair: (results, resends counted, what the
    server received, seconds the cycle took)."""

    async def body() -> tuple[dict[str, ChannelResult], int, list[tuple[int, bool]], float]:
        with socat_pty_pair(tmp_path) as pair:
            link = FixedLink(SNAPSHOT)
            server = BusyServer(link, SERVED, serial_port=pair.server_port, busy_replies={})
            async with server:
                await server.publish()
                bus = TransmitterBus(
                    [DEVICE_1, DEVICE_2], serial_port=pair.client_port, timeout_s=TIMEOUT_S
                )
                try:
                    server.busy_replies = dict(busy_replies)
                    loop = asyncio.get_running_loop()
                    started = loop.time()
                    results = await bus.read_all(1.0)
                    took_s = loop.time() - started
                    connection = bus.hub.link
                    assert isinstance(connection, ModbusConnection)
                    return results, connection.busy_retries, server.log, took_s
                finally:
                    await bus.close()

    return run(body)


def test_a_module_busy_twice_gives_its_reading_on_the_third_ask(tmp_path: Path) -> None:
    results, resent, log, _ = read_once(tmp_path, {1: 2})
    assert_expected(results, list(EXPECTED))
    assert resent == 2
    assert log == [(1, True), (2, False), (1, True), (1, False)]


def test_a_module_always_busy_has_no_reading_after_the_resends(tmp_path: Path) -> None:
    results, resent, log, took_s = read_once(tmp_path, {1: math.inf})
    for sensor in DEVICE_1_SENSORS:
        result = results[sensor]
        assert result.value_C is None and result.status is None, result
        assert result.error is not None and "stayed busy (exception 06)" in result.error
    assert_expected(results, DEVICE_2_SENSORS)  # the other module on the line is read
    assert resent == len(BUSY_BACKOFF_S)
    # The first ask and one per back-off; module 2 was read during module 1's first wait.
    assert log == [(1, True), (2, False)] + [(1, True)] * len(BUSY_BACKOFF_S)
    assert took_s >= sum(BUSY_BACKOFF_S)
    assert took_s < sum(BUSY_BACKOFF_S) + 2 * TIMEOUT_S  # bounded: no timeout waited
