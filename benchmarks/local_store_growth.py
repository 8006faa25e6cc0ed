"""The local store's write cost as its file grows toward its size cap.

The gateway without InfluxDB logs every machine's cycle to the local store
(:class:`gateway.outputs.local_store.LocalStore`): the event-loop thread calls
``LocalStore.write`` once per machine and cycle with that cycle's points (one
``spindle_cycle`` point and one per sensor), one transaction each. This benchmark
fills one store file with a fleet's points (``--machines``, 9 sensors, 1-s cycles)
up to each of ``--sizes-gb`` and, at each size, times the writes of one second of
the fleet (``--machines`` writes of ``points_from_record`` points, as the sink
makes them) for each connection setting in ``VARIANTS``, one after another on the
same file: per block ``--warm-s`` seconds of writes first (the page cache of a
running gateway is warm), then ``--seconds`` timed ones. Reported per setting and size:
the median and 90th percentile of the thread CPU and wall time per second of data,
and the median bytes written (WAL frames and checkpoints) per second of data.

The file is filled fast with rows made from one second's template (the same
tables, keys and row sizes, 60 s of the fleet per transaction); the timed writes
go through ``LocalStore.write``. After each fill the WAL is checkpointed and the
OS's dirty pages flushed; each setting is then timed in ``--blocks`` blocks, the
order reversed every block. With ``--fleet-write`` the default settings are also
timed with the whole fleet's second in one write (one transaction per cycle instead
of one per machine and cycle). With ``--schemas-at GB`` the table made otherwise
(``SCHEMAS``: without rowid, without the time index) is compared too, each filled to
that size in a file of its own. Files live in a temporary folder (``--folder``).

    .venv/bin/python benchmarks/local_store_growth.py [--sizes-gb 0.01 0.5 1 2 4]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.outputs.points import Point, points_from_record  # noqa: E402
from tests import json_layout_store as local_store  # noqa: E402
from tests.json_layout_store import JsonLocalStore as LocalStore  # noqa: E402
from tests.json_layout_store import _tags_text  # noqa: E402
from tests.records import written_record  # noqa: E402

SENSORS = [f"T{i}" for i in range(1, 10)]
EPOCH_S = 1.7e9
FILL_SECONDS_PER_TRANSACTION = 60  # 1 below FINE_FILL_BYTES, to stop close to a small size
FINE_FILL_BYTES = 100_000_000
MAX_BYTES = 8_000_000_000  # the default logging.local_store_max_mb

#: Connection settings compared: the PRAGMAs run on the store's connection after opening.
VARIANTS: dict[str, list[str]] = {
    "default (2 MB cache)": [],
    "cache 64 MB": ["PRAGMA cache_size = -65536"],
    "mmap 2 GB": ["PRAGMA mmap_size = 2000000000"],
    "wal_autocheckpoint 10000": ["PRAGMA wal_autocheckpoint = 10000"],
}
#: With ``--schemas-at``: the store's table made otherwise (each in a file of its own).
SCHEMAS: dict[str, str] = {
    "default schema": local_store.SCHEMA,
    "WITHOUT ROWID": local_store.SCHEMA.replace(
        ");\nCREATE INDEX", ") WITHOUT ROWID;\nCREATE INDEX", 1
    ),
    "no points_by_time index": local_store.SCHEMA.replace(
        "CREATE INDEX IF NOT EXISTS points_by_time ON points (time_ns);", ""
    ),
}
#: With ``--fleet-write``: the default settings, but the whole fleet's second in one write.
FLEET_WRITE = "default, one write per second of the fleet"


def fleet_points(machines: int, second: int) -> list[list[Point]]:
    """One second of the fleet: each machine's cycle points, as the logging sink makes them."""
    batches = []
    for m in range(machines):
        record = written_record(
            f"vmc-{m:03d}",
            float(second),
            {s: 20.0 + 0.01 * (second % 500) + i + 0.001 * m for i, s in enumerate(SENSORS)},
            10.0 + 0.001 * (second % 1000),
            regime="variable",
            model_id=f"mlr-error_um-{m % 3}",
            predicted_um=10.0 + 0.001 * (second % 1000),
            write_status="ok: tracking",
        )
        batches.append(points_from_record(record, EPOCH_S))
    return batches


