"""What watching for promotions costs a cycle, and what one swap costs.

Every cycle the loop ``stat``s the store's proposals folder and
``versions/current.json`` (:meth:`gateway.live.bank.promotion.Promotions.poll`); that must
be negligible next to a 1 s cycle. A swap reads the version, checks the model
(loads it, bias slopes) and puts it into the bank. The bank here is the demo's
plain models; the promoted model is the augmented one ``analyze`` makes of
simulator data with a hidden thermal lag. Prints JSON.

    .venv/bin/python benchmarks/promotion_poll.py [--polls 20000]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.demo.compensate import fit_models, machine_config, write_training_data  # noqa: E402
from gateway.live.bank.promotion import Promotions  # noqa: E402
from gateway.wiring import load_bank  # noqa: E402
from models.analysis import augmented  # noqa: E402
from models.online.proposals import ProposalStore  # noqa: E402
from simulator.params import load_params  # noqa: E402
from simulator.programs import program_by_name  # noqa: E402
from simulator.record import DEFAULT_PROGRAMS, record, write_recording  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--polls", type=int, default=20000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        write_training_data(folder / "training.csv", seed=1)
        store = folder / "models"
        fit_models(folder / "training.csv", store, "bench")
        data = folder / "hidden.csv"
        programs = [program_by_name(name) for name in DEFAULT_PROGRAMS]
        write_recording(data, record(load_params(), programs, ["thermal_lag"], seed=2))
        analysis = folder / "analysis"
        command = [sys.executable, "-m", "gateway", "analyze", str(data), "--model", "mlr"]
        command += ["--store", str(analysis)]
        subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
        (path,) = (analysis / augmented.FOLDER).glob("*.json")
        document = augmented.load(path)

        link = {"host": "127.0.0.1", "port": 1}
        devices = [
            {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
            {"device_id": 2, "channels": ["T9"]},
        ]
        bus = {"name": "b", "tcp": link, "devices": devices}
        machine = machine_config(store, transmitters=[bus], cnc={"modbus": link}, cycle_s=1.0)
        bank = load_bank(machine)
        promotions = Promotions(machine)
        promotions.load(bank)

        start = time.perf_counter()
        for _ in range(args.polls):
            promotions.poll(bank)
        idle_us = (time.perf_counter() - start) / args.polls * 1e6

        proposals = ProposalStore(store)
        figures = {"before_rmse_um": 1.0, "after_rmse_um": 0.5, "probe_rows": 10}
        kind = {"machine_id": machine.id, "effect": "thermal_lag", "params": {}}
        proposal = proposals.publish(document=document, **kind, **figures)
        proposals.versions.promote(proposal.id)
        start = time.perf_counter()
        outcome = promotions.poll(bank)
        swap_ms = (time.perf_counter() - start) * 1e3
        assert outcome is not None and outcome.changed, outcome
    print(
        json.dumps(
            {"idle_poll_us": round(idle_us, 1), "swap_ms": round(swap_ms, 1), "polls": args.polls},
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
