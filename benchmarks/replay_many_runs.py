"""``replay`` on a 43-run campaign, two probe intervals: this tree against an earlier one.

The recording is :func:`tests.many_runs.write_campaign_csv` (43 runs of 4-8 h every
60 s, seven sensors, seed 0; ``--sensors N`` for more). Both trees run the same
command, ``python -m gateway replay CAMPAIGN --probe-interval-min 30
--probe-interval-min 60`` (default model lag-ridge, declared base), one after the
other in this run, as subprocesses; the earlier tree is ``git archive REV`` of this
repository. Prints one JSON document: wall and CPU seconds of each (CPU of the
command and the worker processes it waited for), their ratio, and whether every
figure of the two JSON results agrees to 1e-9.

    .venv/bin/python benchmarks/replay_many_runs.py --baseline 2c03a86
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.many_runs import write_campaign_csv  # noqa: E402

INTERVALS_MIN = ("30", "60")
LIMIT_S = 120.0


def timed_replay(tree: Path, csv: Path, out: Path) -> dict[str, float]:
    """Wall and CPU seconds of one replay run from ``tree``."""
    command = [sys.executable, "-m", "gateway", "replay", str(csv), "--json", str(out)]
    for interval in INTERVALS_MIN:
        command += ["--probe-interval-min", interval]
    env = os.environ | {"PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, cwd=tree, env=env, check=True, capture_output=True)
    wall_s = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": round(wall_s, 1), "cpu_s": round(cpu_s, 1)}


def differences(a, b, path: str = "") -> list[str]:
    """Where two JSON results differ by more than 1e-9 (elapsed time aside; a field only the
    newer result has is listed by :func:`added`, not here)."""
    if isinstance(a, dict) and isinstance(b, dict):
        keys = (a.keys() & b.keys()) - {"elapsed_s"}
        keys |= a.keys() - b.keys()  # a field the newer result lost is a difference
        return [d for k in sorted(keys) for d in differences(a.get(k), b.get(k), f"{path}/{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        pairs = enumerate(zip(a, b, strict=True))
        return [d for i, (x, y) in pairs for d in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if abs(a - b) <= 1e-9 else [f"{path}: {a} vs {b}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def added(old: dict, new: dict) -> list[str]:
    """Top-level fields of the newer result the older one did not have."""
    return sorted(new.keys() - old.keys())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--baseline", required=True, help="git revision to compare with")
    parser.add_argument("--runs", type=int, default=43)
    parser.add_argument("--sensors", type=int, default=7)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        csv = write_campaign_csv(work / "campaign.csv", n_runs=args.runs, n_sensors=args.sensors)
        baseline = work / "baseline"
        baseline.mkdir()
        archive = subprocess.run(
            ["git", "archive", args.baseline], cwd=ROOT, check=True, capture_output=True
        )
        subprocess.run(["tar", "-x", "-C", str(baseline)], input=archive.stdout, check=True)
        before = timed_replay(baseline, csv, work / "before.json")
        now = timed_replay(ROOT, csv, work / "now.json")
        old = json.loads((work / "before.json").read_text(encoding="utf-8"))
        new = json.loads((work / "now.json").read_text(encoding="utf-8"))
    diffs = differences(old, new)
    print(
        json.dumps(
            {
                "machine": {
                    "cpus": os.cpu_count(),
                    "python": platform.python_version(),
                    "load_1min": round(os.getloadavg()[0], 1),
                },
                "recording": {"runs": args.runs, "sensors": args.sensors},
                "intervals_min": list(INTERVALS_MIN),
                "baseline": {"revision": args.baseline, **before},
                "now": now,
                "wall_ratio": round(before["wall_s"] / now["wall_s"], 2),
                "cpu_ratio": round(before["cpu_s"] / now["cpu_s"], 2),
                "within_limit": now["wall_s"] <= LIMIT_S,
                "figures_equal_to_1e-9": not diffs,
                "differences": diffs[:10],
                "fields_added": added(old, new),
                "forward_rmse_um": (new.get("forward") or {}).get("pooled", {}).get("rmse_um"),
                "online_rmse_um": {
                    f"{row['probe_interval_min']:g} min": round(row["rmse_um"], 3)
                    for row in new["online"]
                },
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
