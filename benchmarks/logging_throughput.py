"""Logging throughput: points per second into a real InfluxDB and into the local store,
and how fast the disk buffer replays after an outage.

Points are the gateway's own (``points_from_record`` of synthetic cycle records:
one cycle point + 9 temperature points per machine and cycle). Measured in one
run on this machine:

- ``sink_append``: the runtime's hot path with InfluxDB configured — appending a
  cycle's points to the disk buffer (batches of one cycle);
- ``local_store``: the embedded store, one cycle per write;
- ``influx_direct``: batches of 5000 written straight to the tests' InfluxDB
  (tests/influx_server.py);
- ``buffer_replay``: points buffered while the database was down, then drained
  by the forwarder once it is back.

    .venv/bin/python benchmarks/logging_throughput.py [--cycles 20000]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.outputs.disk_buffer import PointBuffer  # noqa: E402
from gateway.outputs.influx import Forwarder, InfluxWriter  # noqa: E402
from gateway.outputs.local_store import LocalStore  # noqa: E402
from gateway.outputs.points import Point, points_from_record  # noqa: E402
from tests.influx_server import InfluxServer  # noqa: E402
from tests.records import written_record  # noqa: E402

SENSORS = [f"T{i}" for i in range(1, 10)]


def cycle_points(cycles: int, epoch_s: float) -> list[list[Point]]:
    batches = []
    for k in range(cycles):
        record = written_record(
            f"vmc-{k % 4}",
            float(k),
            {s: 20.0 + 0.001 * k + i for i, s in enumerate(SENSORS)},
            10.0,
            regime="constant",
            model_id="mlr-error_um-constant",
            predicted_um=10.0 + 0.001 * k,
            write_status="ok: tracking",
        )
        batches.append(points_from_record(record, epoch_s))
    return batches


def rate(points: int, seconds: float) -> dict[str, float]:
    return {"points": points, "seconds": round(seconds, 3), "points_per_s": round(points / seconds)}


async def main_async(cycles: int) -> dict[str, object]:
    folder = Path(tempfile.mkdtemp(prefix="logging-throughput-"))
    batches = cycle_points(cycles, epoch_s=time.time() - cycles)
    total = sum(len(b) for b in batches)
    result: dict[str, object] = {"points_per_cycle": len(batches[0]), "cycles": cycles}

    buffer = PointBuffer(folder / "buffer.sqlite", max_points=10 * total)
    start = time.perf_counter()
    for batch in batches:
        buffer.append(batch)
    result["sink_append"] = rate(total, time.perf_counter() - start)

    store = LocalStore(folder / "points.sqlite")
    start = time.perf_counter()
    for batch in batches:
        store.write(batch)
    result["local_store"] = rate(total, time.perf_counter() - start)
    store.close()

    with InfluxServer(folder / "influx") as server:
        bucket = server.create_database("bench")
        writer = InfluxWriter(server.url, server.token, server.org, bucket, timeout_s=30.0)
        flat = [p for batch in batches for p in batch]
        start = time.perf_counter()
        for i in range(0, len(flat), 5000):
            writer.write_sync(flat[i : i + 5000])
        result["influx_direct"] = rate(len(flat), time.perf_counter() - start)

        # The buffer filled while the database was "away" (above); now it is back.
        replay_bucket = server.create_database("replay")
        forwarder = Forwarder(
            buffer, InfluxWriter(server.url, server.token, server.org, replay_bucket, 30.0)
        )
        start = time.perf_counter()
        forwarder.start()
        drained = await forwarder.flush(timeout=600.0)
        elapsed = time.perf_counter() - start
        await forwarder.stop()
        result["buffer_replay"] = {**rate(total, elapsed), "drained": drained, "left": len(buffer)}
        writer.close()
    buffer.close()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=20000)
    args = parser.parse_args()
    print(json.dumps(asyncio.run(main_async(args.cycles)), indent=2))


if __name__ == "__main__":
    main()
