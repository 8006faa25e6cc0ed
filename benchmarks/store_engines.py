"""The local store's engines side by side on one fleet's stream: size, disk writes, CPU, reads.

One run feeds the same ``--machines`` × ``--seconds`` stream (1-s cycles, the sink's
points: one ``spindle_cycle`` point and one ``spindle_temperature`` point per sensor)
to each candidate in turn, in a folder of its own:

* ``json-sqlite``: the earlier layout (JSON text per point in SQLite under three
  indexes, :mod:`tests.json_layout_store`), one transaction per machine-cycle;
* ``typed-parquet``: :class:`gateway.outputs.local_store.LocalStore` as the gateway
  runs it — points queued, committed once a second (SQLite WAL, synchronous FULL)
  by its thread, closed 10-minute periods compacted into Parquet (zstd) parts;
* ``duckdb-file``: one DuckDB database file, the same typed columns, one append of
  the fleet's second per second (DuckDB's WAL, checkpointed by DuckDB). It cannot
  be read by another process while the gateway writes it (DuckDB allows one process
  to open a file that is written), which ``export`` and the console's worker need.

The stream: temperatures, ambient and speed of the simulator's recorded programmes
(``simulator.record``, 5-s steps interpolated to 1-s cycles, each machine starting at
another row) with each machine's own transmitter noise (σ 0.03 °C read to 0.01 °C,
speed σ 2 r/min read to 0.1), and the model outputs a cycle logs (prediction and
target at full double precision, the applied value in 0.1 µm, the macro in 0.1 µm).

Reported per candidate: bytes on disk per stored value and per point (every file,
indexes and WAL included, after the writer closed), bytes the process passed to
``write()`` per byte stored (``wchar`` of /proc/self/io: WAL, checkpoints, parts),
the process CPU per machine-cycle spent in the store (its threads included; the
making of the points is timed apart and left out) and the part of it the caller's
thread spends in ``write`` (the event loop's share in the gateway), and the wall time of the
console's 1-h window of one machine (``machine_view``) and of ``export`` of one
machine (typed-parquet and json-sqlite only: the console reads the store's layout).
Then the projection of ``--project-machines`` machines × one year at 1 s from the
measured bytes per machine-second (for typed-parquet its parts: the SQLite file only
ever holds one open period, a constant), against the default cap (8000 MB).

    .venv/bin/python benchmarks/store_engines.py [--machines 200] [--seconds 1800]
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import duckdb  # noqa: E402
import numpy as np  # noqa: E402

from gateway.config import LoggingSection  # noqa: E402
from gateway.offline.export import export_runs  # noqa: E402
from gateway.outputs.local_store import LocalStore  # noqa: E402
from gateway.outputs.points import Point, points_from_record  # noqa: E402
from gateway.outputs.store_parts import TYPED_SELECT, arrays_of  # noqa: E402
from gateway.outputs.store_rows import row_of  # noqa: E402
from gateway.process.gc_tuning import frozen_startup_heap  # noqa: E402
from gateway.web.series import machine_view  # noqa: E402
from tests.json_layout_store import JsonLocalStore  # noqa: E402
from tests.records import written_record  # noqa: E402

EPOCH_S = 1.7e9
DEFAULT_CAP_BYTES = 8_000_000_000
SECONDS_PER_YEAR = 365 * 86_400
DAY_NS = 86_400 * 10**9


def simulator_rows() -> list[dict[str, float]]:
    """The simulator's recorded programmes (5-s rows), as the ``simulate --record`` CSV."""
    from simulator.params import load_params
    from simulator.programs import program_by_name
    from simulator.record import DEFAULT_PROGRAMS, record

    programs = [program_by_name(name) for name in DEFAULT_PROGRAMS]
    recording = record(load_params(), programs, ("none",), seed=3, sample_s=5.0)
    reader = csv.DictReader(recording.to_csv().splitlines())
    return [{k: float(v) for k, v in row.items() if k not in ("run",) and v} for row in reader]


