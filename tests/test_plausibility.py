"""gateway.live.plausibility: sensors judged against each other, the prediction against a
rate bound.

Pure numbers on a manual timeline; the protocol-level scenarios are in
tests/test_plausibility_loop.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gateway.limits import PlausibilityLimits, QualityLimits
from gateway.live.bank.model_bank import BankedModel, ModelBank
from gateway.live.plausibility import Plausibility, relations_from_bank
from gateway.live.quality import Quality, QualityMonitor
from models.base import ModelInputs
from models.estimators.mlr import MlrModel
from models.estimators.sensor_relations import SensorRelations, fit_relations
from models.store import StoredModel, build_document
from tests.test_store import resealed

SENSORS = ("A", "B", "C", "D", "E")
NOISE_C = 0.05
LIMITS = PlausibilityLimits(sigma=5.0, recover_s=300.0)


def training_rises(rows: int = 600) -> np.ndarray:
    """Five sensors on two thermal bodies (p, q), each with its own mix, plus noise."""
    rng = np.random.default_rng(7)
    t = np.linspace(0, 6 * np.pi, rows)
    p = 10 * (1 - np.cos(t / 3)) + 2 * np.sin(t)
    q = 6 * (1 - np.cos(t / 5))
    mix = np.array([[1.0, 0.0], [0.9, 0.1], [0.5, 0.5], [0.1, 0.9], [0.0, 1.0]])
    return np.column_stack([p, q]) @ mix.T + rng.normal(0, NOISE_C, (rows, 5))


@pytest.fixture(scope="module")
def relations() -> SensorRelations:
    return fit_relations(training_rises(), SENSORS, np.repeat([0, 1, 2], 200))


def rises_at(p: float, q: float) -> dict[str, float]:
    """Noise-free rises of the five sensors for body temperatures p, q."""
    mix = {"A": (1.0, 0.0), "B": (0.9, 0.1), "C": (0.5, 0.5), "D": (0.1, 0.9), "E": (0.0, 1.0)}
    return {s: a * p + b * q for s, (a, b) in mix.items()}


def test_consistent_readings_hold_nothing(relations: SensorRelations) -> None:
    check = Plausibility(relations, LIMITS)
    for k in range(50):
        assert check.judge(30.0 * k, rises_at(0.2 * k, 0.1 * k)) == {}
    assert check.flags == 0


def test_an_offset_sensor_is_held_and_only_that_one(relations: SensorRelations) -> None:
    check = Plausibility(relations, LIMITS)
    rises = rises_at(8.0, 4.0)
    rises["C"] += 3.0
    held = check.judge(0.0, rises)
    assert list(held) == ["C"]
    assert held["C"].startswith("implausible: +") and "σ from its neighbours" in held["C"]


def test_a_second_bad_sensor_is_found_while_the_first_is_held(
    relations: SensorRelations,
) -> None:
    check = Plausibility(relations, LIMITS)
    rises = rises_at(8.0, 4.0)
    rises["A"] += 4.0
    assert list(check.judge(0.0, rises)) == ["A"]
    rises["E"] += 4.0  # judged by B, C, D alone now
    assert sorted(check.judge(30.0, rises)) == ["A", "E"]


def test_fewer_than_three_sensors_cannot_blame_one(relations: SensorRelations) -> None:
    check = Plausibility(relations, LIMITS)
    rises = rises_at(8.0, 4.0)
    assert check.judge(0.0, {"A": rises["A"] + 5.0, "E": rises["E"]}) == {}


def test_a_held_sensor_is_trusted_only_after_agreeing_for_recover_s(
    relations: SensorRelations,
) -> None:
    check = Plausibility(relations, LIMITS)
    bad = rises_at(8.0, 4.0) | {"B": rises_at(8.0, 4.0)["B"] + 3.0}
    assert "B" in check.judge(0.0, bad)
    # It agrees again from t = 30 s; one disagreeing cycle at 150 s restarts the clock.
    timeline = {t: rises_at(8.0, 4.0) for t in range(30, 800, 30)}
    timeline[150] = bad
    held_at = {t: "B" in check.judge(float(t), r) for t, r in timeline.items()}
    assert all(held_at[t] for t in range(30, 480, 30))  # 180 s + 300 s of agreement
    assert not held_at[480]
    assert check.flags == 1


def test_without_relations_the_check_is_unavailable() -> None:
    check = Plausibility(None, LIMITS)
    assert not check.available
    rises = rises_at(8.0, 4.0) | {"C": 40.0}
    assert check.judge(0.0, rises) == {}


def as_banked(
    model: Any,
    model_id: str,
    inputs: ModelInputs,
    error_um: np.ndarray,
    folder: Path,
    sensor_relations: dict | None = None,
) -> BankedModel:
    """A fitted model as the bank holds it: its stored document beside it."""
    document = build_document(
        model,
        model_id=model_id,
        inputs=inputs,
        error_um=error_um,
        target="error_um",
        source_file=str(folder / "training.csv"),
        runs=["R1"],
        reference={"policy": "auto"},
        regime="all",
        validation={"pooled": {"rmse_um": 0.1}},
        software_version="test",
        sensor_relations=sensor_relations,
    )
    return BankedModel(model_id, model, StoredModel.model_validate(document))


def stored_mlr(tmp_path: Path, relations_document: dict | None) -> BankedModel:
    """An MLR model e = 2 A + 1 E as the bank holds it (with or without relations)."""
    x = training_rises()
    inputs = ModelInputs(rise_C=x, sensors=SENSORS, speed_rpm=np.zeros(x.shape[0]))
    error_um = 2 * x[:, 0] + x[:, 4]
    model = MlrModel(["A", "E"]).fit(inputs, error_um)
    return as_banked(model, "mlr-error_um-all", inputs, error_um, tmp_path, relations_document)


def test_the_prediction_rate_bound_blames_the_sensor_that_jumped(tmp_path: Path) -> None:
    banked = stored_mlr(tmp_path, None)
    check = Plausibility(None, PlausibilityLimits(max_prediction_rate_um_per_s=0.1))
    for k in range(4):  # heating at 0.01 °C/s: 0.03 µm/s, well within the bound
        now = 30.0 * k
        step = rises_at(8.0 + 0.3 * k, 4.0 + 0.3 * k)
        assert check.check_prediction(now, banked, step, 3000.0) is None
        check.accept(now, step)
    # A jumps 3 °C while both bodies warm 0.3 °C: e = 2 A + E moves 2 · 3.3 + 0.3 = 6.9 µm
    # in 30 s; the bound is 0.1 · 30 + 1 = 4 µm.
    jumped = rises_at(9.2, 5.2) | {"A": rises_at(9.2, 5.2)["A"] + 3.0}
    suspect = check.check_prediction(120.0, banked, jumped, 3000.0)
    assert suspect is not None and suspect.sensor == "A"
    assert "implausible: moved the prediction +6.9 µm in 30 s (bound 4.0 µm" in suspect.reason
    assert check.reasons() == {"A": suspect.reason}
    # Without relations it is trusted again after recover_s of good checks.
    check.judge(150.0, jumped)
    check.judge(150.0 + 899.0, jumped)
    assert "A" in check.reasons()
    check.judge(150.0 + 900.0, jumped)
    assert check.reasons() == {}


def test_a_slow_rise_across_a_gap_is_within_the_bound(tmp_path: Path) -> None:
    banked = stored_mlr(tmp_path, None)
    check = Plausibility(None, PlausibilityLimits())
    check.accept(0.0, rises_at(8.0, 4.0))
    # 100 s later the prediction moved 2 × 1.5 + 1 × 1.5 = 4.5 µm, allowed 0.1 · 100 + 1 = 11.
    assert check.check_prediction(100.0, banked, rises_at(9.5, 5.5), 0.0) is None


def test_the_bank_offers_the_relation_of_its_models(tmp_path: Path, relations) -> None:
    with_relations = stored_mlr(tmp_path, relations.as_document())
    without = stored_mlr(tmp_path, None)
    found = relations_from_bank(ModelBank([with_relations]), SENSORS)
    assert found is not None and found.sensors == SENSORS
    assert relations_from_bank(ModelBank([without]), SENSORS) is None
    assert relations_from_bank(ModelBank([with_relations]), ["A", "B"]) is None  # < 3 covered


def test_quality_monitor_holds_an_implausible_sensor(relations: SensorRelations) -> None:
    check = Plausibility(relations, LIMITS)
    monitor = QualityMonitor(list(SENSORS), QualityLimits(recover_cycles=0), check)
    reference = dict.fromkeys(SENSORS, 20.0)
    values = {s: 20.0 + r for s, r in rises_at(8.0, 4.0).items()}
    checks = monitor.check(0.0, {s: (v, 0) for s, v in values.items()}, reference)
    assert all(c.quality is Quality.GOOD for c in checks.values())
    values["D"] += 3.0
    readings = {s: (v, 0) for s, v in values.items()}
    readings["A"] = (float("nan"), 1)  # an open circuit keeps its own, more specific reason
    checks = monitor.check(30.0, readings, reference)
    assert checks["D"].quality is Quality.BAD and checks["D"].reason.startswith("implausible")
    assert checks["A"].reason == "transmitter fault code 1 (open circuit)"
    assert {s for s, c in checks.items() if c.quality is Quality.GOOD} == {"B", "C", "E"}


def test_an_old_model_file_without_relations_still_loads(tmp_path: Path) -> None:
    from models.store import ModelStore, StoreError, load_file

    banked = stored_mlr(tmp_path, fit_relations(training_rises(), SENSORS).as_document())
    document = json.loads(banked.document.model_dump_json(exclude_none=True))
    path = ModelStore(tmp_path).save(document)
    assert load_file(path)[1].relations() is not None
    old = resealed({k: v for k, v in document.items() if k != "sensor_relations"}, tmp_path)
    path.write_text(json.dumps(old), encoding="utf-8")
    assert load_file(path)[1].relations() is None
    damaged = dict(document)
    damaged["sensor_relations"] = {"sensors": ["A"]}
    path.write_text(json.dumps(resealed(damaged, tmp_path)), encoding="utf-8")
    with pytest.raises(StoreError, match="field 'sensor_relations': sensor_relations: missing"):
        load_file(path)


CONFIG = """\
machines:
  - id: vmc-1
    transmitters:
      - name: bus1
        tcp: {host: 127.0.0.1, port: 5020}
        devices:
          - {device_id: 1, channels: [T1, T2, T3]}
    cnc:
      modbus: {host: 127.0.0.1, port: 5021}
    models: {store: models}
    plausibility:
      plausibility_sigma: SIGMA
      max_prediction_rate_um_per_s: 0.2
