"""A real ``run`` process whose wall clock steps, or whose host pauses, while it compensates.

The gateway runs as its own process under libfaketime (``LD_PRELOAD``): its wall clock
(``time.time()``) takes an offset the test writes to a file, read again at every call,
while ``FAKETIME_DONT_FAKE_MONOTONIC`` leaves its monotonic clock alone. That is what a
step of the system clock does to a process (``date -s``, an NTP step), and what a pause
of a virtual host leaves behind when its monotonic clock does not count the pause and
its wall clock is set right on resume: the two clocks apart by the pause. The simulated
machine (``simulate``, its own process), the Mosquitto broker, the Sparkplug host that
decodes every message (Eclipse Tahu's JavaScript library, tests/node/sparkplug_host.mjs)
and influxd run on the real clock.

* A step of −1 h and back: the cycles stay on the monotonic clock (no stall, no burst
  catching up), and every output of a cycle carries the same time, which follows the
  step: the local store's points, the Sparkplug DDATA and the heartbeat.
* A pause (SIGSTOP … SIGCONT) whose 10 s the monotonic clock missed: afterwards every
  Sparkplug DDATA arrives within a cycle or two of its own time, and its time is the
  time of the same cycle's points in InfluxDB.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.outputs.influx import InfluxReader
from gateway.outputs.local_store import LocalStore
from tests import gateway_rig as rig
from tests import served_bench as bench
from tests.influx_server import InfluxServer
from tests.mqtt_broker import PASSWORD, USER, Broker, mosquitto
from tests.ports import free_tcp_port, wait_for_port
from tests.sparkplug_host import TahuHost

ROOT = Path(__file__).resolve().parent.parent
#: Debian's libfaketime (package ``libfaketime``, installed by scripts/setup-system.sh).
LIBFAKETIME = Path("/usr/lib/x86_64-linux-gnu/faketime/libfaketimeMT.so.1")
GROUP, NODE, HOST = "plant1", "edge1", "scada"
MACHINE = "bench-1"
CYCLE_S = 1.0
HOUR_S = 3600


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("clock-step"))


class FakedWall:
    """The offset of one process's wall clock, s, in the file libfaketime reads."""

    def __init__(self, folder: Path) -> None:
        if not LIBFAKETIME.is_file():
            raise RuntimeError(
                f"{LIBFAKETIME} is missing: install Debian's libfaketime "
                "(scripts/setup-system.sh does)"
            )
        self.file = folder / "faketime-offset"
        self.offset_s = 0
        self.set(0)

    def set(self, offset_s: int) -> None:
        """Step the wall clock to real time + ``offset_s`` (a whole file, never half of one)."""
        part = self.file.with_suffix(".part")
        part.write_text(f"{offset_s:+d}\n")
        os.replace(part, self.file)
        self.offset_s = offset_s

    def env(self) -> dict[str, str]:
        return {
            "LD_PRELOAD": str(LIBFAKETIME),
            "FAKETIME_TIMESTAMP_FILE": str(self.file),
            "FAKETIME_NO_CACHE": "1",
            "FAKETIME_DONT_FAKE_MONOTONIC": "1",
        }


def bench_config(
    tmp_path: Path, store: Path, broker: Broker, logging: dict[str, Any]
) -> tuple[Path, int]:
    """The simulator's machine on Modbus TCP, compensated by a gateway that logs to
    ``logging`` and is a Sparkplug edge node on ``broker``; (the file, the CNC's port)."""
    bus, cnc = free_tcp_port(), free_tcp_port()
    config = bench.bench_config(store, bus, cnc, speedup=1.0, cycle_s=CYCLE_S)
    config["state_dir"] = str(tmp_path / "state")
    config["logging"] = logging
    config["sparkplug"] = {
        "brokers": [broker.url],
        "group_id": GROUP,
        "edge_node_id": NODE,
        "primary_host_id": HOST,
        "username": USER,
        "password_env": "SPB_TEST_PASSWORD",
        "ca_file": str(broker.ca_file),
        "startup_delay_max_s": 0.5,
        "reconnect_max_s": 2.0,
        "buffer_path": str(tmp_path / "spb.sqlite"),
    }
    return bench.write_config(config, tmp_path / "config.yaml"), cnc