def fill(store: LocalStore, machines: int, start_s: int, target_bytes: int) -> int:
    """Add whole seconds of the fleet until the file holds ``target_bytes``; the next second."""
    template = [p for batch in fleet_points(machines, 0) for p in batch]
    rows = [
        (
            p.measurement,
            p.tags["machine"],
            _tags_text(p.tags),
            p.time_ns,
            json.dumps(p.fields, separators=(",", ":")),
        )
        for p in template
    ]  # the store's own row format (LocalStore.write)
    base_ns = template[0].time_ns
    second = start_s
    while (used := store.used_bytes()) < target_bytes:
        span = FILL_SECONDS_PER_TRANSACTION if used > FINE_FILL_BYTES else 1
        chunk = []
        for s in range(second, second + span):
            shift = s * 1_000_000_000 - base_ns + round(EPOCH_S * 1e9)
            chunk.extend((a, b, c, t + shift, f) for a, b, c, t, f in rows)
        store._insert(chunk)  # one big transaction, to fill fast
        second += span
    return second


def written_bytes() -> int:
    """Bytes this process has passed to write() so far (the WAL's frames and checkpoints)."""
    with open("/proc/self/io") as stream:
        return next(int(line.split()[1]) for line in stream if line.startswith("wchar:"))


def timed_seconds(
    store: LocalStore, machines: int, start_s: int, span: tuple[int, int], fleet_write: bool
) -> tuple[list[tuple[float, float, int]], int]:
    """Thread CPU s, wall s and bytes written of each timed second of writes (one write
    per machine, or one for the whole fleet); ``span`` is the warm and the timed seconds."""
    warm_s, seconds = span
    timed = []
    for k in range(warm_s + seconds):
        batches = fleet_points(machines, start_s + k)
        if fleet_write:
            batches = [[p for batch in batches for p in batch]]
        c0, w0, b0 = time.thread_time(), time.perf_counter(), written_bytes()
        for batch in batches:
            store.write(batch)
        c1, w1, b1 = time.thread_time(), time.perf_counter(), written_bytes()
        if k >= warm_s:
            timed.append((c1 - c0, w1 - w0, b1 - b0))
    return timed, start_s + warm_s + seconds


