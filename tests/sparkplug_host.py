"""Drives tests/node/sparkplug_host.mjs, an independent Sparkplug B host (Eclipse Tahu's
JavaScript payload library), and collects the messages it decoded."""

from __future__ import annotations

import asyncio
import json
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.mqtt_broker import PASSWORD, USER, Broker

SCRIPT = Path(__file__).parent / "node" / "sparkplug_host.mjs"


class TahuHost:
    def __init__(self, broker: Broker, group: str, host_id: str) -> None:
        config = {
            "url": broker.url,
            "ca": str(broker.ca_file),
            "username": USER,
            "password": PASSWORD,
            "group": group,
            "host": host_id,
        }
        self.process = subprocess.Popen(
            ["node", str(SCRIPT), json.dumps(config)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self.events: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with self._lock:
                self.events.append(json.loads(line))

    def snapshot(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.events)

    def messages(self, kind: str | None = None, device: str | None = None) -> list[dict[str, Any]]:
        return [
            e
            for e in self.snapshot()
            if e["event"] == "message"
            and (kind is None or e["kind"] == kind)
            and (device is None or e["device"] == device)
        ]

    async def wait(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Poll ``condition`` without blocking the event loop the gateway runs on."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if condition():
                return
            if self.process.poll() is not None:
                stderr = self.process.stderr.read() if self.process.stderr else ""
                raise AssertionError(f"the Tahu host exited: {stderr}")
            await asyncio.sleep(0.05)
        raise AssertionError(f"{what}: not seen within {timeout_s:g} s")

    def send(self, **command: Any) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(json.dumps(command) + "\n")
        self.process.stdin.flush()

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(10)