class Arrivals:
    """When each message the Sparkplug host decoded came in (real wall time, s), as
    :meth:`poll` saw it: within one poll (50 ms) of its arrival."""

    def __init__(self, host: TahuHost) -> None:
        self.host = host
        self.at_s: list[float] = []

    def poll(self) -> None:
        now, seen = time.time(), len(self.host.lines)
        self.at_s.extend([now] * (seen - len(self.at_s)))

    def wait(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert self.host.process.poll() is None, "the Tahu host exited"
            assert time.monotonic() < deadline, f"{what}: not seen within {timeout_s:g} s"
            self.sleep(0.05)

    def sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.poll()
            time.sleep(0.05)
        self.poll()

    def ddata(self) -> list[tuple[int, int, float]]:
        """(cycle counter, timestamp ms, arrival s) of every DDATA of the machine."""
        found = []
        for line, arrived_s in zip(self.host.lines, self.at_s, strict=False):
            event = json.loads(line)
            if event.get("kind") != "DDATA" or event.get("device") != MACHINE:
                continue
            cycles = [m["value"] for m in event["metrics"] if m["name"] == "Health/cycles"]
            found.append((int(cycles[0]), int(event["timestamp"]), arrived_s))
        return found


@contextlib.contextmanager
def running(
    config: Path, cnc: int, wall: FakedWall, log: Path, env: dict[str, str] | None = None
) -> Iterator[subprocess.Popen[bytes]]:
    """``simulate`` (real clock) and ``run`` (on ``wall``, with ``env`` added) on ``config``
    for the block; the gateway stopped by SIGTERM at its end, its log in ``log``."""
    quiet: dict[str, Any] = {"cwd": ROOT, "stdout": subprocess.DEVNULL}
    simulator = subprocess.Popen([sys.executable, "-m", "gateway", "simulate", "--config",
                                  str(config)], **quiet)  # fmt: skip
    gateway = None
    try:
        wait_for_port(cnc)
        faked = {**os.environ, **(env or {}), **wall.env(), "SPB_TEST_PASSWORD": PASSWORD}
        with log.open("w") as out:
            gateway = subprocess.Popen(
                [sys.executable, "-m", "gateway", "run", "--config", str(config)],
                cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env=faked,
            )  # fmt: skip
        yield gateway
    finally:
        if gateway is not None and gateway.poll() is None:
            gateway.send_signal(signal.SIGCONT)  # a paused one must see its SIGTERM
            gateway.send_signal(signal.SIGTERM)
            try:
                gateway.wait(timeout=30)
            except subprocess.TimeoutExpired:
                gateway.kill()
                gateway.wait()
        simulator.send_signal(signal.SIGINT)
        simulator.wait(timeout=30)


def store_stamps(path: Path) -> list[int]:
    """The ``spindle_cycle`` stamps of the local store in the order they were written (one
    per cycle), ns. The store keeps points by time, so the cycles stamped during the step
    (an hour back) are put back in their place: the step is exactly ``HOUR_S``."""
    with LocalStore(path, set_aside_damaged=False) as local:
        stamps = [p.time_ns for p in local.query("spindle_cycle")]
    latest = max(stamps, default=0)
    hour_ns = HOUR_S * 10**9

    def written_at(t: int) -> int:
        return t + hour_ns if t < latest - hour_ns // 2 else t

    return sorted(stamps, key=written_at)


def test_a_wall_clock_step_moves_every_stamp_and_no_cycle(tmp_path: Path, store: Path) -> None:
    with mosquitto(tmp_path / "broker") as broker:
        host = TahuHost(broker, GROUP, HOST)
        try:
            arrivals = Arrivals(host)
            arrivals.wait(lambda: any('"online"' in line for line in host.lines), 20, "STATE")
            points = tmp_path / "points.sqlite"
            config, cnc = bench_config(tmp_path, store, broker, {"local_store": str(points)})
            wall = FakedWall(tmp_path)
            with running(config, cnc, wall, tmp_path / "run.log") as gateway:
                arrivals.wait(lambda: len(arrivals.ddata()) >= 5, 120, "5 DDATA")
                arrivals.sleep(3.0)
                wall.set(-HOUR_S)  # the system clock steps back an hour …
                arrivals.sleep(6.0)
                wall.set(0)  # … and is set right again
                arrivals.sleep(8.0)
                gateway.send_signal(signal.SIGTERM)
                assert gateway.wait(timeout=30) == 0, (tmp_path / "run.log").read_text()[-3000:]
            arrivals.sleep(1.0)
        finally:
            host.close()
    stamps_ns = store_stamps(points)
    beat = json.loads((tmp_path / "state" / f"{MACHINE}-heartbeat.json").read_text())
    assert beat["cycles"] == len(stamps_ns)
    # The outputs followed the step: the cycles run while it lasted are stamped an hour back.
    first_ns = stamps_ns[0]
    stepped = [i for i, t in enumerate(stamps_ns) if t < first_ns - HOUR_S // 2 * 10**9]
    assert 3 <= len(stepped) <= 8, len(stepped)
    assert stepped == list(range(stepped[0], stepped[-1] + 1))
    # The cycles did not: on the monotonic clock, one a second, no stall, no burst.
    real_s = [(t + (HOUR_S * 10**9 if i in stepped else 0)) / 1e9 for i, t in enumerate(stamps_ns)]
    gaps = [b - a for a, b in itertools.pairwise(real_s)]
    around = gaps[max(stepped[0] - 3, 0) : stepped[-1] + 6]
    print(f"step: {len(stepped)} cycles stamped an hour back, gaps {min(around):.2f}-"
          f"{max(around):.2f} s around the step")  # fmt: skip
    assert max(around) < 3.0 * CYCLE_S, around
    span_s = real_s[stepped[-1] + 6] - real_s[stepped[0] - 3]
    assert len(around) <= span_s / CYCLE_S + 2, (len(around), span_s)
    # One time per cycle in every output: the k-th cycle's DDATA carries its points' stamp.
    ddata = arrivals.ddata()
    assert [c for c, _, _ in ddata] == list(range(1, len(ddata) + 1))
    assert len(ddata) >= len(stamps_ns) - 2, (len(ddata), len(stamps_ns))
    by_cycle = {cycle: timestamp_ms for cycle, timestamp_ms, _ in ddata}
    for i in stepped:  # the step first: Sparkplug follows it as the log does
        assert abs(by_cycle[i + 1] * 1_000_000 - stamps_ns[i]) <= 500_001, (i + 1, by_cycle)
    for cycle, timestamp_ms, _ in ddata:
        # Sparkplug keeps whole milliseconds: the same time, rounded.
        assert abs(timestamp_ms * 1_000_000 - stamps_ns[cycle - 1]) <= 500_001, cycle
    assert round(beat["time_s"] * 1e9) == pytest.approx(stamps_ns[-1], abs=1_000)


def test_after_a_pause_the_monotonic_clock_missed_sparkplug_and_influxdb_agree_with_the_wall(
    tmp_path: Path, store: Path
) -> None:
    pause_s, missed_s = 2.0, 10  # the process stopped 2 s; its host's monotonic missed 10 more
    with InfluxServer(tmp_path / "influxdb") as influx, mosquitto(tmp_path / "broker") as broker:
        bucket = influx.create_bucket("gateway")
        host = TahuHost(broker, GROUP, HOST)
        try:
            arrivals = Arrivals(host)
            arrivals.wait(lambda: any('"online"' in line for line in host.lines), 20, "STATE")
            logging = {
                "influxdb": {
                    "url": influx.url,
                    "org": influx.org,
                    "bucket": bucket,
                    "token_env": "INFLUX_TEST_TOKEN",
                },
                "buffer_path": str(tmp_path / "buffer.sqlite"),
            }
            config, cnc = bench_config(tmp_path, store, broker, logging)
            wall = FakedWall(tmp_path)
            log = tmp_path / "run.log"
            token = {"INFLUX_TEST_TOKEN": influx.token}
            with running(config, cnc, wall, log, token) as gateway:
                arrivals.wait(lambda: len(arrivals.ddata()) >= 5, 120, "5 DDATA")
                gateway.send_signal(signal.SIGSTOP)  # no cycle, no point anywhere …
                arrivals.sleep(pause_s)
                wall.set(missed_s)  # … and on resume the wall is 10 s ahead of monotonic time
                gateway.send_signal(signal.SIGCONT)
                resumed_s = time.time()
                arrivals.sleep(10.0)
                beat = json.loads((tmp_path / "state" / f"{MACHINE}-heartbeat.json").read_text())
                reader = InfluxReader(influx.url, influx.token, influx.org, bucket)
                try:
                    logged_ns = [p.time_ns for p in reader.query("spindle_cycle", MACHINE)]
                finally:
                    reader.close()
                assert gateway.poll() is None, log.read_text()[-3000:]
        finally:
            host.close()
    # The cycles started after the resume (arrived 3 s after it: the cycle cut by the
    # stop and the backlog of the pause are out) carry the gateway's wall time.
    after = [(c, ms, at_s) for c, ms, at_s in arrivals.ddata() if at_s > resumed_s + 3.0]
    assert len(after) >= 4, arrivals.ddata()[-12:]
    behind_s = [at_s + missed_s - ms / 1000 for _, ms, at_s in after]
    print(f"pause: {len(after)} DDATA after it arrived {min(behind_s):.2f}-{max(behind_s):.2f} s "
          "after their time")  # fmt: skip
    for (cycle, _, _), behind in zip(after, behind_s, strict=True):
        assert -0.5 < behind < 3.0 * CYCLE_S, (cycle, behind)
    # InfluxDB has the same cycles at the same times (Sparkplug's are whole milliseconds).
    assert logged_ns, "nothing reached InfluxDB"
    matched = [ms for _, ms, _ in after if any(abs(ms * 1e6 - t) <= 5e5 + 1e3 for t in logged_ns)]
    in_influx = [ms for _, ms, _ in after if ms * 1e6 <= logged_ns[-1] + 5e5]
    assert len(in_influx) >= 2, (after, logged_ns[-5:])
    assert matched == in_influx
    # And the heartbeat's cycle time is its wall time, less the cycle.
    assert 0.0 <= beat["wall_time"] - beat["time_s"] < 3.0 * CYCLE_S, beat