def summary(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {
        "median_ms": round(1000 * statistics.median(ordered), 1),
        "p90_ms": round(1000 * ordered[int(0.9 * (len(ordered) - 1))], 1),
    }


def settle(path: Path) -> None:
    """Checkpoint the WAL into the file and flush the OS's dirty pages, so the timed writes
    do not pay for the fill's write-back."""
    store = LocalStore(path, max_bytes=MAX_BYTES)
    store._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    store.close()
    os.sync()


def measure_variants(
    path: Path, args: argparse.Namespace, second: int
) -> tuple[dict[str, object], int]:
    """Each variant in ``args.blocks`` blocks, the order reversed every block (A B C, C B A,
    …) so that no variant always follows the fill or another; the blocks' seconds pooled."""
    names = [*VARIANTS, *([FLEET_WRITE] if args.fleet_write else [])]
    timed: dict[str, list[tuple[float, float, int]]] = {name: [] for name in names}
    for block in range(args.blocks):
        for name in names if block % 2 == 0 else names[::-1]:
            store = LocalStore(path, max_bytes=MAX_BYTES)
            for pragma in VARIANTS.get(name, []):
                store._db.execute(pragma)  # the setting compared
            span = (args.warm_s, args.seconds)
            seconds, second = timed_seconds(store, args.machines, second, span, name == FLEET_WRITE)
            store.close()
            timed[name].extend(seconds)
    return {
        name: {
            "cpu": summary([c for c, _, _ in timed[name]]),
            "wall": summary([w for _, w, _ in timed[name]]),
            "written_mb_per_s": round(statistics.median(b for _, _, b in timed[name]) / 1e6, 1),
        }
        for name in names
    }, second


def measure(args: argparse.Namespace, folder: Path) -> dict[str, object]:
    path = folder / "points.sqlite"
    second = 0
    results: dict[str, object] = {}
    for size_gb in args.sizes_gb:
        store = LocalStore(path, max_bytes=MAX_BYTES)
        started = time.perf_counter()
        second = fill(store, args.machines, second, round(size_gb * 1e9))
        fill_s = time.perf_counter() - started
        rows = len(store)
        used = store.used_bytes()
        store.close()
        settle(path)
        variants, second = measure_variants(path, args, second)
        results[f"{size_gb} GB"] = {
            "used_mb": round(used / 1e6),
            "rows": rows,
            "fill_s": round(fill_s, 1),
            **variants,
        }
        print(f"{size_gb} GB: {json.dumps(variants)}", file=sys.stderr, flush=True)
    return results


def compare_schemas(args: argparse.Namespace, folder: Path) -> dict[str, object]:
    """Each of ``SCHEMAS`` filled to ``--schemas-at`` GB in its own file, then timed in
    blocks as :func:`measure_variants` does (default connection settings)."""
    paths, second, results = {}, {}, {}
    default_schema = local_store.SCHEMA
    try:
        for name, schema in SCHEMAS.items():
            local_store.SCHEMA = schema  # what LocalStore creates its table with
            paths[name] = folder / f"schema-{len(paths)}.sqlite"
            store = LocalStore(paths[name], max_bytes=MAX_BYTES)
            second[name] = fill(store, args.machines, 0, round(args.schemas_at * 1e9))
            results[name] = {"used_mb": round(store.used_bytes() / 1e6), "rows": len(store)}
            store.close()
            settle(paths[name])
        timed: dict[str, list[tuple[float, float, int]]] = {name: [] for name in SCHEMAS}
        names = list(SCHEMAS)
        for block in range(args.blocks):
            for name in names if block % 2 == 0 else names[::-1]:
                local_store.SCHEMA = SCHEMAS[name]
                store = LocalStore(paths[name], max_bytes=MAX_BYTES)
                span = (args.warm_s, args.seconds)
                seconds, second[name] = timed_seconds(
                    store, args.machines, second[name], span, False
                )
                store.close()
                timed[name].extend(seconds)
    finally:
        local_store.SCHEMA = default_schema
    for name in SCHEMAS:
        results[name]["cpu"] = summary([c for c, _, _ in timed[name]])
        results[name]["wall"] = summary([w for _, w, _ in timed[name]])
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--machines", type=int, default=200)
    parser.add_argument("--sizes-gb", type=float, nargs="*", default=[0.1, 0.5, 1.0, 2.0])
    parser.add_argument("--warm-s", type=int, default=5, help="untimed seconds per block first")
    parser.add_argument("--seconds", type=int, default=15, help="timed seconds per block")
    parser.add_argument("--blocks", type=int, default=2, help="blocks per variant and size")
    parser.add_argument(
        "--fleet-write", action="store_true", help="also time one write per fleet second"
    )
    parser.add_argument(
        "--schemas-at", type=float, default=None, help="also compare SCHEMAS at this size, GB"
    )
    parser.add_argument("--folder", type=Path, default=None, help="where the file is made")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="local-store-growth-", dir=args.folder))
    try:
        result = {
            "machines": args.machines,
            "sensors": len(SENSORS),
            "points_per_write": len(fleet_points(1, 0)[0]),
            "sizes": measure(args, folder),
        }
        if args.schemas_at is not None:
            result["schemas"] = compare_schemas(args, folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
