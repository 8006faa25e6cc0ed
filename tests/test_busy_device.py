"""A transmitter module that answers "slave device busy" (Modbus exception 06) now and then.

A real pymodbus server (the simulator's transmitter modules) answers every other
request with exception 06, as a module does while it converts. The gateway's bus
asks again after a short back-off within the cycle, so no cycle loses its
temperatures, and counts the requests it sent again.
"""

from __future__ import annotations

import asyncio
from typing import Any

from pymodbus.constants import ExcCodes

from drivers.transmitters import ModbusConnection, TransmitterBus
from simulator.link import FixedLink
from simulator.servers import modbus_transmitters
from simulator.servers.modbus_transmitters import TransmitterServer
from tests.test_drivers_transmitters import (
    DEVICE_1,
    DEVICE_2,
    EXPECTED,
    HOST,
    SERVED,
    SNAPSHOT,
    assert_expected,
)

CYCLES = 20


class FlappingServer(TransmitterServer):
    """Transmitter modules that answer every ``busy_every``-th request with exception 06."""

    def __init__(self, *args: Any, busy_every: int, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.busy_every = busy_every
        self.asked = 0
        self.busy_sent = 0

    def _make_server(self) -> Any:
        original = modbus_transmitters._module_action

        def flapping(layout: Any) -> Any:
            action = original(layout)

            async def busy_sometimes(*request: Any) -> ExcCodes | None:
                if request[-1] is not None:  # a write (the server's own updates): no reply
                    return await action(*request)
                self.asked += 1
                if self.asked % self.busy_every == 0:
                    self.busy_sent += 1
                    return ExcCodes.DEVICE_BUSY
                return await action(*request)

            return busy_sometimes

        modbus_transmitters._module_action = flapping
        try:
            return super()._make_server()
        finally:
            modbus_transmitters._module_action = original


def read_cycles(busy_every: int) -> tuple[int, int, int]:
    """``CYCLES`` reads of two modules; (cycles with every sensor, busy replies, resends)."""

    async def body() -> tuple[int, int, int]:
        link = FixedLink(SNAPSHOT)
        server = FlappingServer(link, SERVED, tcp=(HOST, 0), busy_every=busy_every)
        async with server:
            bus = TransmitterBus([DEVICE_1, DEVICE_2], tcp=server.address, timeout_s=0.5)
            whole = 0
            try:
                for cycle in range(CYCLES):
                    results = await bus.read_all(float(cycle))
                    if all(
                        results[name].error is None or name in ("T3", "T4", "T5")
                        for name in EXPECTED
                    ):
                        assert_expected(results, list(EXPECTED))
                        whole += 1
                connection = bus.hub.link
                assert isinstance(connection, ModbusConnection)
                return whole, server.busy_sent, connection.busy_retries
            finally:
                await bus.close()

    return asyncio.run(asyncio.wait_for(body(), 60))


def test_a_device_busy_every_other_request_loses_no_cycle() -> None:
    whole, busy_sent, resent = read_cycles(busy_every=2)
    assert busy_sent >= CYCLES  # two modules a cycle, every other request busy
    assert whole == CYCLES
    assert resent == busy_sent


def test_a_device_that_stays_busy_fails_its_cycle_after_a_bounded_wait() -> None:
    whole, busy_sent, resent = read_cycles(busy_every=1)
    assert whole == 0
    # Per request the first answer and three more, 50 ms of back-off in all.
    assert busy_sent == 4 * 2 * CYCLES
    assert resent == 3 * 2 * CYCLES
