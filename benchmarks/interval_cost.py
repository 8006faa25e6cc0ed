"""What the prediction interval adds to one machine-cycle, gate off and on side by side.

Per cycle the loop calls :func:`gateway.live.interval.assess` (the training-span check
of the model's sensors and the speed, and the widened half-width) and the uncertainty
gate's :meth:`~gateway.live.uncertainty_gate.UncertaintyGate.aim`; the time-series
point gains three fields. Measured here on the demo's fitted models (nine sensors),
each figure the median of ``--repeats`` runs of ``--cycles`` calls, in µs per cycle:

- ``assess_inside_us`` / ``assess_outside_us``: the span check and the width, inputs
  inside the span / with the speed beyond it;
- ``gate_off_us`` / ``gate_on_us``: ``aim`` with no ``when_uncertain`` section / with one
  that triggers (hold);
- ``cycle_gate_off_us`` / ``cycle_gate_on_us``: both together, as a cycle runs them;
- ``probe_age_us``: with the online correction on, the variance its filter gained since
  the last probe and the width widened by it; ``cycle_gate_off_correction_us`` /
  ``cycle_gate_on_correction_us``: a cycle's whole addition with the correction on;
- ``budget_us`` / ``within_budget``: the largest of the cycle figures against 20 µs;
- ``points_plain_us`` / ``points_with_interval_us``: ``points_from_record`` without and
  with the interval fields.

Prints one JSON document.

    .venv/bin/python benchmarks/interval_cost.py [--cycles 20000] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.config import WhenUncertainSection  # noqa: E402
from gateway.demo.compensate import fit_models, write_training_data  # noqa: E402
from gateway.live.bank.model_bank import BankedModel  # noqa: E402
from gateway.live.interval import assess  # noqa: E402
from gateway.live.record import CycleRecord  # noqa: E402
from gateway.live.uncertainty_gate import UncertaintyGate  # noqa: E402
from gateway.outputs.points import points_from_record  # noqa: E402
from models.fit.interval import with_probe_age  # noqa: E402
from models.online.correction import OnlineCorrection  # noqa: E402
from models.store import ModelStore  # noqa: E402

#: What the interval may add to a machine-cycle, µs.
BUDGET_US = 20.0


def per_call_us(work: Callable[[], object], cycles: int, repeats: int) -> float:
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(cycles):
            work()
        runs.append((time.perf_counter() - start) / cycles * 1e6)
    return statistics.median(runs)


def record(rises: dict[str, float], with_interval: bool) -> CycleRecord:
    rec = CycleRecord(
        machine="m1",
        time_s=100.0,
        temperatures_C={n: 20.0 + v for n, v in rises.items()},
        quality=dict.fromkeys(rises, "good"),
        quality_reasons={},
        speed_rpm=4000.0,
        regime="variable",
        model_id="mlr-error_um-variable",
        predicted_um=5.0,
        target_um=5.0,
        applied_um=5.0,
        written_cnc=0.005,
        write_status="ok",
    )
    if with_interval:
        rec.interval_um, rec.training_span, rec.outside_inputs = 0.5, "outside", ["speed"]
    return rec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="interval-cost-"))
    write_training_data(folder / "training.csv", seed=1)
    fit_models(folder / "training.csv", folder / "models", "bench")
    model, document = ModelStore(folder / "models").load("mlr-error_um-constant")
    banked = BankedModel(document.model_id, model, document)
    rises = {f"T{i}": 3.0 + 0.1 * i for i in range(1, 10)}
    off = UncertaintyGate("m1", None)
    on = UncertaintyGate("m1", WhenUncertainSection(above_um=0.01))
    n, r = args.cycles, args.repeats

    filter_ = OnlineCorrection()
    filter_.update(0.0, 1.0)  # one accepted probe: the correction runs

    def probe_age() -> float:
        return with_probe_age(0.5, filter_.added_variance_um2(120.0, 5.0), 0.9)

    def cycle(gate: UncertaintyGate, correction: bool = False) -> Callable[[], object]:
        def run() -> object:
            state = assess(banked, 5.0, rises, 8000.0, 0)
            width = state.half_width_um
            if correction and width is not None:
                width = with_probe_age(width, filter_.added_variance_um2(120.0, 5.0), 0.9)
            return gate.aim(5.0, width, 4.0)

        return run

    plain, extended = record(rises, False), record(rises, True)
    figures = {
        "model": document.model_id,
        "sensors": len(rises),
        "assess_inside_us": per_call_us(lambda: assess(banked, 5.0, rises, 4000.0, 0), n, r),
        "assess_outside_us": per_call_us(lambda: assess(banked, 5.0, rises, 8000.0, 0), n, r),
        "gate_off_us": per_call_us(lambda: off.aim(5.0, 0.7, 4.0), n, r),
        "gate_on_us": per_call_us(lambda: on.aim(5.0, 0.7, 4.0), n, r),
        "cycle_gate_off_us": per_call_us(cycle(off), n, r),
        "cycle_gate_on_us": per_call_us(cycle(on), n, r),
        "probe_age_us": per_call_us(probe_age, n, r),
        "cycle_gate_off_correction_us": per_call_us(cycle(off, True), n, r),
        "cycle_gate_on_correction_us": per_call_us(cycle(on, True), n, r),
        "points_plain_us": per_call_us(lambda: points_from_record(plain), n, r),
        "points_with_interval_us": per_call_us(lambda: points_from_record(extended), n, r),
        "budget_us": BUDGET_US,
    }
    worst = max(v for k, v in figures.items() if k.startswith("cycle_"))
    figures["within_budget"] = worst <= BUDGET_US
    print(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