class Stream:
    """Each machine's cycle points at second ``s`` from the simulator's rows."""

    def __init__(self, machines: int) -> None:
        self.rows = simulator_rows()
        self.machines = machines
        self.sensors = [k for k in self.rows[0] if k.startswith("T") or k == "ambient_C"]
        self.noise = [np.random.default_rng(m) for m in range(machines)]

    def _row(self, s: int, m: int) -> dict[str, float]:
        """Machine ``m`` at second ``s``: its programme row (each machine starts at another),
        interpolated between the 5-s rows, with the machine's own transmitter noise
        (σ 0.03 °C, read to 0.01 °C) and speed jitter (σ 2 r/min, read to 0.1)."""
        k, frac = divmod(s + 4985 * m, 5)
        a = self.rows[k % len(self.rows)]
        b = self.rows[(k + 1) % len(self.rows)]
        rng = self.noise[m]
        row = {c: a[c] + (b[c] - a[c]) * frac / 5 for c in self.sensors}
        row = {c: round(v + rng.normal(0, 0.03), 2) for c, v in row.items()}
        speed = a["speed_rpm"]
        row["speed_rpm"] = round(speed + rng.normal(0, 2.0), 1) if speed else 0.0
        return row

    def second(self, s: int) -> list[list[Point]]:
        batches = []
        for m in range(self.machines):
            row = self._row(s, m)
            temps = {k: row[k] for k in self.sensors}
            predicted = 0.37 * (temps["T1"] - temps["ambient_C"]) + 0.011 * row["speed_rpm"] / 7
            applied = round(predicted, 1)
            record = written_record(
                f"vmc-{m:03d}",
                float(s),
                temps,
                applied,
                speed_rpm=row["speed_rpm"],
                predicted_um=predicted,
                target_um=predicted,
                written_cnc=round(applied / 1000.0, 4),
                correction_um=applied,
                model_id=f"mlr-error_um-{m % 3}",
                write_status="ok: tracking",
                probe_error_um=None,
            )
            batches.append(points_from_record(record, EPOCH_S))
        return batches


def wchar() -> int:
    with open("/proc/self/io") as stream:
        return next(int(line.split()[1]) for line in stream if line.startswith("wchar:"))


def disk_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


class DuckFile:
    """One DuckDB file with the typed columns; the fleet's second appended at once."""

    def __init__(self, path: Path) -> None:
        self.db = duckdb.connect(str(path))
        self.db.execute("SET threads = 1")
        self.db.execute(f"CREATE TABLE points AS SELECT {TYPED_SELECT} FROM batch LIMIT 0")
        self.queue: list = []

    def write(self, points: list[Point]) -> None:
        self.queue.extend(row_of(p) for p in points)

    def commit(self) -> None:
        batch = arrays_of(self.queue)  # noqa: F841  (scanned by name)
        self.db.execute(f"INSERT INTO points SELECT {TYPED_SELECT} FROM batch")
        self.queue = []

    def close(self) -> None:
        self.db.execute("CHECKPOINT")
        self.db.close()


batch = arrays_of([])  # DuckFile's empty template


def run(name: str, folder: Path, stream: Stream, seconds: int) -> dict:
    """Feed ``seconds`` of the stream to candidate ``name``; its measurements."""
    path = folder / "points.sqlite"
    store: object
    if name == "json-sqlite":
        store = JsonLocalStore(path)
    elif name == "typed-parquet":
        # The commit thread's work (flush, compact) is done here once per simulated
        # second, so the run need not last as long as the stream it writes.
        store = LocalStore(path, synchronous="FULL", commit_interval_s=3600.0)
    else:
        store = DuckFile(folder / "points.duckdb")
    points = values = 0
    making = caller = 0.0
    # the gateway runs its cycles with its start-up heap frozen and young passes rarer
    with frozen_startup_heap():
        c0, io0 = time.process_time(), wchar()
        for s in range(seconds):
            m0 = time.thread_time()
            batches = stream.second(s)
            making += time.thread_time() - m0
            w0 = time.thread_time()
            for batch_points in batches:
                store.write(batch_points)  # type: ignore[attr-defined]
                points += len(batch_points)
                values += sum(len(p.fields) for p in batch_points)
            caller += time.thread_time() - w0  # what the sink's thread (the event loop) spends
            if isinstance(store, DuckFile):
                store.commit()
            elif isinstance(store, LocalStore):
                store.flush()
                store.compact()
        if isinstance(store, LocalStore):
            store.compact(stream_ns(seconds + 700))  # the last closed period, as later cycles would
            store.merge_days(stream_ns(seconds) + DAY_NS)  # its day closed: parts merged
        store.close()  # type: ignore[attr-defined]
    cpu = time.process_time() - c0 - making
    parts = history = None
    if isinstance(store, LocalStore):
        parts = disk_bytes(folder / "points.sqlite.parts")
        history = disk_bytes(folder / "points.sqlite.history")
    written = wchar() - io0
    stored = disk_bytes(folder)
    cycles = stream.machines * seconds
    return {
        "candidate": name,
        "points": points,
        "values": values,
        "bytes_on_disk": stored,
        "bytes_per_value": round(stored / values, 2),
        "bytes_per_point": round(stored / points, 2),
        "written_per_stored": round(written / stored, 2),
        "bytes_per_machine_s": round(stored / cycles, 1),
        "parts_bytes_per_value": None if parts is None else round(parts / values, 2),
        "parts_bytes_per_machine_s": None if parts is None else round(parts / cycles, 1),
        "history_bytes_per_machine_s": None if history is None else round(history / cycles, 2),
        "written_per_parts": None if parts is None else round(written / (parts + history), 1),
        "cpu_us_per_machine_cycle": round(1e6 * cpu / cycles, 1),
        "caller_us_per_machine_cycle": round(1e6 * caller / cycles, 1),
    }


