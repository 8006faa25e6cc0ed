"""The prediction rate bound with kept earlier predictions answers as the plain scan does.

Rule 2 of :mod:`gateway.live.plausibility` compares this cycle's prediction with
every earlier cycle's of the last RATE_HORIZON_S, predicted again at this cycle's
model and speed. It now keeps those predictions from cycle to cycle
(:mod:`gateway.live.earlier_rows`); ``PlainPlausibility`` below keeps the rises
of every earlier cycle and predicts them all again each cycle, as the rule
always did. Over long random sequences (heating, speed steps and jitter, model
switches between sensor sets and a speed model, untrusted sensors, jumps that
get a sensor held and released, gaps, NaN rises) both give the same Suspect (or
None) every cycle, and the kept path predicts a few rows a cycle where the plain
one predicts the whole horizon.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest

from gateway.limits import PlausibilityLimits
from gateway.live.bank.model_bank import BankedModel
from gateway.live.plausibility import RATE_HORIZON_S, Plausibility, _predict
from models.base import ModelInputs, ThermalModel
from models.estimators.registry import make_model
from tests.test_plausibility import as_banked

SENSORS = ("A", "B", "C", "D", "E")


class PlainPlausibility(Plausibility):
    """Rule 2 as a plain scan: every kept cycle's rises predicted again every cycle."""

    def __init__(self, limits: PlausibilityLimits) -> None:
        super().__init__(None, limits)
        self.kept: deque[tuple[float, dict[str, float]]] = deque()

    def accept(self, now_s: float, rises_C: Mapping[str, float], speed_rpm=None) -> None:
        self.kept.append((now_s, {s: v for s, v in rises_C.items() if s not in self.holds}))
        while self.kept and now_s - self.kept[0][0] > RATE_HORIZON_S:
            self.kept.popleft()
        super().accept(now_s, rises_C, speed_rpm)

    def _fastest_move(self, now_s, banked, sensors, now_x, speed_rpm):
        earlier = [
            (then_s, rises)
            for then_s, rises in self.kept
            if now_s - then_s <= RATE_HORIZON_S and all(s in rises for s in sensors)
        ]
        if not earlier:
            return []
        rows = np.array([now_x, *([rises[s] for s in sensors] for _, rises in earlier)])
        predicted = _predict(banked, sensors, rows, speed_rpm)
        spans_s = now_s - np.array([then_s for then_s, _ in earlier])
        moved = predicted[0] - predicted[1:]
        excess = np.abs(moved) - self._allowed_um(spans_s)
        excess[np.isnan(excess)] = -np.inf
        worst = int(np.argmax(excess))
        if not excess[worst] > 0:
            return []
        past = [k for k in range(len(earlier)) if excess[k] > 0]
        return [
            (float(moved[k]), float(spans_s[k]), earlier[k][1])
            for k in dict.fromkeys((past[-1], worst))
        ]

    def _re_reference(self, *args) -> None:
        self.kept.clear()  # the plain scan forgets its earlier cycles too
        super()._re_reference(*args)


def _training() -> tuple[ModelInputs, np.ndarray]:
    rng = np.random.default_rng(3)
    n = 800
    t = np.linspace(0.0, 6 * np.pi, n)
    bodies = np.column_stack([10 * (1 - np.cos(t / 3)), 6 * (1 - np.cos(t / 5))])
    mix = np.array([[1.0, 0.0], [0.9, 0.1], [0.5, 0.5], [0.1, 0.9], [0.0, 1.0]])
    rises = bodies @ mix.T + rng.normal(0, 0.05, (n, 5))
    speed = rng.choice([0.0, 2000.0, 4000.0, 8000.0], n)
    error_um = 2 * rises[:, 0] + rises[:, 4] - 0.5 * rises[:, 2] + speed / 2000.0
    return ModelInputs(rise_C=rises, sensors=SENSORS, speed_rpm=speed), error_um


def _bank(tmp_path: Path, method: str, sensors: list[str]) -> BankedModel:
    inputs, error_um = _training()
    model = make_model(method, sensors).fit(inputs, error_um)
    return as_banked(model, f"{method}-{''.join(sensors)}", inputs, error_um, tmp_path)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> list[BankedModel]:
    folder = tmp_path_factory.mktemp("models")
    banked = [
        _bank(folder, "mlr", ["A", "E"]),
        _bank(folder, "mlr", ["A", "C", "E"]),
        _bank(folder, "ridge", list(SENSORS)),
        _bank(folder, "pca-quadratic", list(SENSORS)),
    ]
    assert [m.model.uses_speed for m in banked] == [False, False, False, True]
    return banked