"""


def test_config_keys_reach_the_limits(tmp_path: Path) -> None:
    from gateway.config import load_config

    path = tmp_path / "config.yaml"
    path.write_text(CONFIG.replace("SIGMA", "6"), encoding="utf-8")
    limits = load_config(path).machines[0].plausibility.limits()
    assert limits == PlausibilityLimits(sigma=6.0, max_prediction_rate_um_per_s=0.2)


@pytest.mark.parametrize("value", ["0", "-1", ".inf", "x"])
def test_a_bad_threshold_is_refused_with_its_line(tmp_path: Path, value: str) -> None:
    from gateway.config import ConfigError, load_config

    path = tmp_path / "config.yaml"
    path.write_text(CONFIG.replace("SIGMA", value), encoding="utf-8")
    with pytest.raises(
        ConfigError, match=r"config.yaml:12: machines\[0\].plausibility.plausibility_sigma"
    ):
        load_config(path)


def test_a_reference_taken_with_the_spindle_turning_judges_the_rises_since_it(
    relations: SensorRelations,
) -> None:
    check = Plausibility(relations, LIMITS)
    check.accept(0.0, {}, 8000.0)  # the gateway's first cycle: spindle turning, no rises yet
    check.accept(30.0, dict.fromkeys(SENSORS, 0.0), 8000.0)  # the reference just taken
    assert check.armed and check.warm and check.available
    # The machine was at (8, 4) when the reference was taken: rises count from there.
    warm = rises_at(8.0, 4.0)
    since = {s: v - warm[s] for s, v in rises_at(11.0, 6.0).items()}
    assert check.judge(60.0, since) == {}
    since["C"] += 3.0
    assert list(check.judge(90.0, since)) == ["C"]


def test_a_reference_marked_warm_stays_warm_after_a_restart(relations: SensorRelations) -> None:
    check = Plausibility(relations, LIMITS)
    check.reference_turning = True  # the saved file's mark; the rises are no longer near 0
    warm = rises_at(8.0, 4.0)
    since = {s: v - warm[s] for s, v in rises_at(14.0, 7.0).items()}
    check.accept(0.0, since, 0.0)
    assert check.warm
    assert check.judge(30.0, since) == {}


def test_a_reference_taken_at_rest_or_kept_from_before_arms_rule_1(
    relations: SensorRelations,
) -> None:
    at_rest = Plausibility(relations, LIMITS)
    at_rest.accept(0.0, {}, 0.0)
    at_rest.accept(30.0, dict.fromkeys(SENSORS, 0.0), 6000.0)
    kept = Plausibility(relations, LIMITS)
    kept.accept(0.0, {}, 8000.0)
    kept.accept(30.0, rises_at(8.0, 4.0), 8000.0)  # a cold reference from an earlier start
    assert at_rest.armed and kept.armed


def fitted_mlr(tmp_path: Path, sensors: list[str], error_um: np.ndarray, model_id: str):
    x = training_rises()
    inputs = ModelInputs(rise_C=x, sensors=SENSORS, speed_rpm=np.zeros(x.shape[0]))
    model = MlrModel(sensors).fit(inputs, error_um)
    return as_banked(model, model_id, inputs, error_um, tmp_path)


def heating(k: int, rng: np.random.Generator) -> dict[str, float]:
    """Rises at second k of a slow warm-up (0.002 °C/s), read to 0.1 °C with noise."""
    rises = rises_at(8.0 + 0.002 * k, 4.0 + 0.001 * k)
    return {s: round(v + float(rng.normal(0, 0.03)), 1) for s, v in rises.items()}


def test_a_switch_to_the_model_without_a_sensor_is_never_a_step(tmp_path: Path) -> None:
    """Every 20 cycles of 1 s the model switches between e = 2 A + E and its fallback
    without A (a different intercept and coefficients: several µm apart)."""
    x = training_rises()
    error = 2 * x[:, 0] + x[:, 4]
    full = fitted_mlr(tmp_path, ["A", "E"], error, "full")
    fallback = fitted_mlr(tmp_path, ["B", "C", "E"], error + 4.0, "without-A")
    check = Plausibility(None, PlausibilityLimits())
    rng = np.random.default_rng(1)
    for k in range(300):
        banked = full if (k // 20) % 2 == 0 else fallback
        rises = heating(k, rng)
        assert check.check_prediction(float(k), banked, rises, 0.0) is None, k
        check.accept(float(k), rises)
    assert check.flags == 0


def test_one_register_step_through_large_coefficients_holds_nobody(
    tmp_path: Path, relations: SensorRelations
) -> None:
    """e = 12 C − 10 B: a 0.1 °C step on C moves it 1.2 µm in 1 s, past the 1.1 µm bound;
    C itself did nothing a transmitter's last digit does not do."""
    x = training_rises()
    banked = fitted_mlr(tmp_path, ["B", "C"], 12 * x[:, 2] - 10 * x[:, 1], "large")
    for judged_by in (None, relations):
        check = Plausibility(judged_by, PlausibilityLimits())
        rises = rises_at(8.0, 4.0)
        check.accept(0.0, rises)
        stepped = rises | {"C": rises["C"] + 0.1}
        assert check.check_prediction(1.0, banked, stepped, 0.0) is None
        assert check.holds == {} and check.re_references == 1
        check.accept(1.0, stepped)
        assert check.check_prediction(2.0, banked, stepped, 0.0) is None  # counts from there