def stream_ns(s: int) -> int:
    return round((EPOCH_S + s) * 1e9)


def timed(call: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    call()
    return round(time.perf_counter() - t0, 3)


def reads(name: str, folder: Path, seconds: int) -> dict:
    """Wall s of the console's window of the whole run and of ``export`` of one machine."""
    path = folder / "points.sqlite"
    if name == "typed-parquet":
        spec = ("local", str(path))
        window = timed(lambda: machine_view(spec, "vmc-007", EPOCH_S, EPOCH_S + seconds, 0.001))
    else:
        window = None  # the console reads the typed layout only
    store = LocalStore(path, set_aside_damaged=False) if name == "typed-parquet" else None
    source = store if store is not None else JsonLocalStore(path, set_aside_damaged=False)
    out = folder / "export.csv"
    try:
        export_s = timed(
            lambda: export_runs(source, "vmc-007", None, None, out, epoch_s=EPOCH_S, cycle_s=1.0)
        )
    except ValueError:  # no probe values in this stream: export reads, then says so
        export_s = None
    finally:
        source.close()
    return {"console_window_s": window, "export_read_s": export_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--machines", type=int, default=200)
    parser.add_argument("--seconds", type=int, default=1800)
    parser.add_argument("--project-machines", type=int, default=10)
    parser.add_argument(
        "--raw-retention-days",
        type=float,
        default=LoggingSection().local_store_retention_days,
        help="age of the 1-s points kept in the projection (the minute history: a year)",
    )
    parser.add_argument("--folder", type=Path, default=None)
    parser.add_argument(
        "--candidates", nargs="+", default=["json-sqlite", "typed-parquet", "duckdb-file"]
    )
    args = parser.parse_args()
    stream = Stream(args.machines)
    base = Path(tempfile.mkdtemp(dir=args.folder))
    results = []
    try:
        for name in args.candidates:
            folder = base / name
            folder.mkdir()
            result = run(name, folder, stream, args.seconds)
            if name != "duckdb-file":
                result.update(reads(name, folder, args.seconds))
            # The store's lasting growth: its parts (the open period is a constant), the
            # 1-s parts kept --raw-retention-days and the minute history the whole year.
            per_year = result["bytes_per_machine_s"] * SECONDS_PER_YEAR
            if result["parts_bytes_per_machine_s"] is not None:
                raw_s = min(SECONDS_PER_YEAR, args.raw_retention_days * 86_400)
                per_year = result["parts_bytes_per_machine_s"] * raw_s
                per_year += result["history_bytes_per_machine_s"] * SECONDS_PER_YEAR
            result["projection_bytes"] = round(args.project_machines * per_year)
            result["projection_within_cap"] = result["projection_bytes"] <= DEFAULT_CAP_BYTES
            results.append(result)
            print(json.dumps(result), flush=True)
            shutil.rmtree(folder)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    print(f"{'candidate':14} {'B/value':>8} {'B/point':>8} {'written/stored':>15} {'CPU µs':>8}")
    for r in results:
        print(
            f"{r['candidate']:14} {r['bytes_per_value']:8} {r['bytes_per_point']:8} "
            f"{r['written_per_stored']:15} {r['cpu_us_per_machine_cycle']:8}"
        )
    print(
        f"projection: {args.project_machines} machines × 1 year at 1 s "
        f"(1-s points kept {args.raw_retention_days:g} days, minutes a year), "
        "MB: " + ", ".join(f"{r['candidate']} {r['projection_bytes'] / 1e6:.0f}" for r in results)
    )


if __name__ == "__main__":
    main()
