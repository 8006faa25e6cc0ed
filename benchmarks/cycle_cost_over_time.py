"""Per-cycle CPU of the per-machine checks against the time a machine has run; prints JSON.

A gateway polls every machine every cycle, so any per-cycle computation that
scans a history growing with run time makes the whole gateway slower the
longer it runs. This measures, for 1-s cycles after 10 s, 120 s, 1800 s and
3600 s of run time, the CPU µs per cycle of:

- ``regime``: ``RegimeSelector.update`` (default rules: 1800-s window), speed
  6000 ± 20 r/min;
- ``rate_mlr`` and ``rate_speed_model``: the prediction rate bound (plausibility
  rule 2, ``check_prediction`` + ``accept``) with a plain MLR model, and with the
  PCA-quadratic speed model at a speed that changes every cycle (its kept
  predictions are of no use then: every cycle predicts the horizon again);
- ``quality``: ``QualityMonitor.check`` of a stopped machine's 6 steady sensors
  (default limits: stuck_s 900 s), the stuck check's "others moved" test.

"old" is the plain computation each replaced (``classify`` over the kept
history; every earlier cycle of the horizon predicted again; a scan of each
other sensor's kept values), run in the same process right after "new";
``ratio`` is old / new. CPU time of this process (``time.process_time``), the
best of ``--repeats``; other processes on the machine do not count in it, but
share its caches and cores.

Run: ``.venv/bin/python benchmarks/cycle_cost_over_time.py`` (about a minute).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from gateway.limits import PlausibilityLimits, QualityLimits
from gateway.live.bank.model_bank import BankedModel
from gateway.live.plausibility import RATE_HORIZON_S, Plausibility, _predict
from gateway.live.quality import OTHERS_MOVED_C, QualityMonitor, _SensorState
from models.base import ModelInputs
from models.estimators.registry import make_model
from models.online.regime_rules import RegimeRules, RegimeSelector, classify
from models.store import StoredModel, build_document

HISTORIES_S = (10, 120, 1800, 3600)
SENSORS = ("A", "B", "C", "D", "E", "F")


# --- the plain computations, as they ran before ---------------------------------------


class PlainSelector(RegimeSelector):
    """``classify`` over the kept history every update."""

    def _classify(self, now_s: float) -> str:
        return classify(self._history, now_s, self.rules)


class _Past:
    """One earlier cycle's trusted rises, its row for the model's sensors kept."""

    __slots__ = ("_row", "_sensors", "rises_C", "time_s")

    def __init__(self, time_s: float, rises_C: dict[str, float]) -> None:
        self.time_s, self.rises_C = time_s, rises_C
        self._sensors: tuple[str, ...] | None = None
        self._row: list[float] | None = None

    def row(self, sensors: tuple[str, ...]) -> list[float] | None:
        if sensors != self._sensors:
            rises = self.rises_C
            self._sensors = sensors
            self._row = [rises[s] for s in sensors] if all(s in rises for s in sensors) else None
        return self._row


class PlainPlausibility(Plausibility):
    """Every earlier cycle of the horizon predicted again each cycle."""

    def __init__(self, limits: PlausibilityLimits) -> None:
        super().__init__(None, limits)
        self.kept: deque[_Past] = deque()

    def accept(self, now_s: float, rises_C: Mapping[str, float], speed_rpm=None) -> None:
        self.kept.append(_Past(now_s, {s: v for s, v in rises_C.items() if s not in self.holds}))
        while self.kept and now_s - self.kept[0].time_s > RATE_HORIZON_S:
            self.kept.popleft()
        super().accept(now_s, rises_C, speed_rpm)

    def _fastest_move(self, now_s, banked, sensors, now_x, speed_rpm):
        earlier = [
            (past, row)
            for past in self.kept
            if now_s - past.time_s <= RATE_HORIZON_S and (row := past.row(sensors)) is not None
        ]
        if not earlier:
            return []
        rows = np.array([now_x, *(then for _, then in earlier)])
        predicted = _predict(banked, sensors, rows, speed_rpm)
        spans_s = now_s - np.array([past.time_s for past, _ in earlier])
        moved = predicted[0] - predicted[1:]
        excess = np.abs(moved) - self._allowed_um(spans_s)
        excess[np.isnan(excess)] = -np.inf
        worst = int(np.argmax(excess))
        if not excess[worst] > 0:
            return []
        latest = int(np.flatnonzero(excess > 0)[-1])
        return [
            (float(moved[k]), float(spans_s[k]), earlier[k][0].rises_C)
            for k in dict.fromkeys((latest, worst))
        ]

    def _re_reference(self, *args) -> None:
        self.kept.clear()
        super()._re_reference(*args)


class PlainQualityMonitor(QualityMonitor):
    """The "others moved" test as a scan of each other sensor's kept values."""

    def __init__(self, sensors, limits) -> None:
        super().__init__(sensors, limits)
        self.kept: dict[str, deque[tuple[float, float]]] = {s: deque() for s in sensors}

    def _remember(self, state: _SensorState, now_s: float, value: float) -> None:
        super()._remember(state, now_s, value)
        kept = self.kept[state.last_check.sensor]
        kept.append((now_s, value))
        while kept and kept[0][0] < now_s - self._history_s:
            kept.popleft()

    def _stuck_reason(self, name, state, now_s, value):
        if state.run_start_s is None:
            return None
        held_s = now_s - state.run_start_s
        if state.stuck_run_s == state.run_start_s:
            return f"stuck at {value:.1f} °C for {held_s:.0f} s"
        if held_s < state.limits.stuck_s:
            return None
        for other in self._states:
            values = [v for t, v in self.kept[other] if t >= state.run_start_s]
            moved = max(values) - min(values) if values else 0.0
            if other != name and moved > OTHERS_MOVED_C:
                state.stuck_run_s = state.run_start_s
                return f"stuck at {value:.1f} °C for {held_s:.0f} s"
        return None


