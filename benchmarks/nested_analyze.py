"""`analyze --model auto --nested` on every channel of a measured-run file: the figures
of the README's nested rows, and what they cost.

For each target the CLI runs once (one subprocess, timed): every base model is
analysed on all runs (the kept base's figure is optimistic by that choice), then the
whole procedure, base choice included, is scored by an outer leave-one-run-out.

``--inner-only RUN`` prints, for the one outer fold that holds RUN out, each base's
analysis on the other runs and the base that fold keeps, and never scores RUN:
the check a design may look at before its held-out run.

    .venv/bin/python benchmarks/nested_analyze.py [DATA.csv] [--target ch1_um ...]
    .venv/bin/python benchmarks/nested_analyze.py --inner-only c6
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def nested_run(data: Path, target: str, workdir: Path) -> tuple[dict, float]:
    out = workdir / f"{target}.json"
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "gateway", "analyze", str(data), "--target", target,
         "--model", "auto", "--nested", "--json", str(out), "--no-progress"],
        cwd=ROOT, check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    return json.loads(out.read_text(encoding="utf-8")), time.perf_counter() - start


def inner_only(data: Path, target: str, held_out: str) -> dict:
    import numpy as np

    from models.analysis.nested import AUTO_BASES, analyse_bases
    from models.data.dataset import load_runs
    from models.data.features import prepare

    prepared = prepare(load_runs(data, target=target)).without_sensor_readings()
    train = np.asarray(prepared.data.run) != held_out
    if train.all():
        raise SystemExit(f"{data}: no run {held_out!r}")
    chosen, analyses = analyse_bases(prepared, AUTO_BASES, fit_rows=train)
    return {
        "held_out_never_scored": held_out,
        "inner_rmse_um": {m: round(a.heldout_rmse_um, 3) for m, a in analyses.items()},
        "chosen": chosen,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", type=Path, default=ROOT / "data" / "fl_thermal.csv")
    parser.add_argument("--target", nargs="+", default=["ch1_um", "ch3_um", "ch5_um"])
    parser.add_argument("--inner-only", metavar="RUN", help="one outer fold's inner scores only")
    args = parser.parse_args()
    if args.inner_only:
        for target in args.target:
            print(target, json.dumps(inner_only(args.data, target, args.inner_only)))
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for target in args.target:
            document, seconds = nested_run(args.data, target, Path(tmp))
            nested = document["nested"]
            rows.append(
                {
                    "target": target,
                    "kept_on_all_runs": document["base_choice"]["kept"],
                    "kept_rmse_um_optimistic": round(document["after"]["rmse_um"], 3),
                    "nested_rmse_um": round(nested["heldout"]["rmse_um"], 3),
                    "nested_per_base_um": {
                        m: round(a["rmse_um"], 3) for m, a in nested["heldout_per_model"].items()
                    },
                    "chosen_per_run": {r["run"]: r["chosen_model"] for r in nested["runs"]},
                    "heldout_per_run_um": {
                        r["run"]: round(r["rmse_um"]["chosen"], 3) for r in nested["runs"]
                    },
                    "seconds": round(seconds, 1),
                }
            )
            print(json.dumps(rows[-1]), flush=True)


if __name__ == "__main__":
    main()