class Programme:
    """A random machine: two heating bodies, speed segments, jumps, gaps, lost sensors."""

    def __init__(self, seed: int, models: list[BankedModel]) -> None:
        self.rng = np.random.default_rng(seed)
        self.models = models
        self.now_s, self.p, self.q = 0.0, 0.0, 0.0
        self.speed: float | None = 4000.0
        self.jitter, self.model = 0.0, models[0]
        self.offsets: dict[str, float] = {}

    def step(self) -> tuple[float, BankedModel, dict[str, float], float | None]:
        rng = self.rng
        gap = rng.random() < 0.01
        dt = float(rng.uniform(30.0, 200.0)) if gap else float(rng.choice([1.0, 1.0, 0.5, 2.5]))
        self.now_s += dt
        self.p += dt * float(rng.uniform(0.0, 0.02))
        self.q += dt * float(rng.uniform(-0.005, 0.01))
        if rng.random() < 0.02:
            self.model = self.models[int(rng.integers(len(self.models)))]
        if rng.random() < 0.03:
            self.speed = [None, 0.0, 2000.0, 4000.0, 8000.0][int(rng.integers(5))]
            self.jitter = float(rng.choice([0.0, 0.0, 2.0]))
        if rng.random() < 0.01:  # a knock: one sensor reads high (or back to normal)
            self.offsets[str(rng.choice(SENSORS))] = float(rng.choice([0.0, 2.0, -3.0]))
        mix = {"A": (1.0, 0.0), "B": (0.9, 0.1), "C": (0.5, 0.5), "D": (0.1, 0.9), "E": (0.0, 1.0)}
        rises = {
            s: a * self.p + b * self.q + float(rng.normal(0, 0.02)) + self.offsets.get(s, 0.0)
            for s, (a, b) in mix.items()
            if rng.random() > 0.02  # now and then a sensor is not trusted this cycle
        }
        if rng.random() < 0.003:
            rises[str(rng.choice(SENSORS))] = float("nan")
        speed = self.speed
        if speed is not None and self.jitter:
            speed += float(rng.uniform(-self.jitter, self.jitter))
        return self.now_s, self.model, rises, speed


def _run(seed: int, models: list[BankedModel], cycles: int) -> tuple[int, int]:
    limits = PlausibilityLimits(
        recover_s=60.0, max_prediction_rate_um_per_s=0.04, prediction_noise_um=0.5
    )
    kept, plain = Plausibility(None, limits), PlainPlausibility(limits)
    programme = Programme(seed, models)
    suspects = compared = 0
    for _ in range(cycles):
        now_s, banked, rises, speed = programme.step()
        assert kept.judge(now_s, rises) == plain.judge(now_s, rises)
        got = kept.check_prediction(now_s, banked, rises, speed)
        assert got == plain.check_prediction(now_s, banked, rises, speed), now_s
        assert kept.reasons() == plain.reasons()
        suspects += got is not None
        compared += 1
        kept.accept(now_s, rises, speed)
        plain.accept(now_s, rises, speed)
    return suspects, compared


@pytest.mark.parametrize("seed", range(6))
def test_kept_predictions_give_the_same_suspects_as_the_plain_scan(seed, models):
    suspects, _ = _run(seed, models, 2500)
    assert suspects >= 3  # the blame path ran, not only "nothing moved"


def _rows_predicted_per_cycle(check: Plausibility, banked: BankedModel, speed: float) -> float:
    """Rows the model predicted per cycle over 300 steady 1-s cycles after a full horizon."""
    rows: list[int] = []
    model: ThermalModel = banked.model
    original = model.predict
    model.predict = lambda inputs: (rows.append(inputs.n_samples), original(inputs))[1]
    try:
        rng = np.random.default_rng(0)
        for k in range(int(RATE_HORIZON_S) + 300):
            if k == int(RATE_HORIZON_S):
                rows.clear()
            rises = {s: 5.0 + 0.001 * k + float(rng.normal(0, 0.01)) for s in SENSORS}
            assert check.check_prediction(float(k), banked, rises, speed) is None
            check.accept(float(k), rises, speed)
    finally:
        del model.predict
    return sum(rows) / 300


@pytest.mark.parametrize("index", [0, 3])
def test_a_steady_cycle_predicts_a_few_rows_not_the_horizon(index, models):
    per_cycle = _rows_predicted_per_cycle(
        Plausibility(None, PlausibilityLimits()), models[index], 4000.0
    )
    assert per_cycle <= 2.0, per_cycle  # this cycle's row and the newest earlier one
    plain = _rows_predicted_per_cycle(
        PlainPlausibility(PlausibilityLimits()), models[index], 4000.0
    )
    assert plain > 100.0  # the horizon, predicted again every cycle