def test_a_step_every_sensor_shares_re_references_and_one_of_its_own_is_held(
    tmp_path: Path, relations: SensorRelations
) -> None:
    banked = stored_mlr(tmp_path, None)  # e = 2 A + E
    # A restart whose machine comes back cooler (-16 µm in 16 s), and a re-zero that
    # takes 2 °C off every transmitter.
    cooler = rises_at(2.0, 1.0)
    re_zeroed = {s: v - 2.0 for s, v in rises_at(8.0, 4.0).items()}
    for judged_by in (None, relations):
        for after in (cooler, re_zeroed):
            check = Plausibility(judged_by, PlausibilityLimits())
            check.accept(0.0, rises_at(8.0, 4.0))
            assert check.check_prediction(16.0, banked, after, 0.0) is None
            assert check.holds == {} and check.re_references == 1
            check.accept(16.0, after)
            # From the new level, one sensor's own jump is still caught.
            jumped = after | {"A": after["A"] + 3.0}
            suspect = check.check_prediction(17.0, banked, jumped, 0.0)
            assert suspect is not None and suspect.sensor == "A", judged_by


def test_a_sensor_held_for_a_step_its_neighbours_then_share_is_trusted_again(
    tmp_path: Path, relations: SensorRelations
) -> None:
    """A stepped first (held by the rate bound); a cycle later the others follow: without
    relations every sensor 3 °C up (the transmitters re-zeroed one after the other), with
    them the body A sits on 3 °C warmer. A's step was theirs too."""
    banked = stored_mlr(tmp_path, None)
    start = rises_at(8.0, 4.0)
    uniform = {s: v + 3.0 for s, v in start.items()}
    for judged_by, followed in ((None, uniform), (relations, rises_at(11.0, 4.0))):
        check = Plausibility(judged_by, PlausibilityLimits())
        check.accept(0.0, start)
        first = start | {"A": followed["A"]}
        suspect = check.check_prediction(1.0, banked, first, 0.0)
        assert suspect is not None and suspect.sensor == "A"
        check.accept(1.0, first)
        check.judge(2.0, followed)
        assert check.holds == {}, (judged_by, check.reasons())
        # A spike that went away is not a shared step: it waits for recover_s.
        check.judge(3.0, followed)
        check.accept(3.0, followed)
        spiked = followed | {"A": followed["A"] + 3.0}
        assert check.check_prediction(4.0, banked, spiked, 0.0) is not None
        check.judge(5.0, followed)
        assert "A" in check.holds, judged_by
