"""Drives tests/node/sparkplug_host.mjs, an independent Sparkplug B host (Eclipse Tahu's
JavaScript payload library), and collects the messages it decoded."""

from __future__ import annotations

import asyncio
import json
import subprocess
import threading
import time
from collections import Counter
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
        # The decoded messages as the host printed them: strings, which the garbage
        # collector does not track. Thousands of parsed messages (dicts of dicts) in the
        # process the gateway runs in made its full collections stall the loops ~1 s.
        self.lines: list[str] = []
        # Kept up to date as events arrive, so that waiting on them costs the event loop
        # (which the gateway under test shares) nothing however long the run.
        self._counts: Counter[tuple[str, str | None]] = Counter()
        self._last_cycle: dict[str, int] = {}
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            event = json.loads(line)
            with self._lock:
                self.lines.append(line)
                if event["event"] == "message":
                    self._count(event)
            del event

    def _count(self, event: dict[str, Any]) -> None:
        kind, device = event["kind"], event["device"]
        self._counts[kind, device] += 1
        self._counts[kind, None] += device is not None
        if kind == "DDATA":
            for metric in event["metrics"]:
                if metric["name"] == "Health/cycles":
                    self._last_cycle[device] = metric["value"]

    def count(self, kind: str, device: str | None = None) -> int:
        """Messages of ``kind`` (of ``device``; of every device, or the node's own)."""
        with self._lock:
            return self._counts[kind, device]

    def last_cycle(self, device: str) -> int:
        """The cycle counter of ``device``'s latest DDATA (0 before any)."""
        with self._lock:
            return self._last_cycle.get(device, 0)

    def snapshot(self) -> list[dict[str, Any]]:
        with self._lock:
            lines = list(self.lines)
        return [json.loads(line) for line in lines]

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
