"""``export`` of a long window: wall time and peak memory against the window's length.

Writes (once, kept in ``--folder``) a local store of ``--days`` days of one machine's
8-hour shifts at 1-s cycles with the store's own writer (:mod:`tests.long_store`: a
cycle point, four sensors, a probe value in two cycles of three), then exports the first
day and every day, each in a fresh process, and reports the rows, the wall time and
the process's peak resident memory (``ru_maxrss``: Python, DuckDB and Parquet reads
together).

    .venv/bin/python benchmarks/export_memory.py [--days 4] [--folder /tmp/export-bench]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.long_store import DAY_S, write_long_store  # noqa: E402

ONE_EXPORT = """
import json, resource, sys, time
sys.path.insert(0, {root!r})
from gateway.offline.export import export_runs
from gateway.outputs.local_store import LocalStore
from tests.long_store import EPOCH_S
with LocalStore({store!r}, set_aside_damaged=False) as store:
    start = time.perf_counter()
    result = export_runs(store, "m1", None, {stop_s!r}, {out!r}, epoch_s=EPOCH_S)
    wall_s = time.perf_counter() - start
peak_MB = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({{"rows": result.rows, "wall_s": wall_s, "peak_rss_MB": peak_MB}}))
"""


def export_in_process(store: Path, days: int, out: Path) -> dict:
    code = ONE_EXPORT.format(root=str(ROOT), store=str(store), stop_s=days * DAY_S * 1.0,
                             out=str(out))  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(done.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=int, default=4)
    parser.add_argument("--folder", type=Path, default=Path("/tmp/export-bench"))
    args = parser.parse_args()
    store = args.folder / f"series-{args.days}d.sqlite"
    if not store.exists():
        args.folder.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        write_long_store(store, args.days, machines=("m1",), cycle_s=1.0)
        print(f"store written in {time.perf_counter() - start:.0f} s")
    for days in (1, args.days):
        figures = export_in_process(store, days, args.folder / f"export-{days}d.csv")
        print(f"{days} day(s): {figures['rows']} rows, {figures['wall_s']:.1f} s, "
              f"peak RSS {figures['peak_rss_MB']:.0f} MB")  # fmt: skip


if __name__ == "__main__":
    main()
