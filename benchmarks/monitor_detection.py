"""How fast the residual monitor proposes a hidden effect, what promotion gains, how often it
alarms without one: the simulated machine's physics in-process (``gateway/demo/monitor_phase.py``).

For each seed: production days with the hidden effect, a probe every 300 s, the demo's
models (fitted on runs without it), the monitor attached with its defaults. Reported:
machine hours to the first proposal, the effect named, and the next day's compensated
RMSE with the proposal promoted against the same day without it. Without a hidden
effect, ``--null-days`` days per seed: alarms (each only starts an analysis) and
proposals.

    .venv/bin/python benchmarks/monitor_detection.py [--seeds 0 1 2 3] [--null-days 10]
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gateway.config import MonitorSection  # noqa: E402
from gateway.demo.compensate import fit_models, write_training_data  # noqa: E402
from gateway.demo.monitor_phase import SENSORS, InProcessPlant, programme_days  # noqa: E402
from gateway.live.proposal_monitor import MonitorSink  # noqa: E402
from models.online.correction import CorrectionParams  # noqa: E402

DAY_S = 86400.0


def monitored(store: Path, effects: tuple[str, ...], seed: int, days: int):
    plant = InProcessPlant(store, programme_days(seed, days), effects, seed=seed)
    section = MonitorSection()
    sink = MonitorSink(
        "vmc",
        SENSORS,
        section.params(),
        CorrectionParams(process_um2_per_h=section.process_um2_per_h),
        cycle_s=plant.cycle_s,
        in_process=True,
    )
    plant.sinks.append(sink)
    return plant, sink


def detection(store: Path, effect: str, seed: int, limit_days: float) -> dict[str, object]:
    plant, sink = monitored(store, (effect,), seed, int(limit_days) + 2)
    took = plant.run_for(limit_days * DAY_S, until=lambda: bool(sink.state.proposals))
    out: dict[str, object] = {"seed": seed, "alarms": len(sink.state.alarms)}
    if not sink.state.proposals:
        return out | {"proposal_h": None}
    proposal = sink.state.proposals[0]
    plant.sinks.clear()
    kept = copy.deepcopy(plant)
    plant.promote(proposal["document"])
    kept.run_for(DAY_S)
    plant.run_for(DAY_S)
    day = int(DAY_S // plant.cycle_s)
    before, after = kept.rmse_um(last=day), plant.rmse_um(last=day)
    return out | {
        "proposal_h": round(took / 3600.0, 2),
        "effects": [(e["effect"], e["params"]) for e in proposal["effects"]],
        "analyses": sink.state.analyses,
        "heldout_before_um": round(proposal["before"]["rmse_um"], 3),
        "heldout_after_um": round(proposal["after"]["rmse_um"], 3),
        "next_day_rmse_without_um": round(before, 3),
        "next_day_rmse_promoted_um": round(after, 3),
        "ratio": round(after / before, 3),
    }


def null_run(store: Path, seed: int, days: float) -> dict[str, object]:
    plant, sink = monitored(store, (), seed, int(days) + 1)
    plant.run_for(days * DAY_S)
    return {
        "seed": seed,
        "days": days,
        "probes": sink.state.probes,
        "alarms": len(sink.state.alarms),
        "analyses": sink.state.analyses,
        "proposals": len(sink.state.proposals),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--effects", nargs="+", default=["drift", "thermal_lag"])
    parser.add_argument("--null-days", type=float, default=10.0)
    parser.add_argument("--limit-days", type=float, default=3.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        write_training_data(folder / "training.csv", seed=1)
        fit_models(folder / "training.csv", folder / "models", "bench")
        store = folder / "models"
        out: dict[str, object] = {
            effect: [detection(store, effect, s, args.limit_days) for s in args.seeds]
            for effect in args.effects
        }
        nulls = [null_run(store, s, args.null_days) for s in args.seeds]
    days = sum(float(n["days"]) for n in nulls)  # type: ignore[arg-type]
    out["none"] = nulls
    out["none_alarms_per_month"] = round(sum(n["alarms"] for n in nulls) / days * 30.0, 2)  # type: ignore[misc]
    out["none_proposals"] = sum(n["proposals"] for n in nulls)  # type: ignore[misc]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