# --- the workloads ----------------------------------------------------------------------


def _banked(folder: Path, method: str) -> BankedModel:
    """A model fitted on two heating bodies seen by six sensors, as the bank holds it."""
    rng = np.random.default_rng(3)
    n = 800
    t = np.linspace(0.0, 6 * np.pi, n)
    bodies = np.column_stack([10 * (1 - np.cos(t / 3)), 6 * (1 - np.cos(t / 5))])
    mix = np.linspace([1.0, 0.0], [0.0, 1.0], len(SENSORS))
    rises = bodies @ mix.T + rng.normal(0, 0.05, (n, len(SENSORS)))
    speed = rng.choice([0.0, 2000.0, 4000.0, 8000.0], n)
    error_um = 2 * rises[:, 0] + rises[:, 5] + speed / 2000.0
    inputs = ModelInputs(rise_C=rises, sensors=SENSORS, speed_rpm=speed)
    model = make_model(method, list(SENSORS)).fit(inputs, error_um)
    document = build_document(
        model,
        model_id=method,
        inputs=inputs,
        error_um=error_um,
        target="error_um",
        source_file=str(folder / "training.csv"),
        runs=["R1"],
        reference={"policy": "auto"},
        regime="all",
        validation={"pooled": {"rmse_um": 0.1}},
        software_version="benchmark",
    )
    return BankedModel(method, model, StoredModel.model_validate(document))


def _cpu_us(run: Callable[[int], None], start: int, cycles: int) -> float:
    """CPU µs per cycle of ``run(k)`` for k in [start, start + cycles)."""
    began = time.process_time()
    for k in range(start, start + cycles):
        run(k)
    return (time.process_time() - began) / cycles * 1e6


def regime_us(plain: bool, history_s: int, cycles: int) -> float:
    selector = (PlainSelector if plain else RegimeSelector)(RegimeRules())
    speeds = 6000.0 + np.random.default_rng(1).uniform(-20.0, 20.0, history_s + cycles)

    def run(k: int) -> None:
        selector.update(float(k), float(speeds[k]))

    for k in range(history_s):
        run(k)
    return _cpu_us(run, history_s, cycles)


def rate_us(plain: bool, history_s: int, cycles: int, banked: BankedModel, jitter: float) -> float:
    limits = PlausibilityLimits()
    check = PlainPlausibility(limits) if plain else Plausibility(None, limits)
    rng = np.random.default_rng(2)
    noise = rng.normal(0.0, 0.01, (history_s + cycles, len(SENSORS)))
    speeds = 4000.0 + rng.uniform(-jitter, jitter, history_s + cycles)

    def run(k: int) -> None:
        rises = {s: 5.0 + 0.001 * k + noise[k, i] for i, s in enumerate(SENSORS)}
        check.check_prediction(float(k), banked, rises, float(speeds[k]))
        check.accept(float(k), rises, float(speeds[k]))

    for k in range(history_s):
        run(k)
    return _cpu_us(run, history_s, cycles)


def quality_us(plain: bool, history_s: int, cycles: int) -> float:
    limits = QualityLimits()
    monitor = (PlainQualityMonitor if plain else QualityMonitor)(list(SENSORS), limits)
    readings = {s: (20.0 + 0.5 * i, 0) for i, s in enumerate(SENSORS)}  # a stopped machine

    def run(k: int) -> None:
        monitor.check(float(k), readings)

    for k in range(history_s):
        run(k)
    return _cpu_us(run, history_s, cycles)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=300, help="cycles timed per figure")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        mlr, speed_model = _banked(Path(folder), "mlr"), _banked(Path(folder), "pca-quadratic")
    workloads: dict[str, Callable[[bool, int, int], float]] = {
        "regime": regime_us,
        "rate_mlr": lambda plain, h, n: rate_us(plain, h, n, mlr, 0.0),
        "rate_speed_model": lambda plain, h, n: rate_us(plain, h, n, speed_model, 3.0),
        "quality": quality_us,
    }
    result: dict[str, dict[str, dict[str, float]]] = {}
    for name, workload in workloads.items():
        result[name] = {}
        workload(False, 10, 50), workload(True, 10, 50)  # imports, first allocations
        for history_s in HISTORIES_S:
            figures = {}
            for side in ("new", "old"):
                runs = [
                    workload(side == "old", history_s, args.cycles) for _ in range(args.repeats)
                ]
                figures[f"{side}_us"] = round(min(runs), 1)
            figures["ratio"] = round(figures["old_us"] / figures["new_us"], 2)
            result[name][f"{history_s}s"] = figures
            print(name, history_s, figures, flush=True)
    print(json.dumps({"cpu_us_per_cycle": result, "cycles": args.cycles}, indent=1))


if __name__ == "__main__":
    main()
