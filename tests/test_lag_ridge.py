"""``lag-ridge``: the closed-form ridge, its nested penalties, its JSON, its streaming form.

Synthetic runs (each its own cold recording, time from 0) whose error follows a
lag of one sensor and the speed: the pure maths is checked against scikit-learn
and by hand; the real ``fl_thermal.csv`` gives the held-out figure.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gateway.live.bank.lag_state import EffectStates
from gateway.live.bank.model_bank import BankedAugmented, ModelBank
from gateway.wiring import load_bank
from models.base import ModelInputs
from models.data.dataset import load_runs
from models.data.features import Prepared, prepare
from models.data.lag_terms import first_order_lag
from models.estimators.lag_ridge import (
    GroupGrams,
    LagRidgeModel,
    candidate_paths,
    lag_terms,
    ridge_path,
    term_groups,
    term_names,
)
from models.estimators.lag_structures import (
    DEFAULT_SPEED_POWERS,
    ELASTIC_NET,
    MINIMUM,
    ONE_STANDARD_ERROR,
    STRUCTURE_NAMES,
    TWO_GROUP_RIDGE,
    Structure,
    structure_named,
)
from models.fit.workflow import fit_and_store
from models.store import ModelStore, load_file
from tests.cli import ROOT, gateway_in_process
from tests.streaming import streamed
from tests.test_conditioning import machine

FL_THERMAL = ROOT / "data" / "fl_thermal.csv"
TAUS_S = (600.0, 3600.0)
POWERS = (1.0, 2.0)


def synthetic_csv(path: Path, runs: int = 4, seed: int = 3) -> Path:
    """Runs at rest 10 min, then speed steps; T1 follows the heat fast, T2 slowly, and the
    error follows T1, a 1 h lag of T2 and n² (plus 0.1 µm probe noise)."""
    rng = np.random.default_rng(seed)
    lines = ["run,time_s,speed_rpm,T1,T2,T3,error_um"]
    for r in range(runs):
        time_s = np.arange(0, 8 * 3600, 60.0)
        levels = rng.choice([1500.0, 3000.0, 4500.0, 6000.0], size=4)
        speed = np.where(time_s < 600, 0.0, levels[np.minimum((time_s // 7200).astype(int), 3)])
        heat = (speed / 1000.0) ** 2
        rec = np.zeros(time_s.size, dtype=int)
        t1 = 20 + 0.6 * first_order_lag(heat, time_s, rec, 900.0)
        t2 = 20 + 0.3 * first_order_lag(heat, time_s, rec, 5400.0)
        t3 = 20 + 0.05 * rng.normal(size=time_s.size).cumsum() / 10
        slow = first_order_lag(t2 - 20, time_s, rec, 3600.0)
        error = 2.0 * (t1 - 20) + 4.0 * slow + 0.3 * heat + rng.normal(0, 0.1, time_s.size)
        for k in range(time_s.size):
            lines.append(
                f"R{r},{time_s[k]:.0f},{speed[k]:.0f},{t1[k]:.4f},{t2[k]:.4f},{t3[k]:.4f},"
                f"{error[k]:.4f}"
            )
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Prepared:
    return prepare(load_runs(synthetic_csv(tmp_path_factory.mktemp("lag") / "runs.csv")))


def small_model() -> LagRidgeModel:
    return LagRidgeModel(lag_taus_s=TAUS_S, speed_powers=POWERS)


def test_the_closed_form_path_is_ridge_on_standardised_terms(synthetic: Prepared) -> None:
    from sklearn.linear_model import Ridge

    sensors = synthetic.inputs.sensors
    terms = lag_terms(synthetic.inputs, sensors, TAUS_S, POWERS)
    groups = term_groups(len(sensors), len(TAUS_S), len(POWERS))
    grams = GroupGrams(terms, synthetic.error_um, np.zeros(terms.shape[0], dtype=int))
    gram, cross = grams.total([0])
    penalty, ratio = 1e-3, 10.0
    (beta,) = ridge_path(gram, cross, groups, ratio, (penalty,))
    # The same problem by hand: standardise, scale the speed group by 1/√ratio, sklearn Ridge.
    mean, scale = terms.mean(axis=0), terms.std(axis=0)
    weight = np.where(groups == 1, 1 / np.sqrt(ratio), 1.0)
    n = terms.shape[0]
    reference = Ridge(alpha=penalty * n).fit((terms - mean) / scale * weight, synthetic.error_um)
    coef = reference.coef_ * weight / scale
    assert beta[1:] == pytest.approx(coef, rel=1e-6, abs=1e-9)
    assert beta[0] == pytest.approx(
        reference.intercept_ - (mean / scale * weight) @ reference.coef_
    )


def test_without_standardising_the_penalty_is_on_the_terms_in_their_own_units(
    synthetic: Prepared,
) -> None:
    from sklearn.linear_model import Ridge

    sensors = synthetic.inputs.sensors
    terms = lag_terms(synthetic.inputs, sensors, TAUS_S, POWERS)
    groups = term_groups(len(sensors), len(TAUS_S), len(POWERS))
    grams = GroupGrams(terms, synthetic.error_um, np.zeros(terms.shape[0], dtype=int))
    gram, cross = grams.total([0])
    penalty = 1e-2
    (raw,) = ridge_path(gram, cross, groups, 1.0, (penalty,), standardise=False)
    (scaled,) = ridge_path(gram, cross, groups, 1.0, (penalty,))
    reference = Ridge(alpha=penalty * terms.shape[0]).fit(terms, synthetic.error_um)
    assert raw[1:] == pytest.approx(reference.coef_, rel=1e-6, abs=1e-9)
    assert raw[0] == pytest.approx(reference.intercept_)
    assert np.max(np.abs(raw[1:] - scaled[1:])) > 1e-3  # the two penalties differ


def test_held_out_error_follows_the_lag_and_the_penalties_ignore_the_held_out_run(
    synthetic: Prepared,
) -> None:
    runs = synthetic.data.run
    held = runs == "R3"
    model = small_model().fit_rows(synthetic.inputs, synthetic.error_um, ~held)
    changed = synthetic.error_um.copy()
    changed[held] += 50.0 * np.sin(np.arange(held.sum()))  # the held-out target only
    other = small_model().fit_rows(synthetic.inputs, changed, ~held)
    assert other.penalties_ == model.penalties_
    assert (
        other.stack_weights_ == model.stack_weights_
        and other.inner_rmse_um_ == model.inner_rmse_um_
    )
    assert np.array_equal(other.coef_, model.coef_)
    residual = synthetic.error_um[held] - model.predict_rows(synthetic.inputs, held)
    # The error spans about 30 µm; the lags and n² carry it to the probe's noise and a little.
    assert np.sqrt(np.mean(residual**2)) < 0.5
    assert np.ptp(synthetic.error_um[held]) > 20


def test_the_stack_is_the_weighted_sum_of_its_structures_fitted_alone(synthetic: Prepared) -> None:
    train = synthetic.data.run != "R3"
    stack = LagRidgeModel().fit_rows(synthetic.inputs, synthetic.error_um, train)
    weights = stack.stack_weights_
    assert set(weights) == set(STRUCTURE_NAMES) and sum(weights.values()) == pytest.approx(1.0)
    by_hand = sum(
        w
        * LagRidgeModel(structures=[name])
        .fit_rows(synthetic.inputs, synthetic.error_um, train)
        .predict(synthetic.inputs)
        for name, w in weights.items()
        if w > 0
    )
    assert np.max(np.abs(stack.predict(synthetic.inputs) - by_hand)) < 1e-9
    # On these runs the weights split, so the sum above maps the lassos' 30 min lags into the
    # terms of the largest structure with a weight (a ridge's).
    assert sum(w > 0 for w in weights.values()) >= 2
    largest = max(
        (structure_named(name) for name, w in weights.items() if w > 0),
        key=lambda s: len(s.lag_taus_s) * 10 + len(s.speed_powers),
    )
    own = term_names(synthetic.inputs.sensors, largest.lag_taus_s, largest.speed_powers)
    assert stack.structure_.estimator == "stack" and stack.coef_.size == len(own)
    assert stack.lag_taus_s == list(largest.lag_taus_s)


def test_the_one_standard_error_rule_takes_the_most_penalised_point_within_one_se(
    synthetic: Prepared,
) -> None:
    plain = Structure("plain", TAUS_S, POWERS, TWO_GROUP_RIDGE)
    smooth = Structure("smooth", TAUS_S, POWERS, TWO_GROUP_RIDGE, "fitted", ONE_STANDARD_ERROR)
    labels = synthetic.data.run_index
    paths = candidate_paths(
        synthetic.inputs, synthetic.inputs.sensors, [plain, smooth], synthetic.error_um, labels
    )
    members = paths[0].members
    assert len(members) == 4
    # By hand: each run's squared error at each grid point, fitted on the other three.
    sse = np.array(
        [
            [paths[0].grams.sse(held, beta) for beta in paths[0].path(members - {held})]
            for held in sorted(members)
        ]
    )
    total = sse.sum(axis=0)
    lowest = int(np.argmin(total))
    limit = total[lowest] + 2.0 * sse[:, lowest].std(ddof=1)  # √4 × the spread over the runs
    within = [k for k in range(total.size) if total[k] <= limit]
    grid = paths[1].grid
    expected = max(within, key=lambda k: (grid[k]["sensors"], grid[k]["speed"]))
    assert paths[0].choose(members) == lowest
    assert paths[1].choose(members) == expected
    assert expected != lowest  # the rule moves the choice on these runs
    assert grid[expected]["sensors"] >= grid[lowest]["sensors"]
    # Below three runs there is no spread to take: the lowest point.
    two = frozenset(sorted(members)[:2])
    assert paths[1].choose(two) == paths[0].choose(two)


def test_the_penalty_choice_is_stored_with_the_structure_and_older_ones_load() -> None:
    smooth = Structure("s", TAUS_S, POWERS, TWO_GROUP_RIDGE, "fitted", ONE_STANDARD_ERROR)
    assert Structure.from_dict(json.loads(json.dumps(smooth.as_dict()))) == smooth
    older = {k: v for k, v in smooth.as_dict().items() if k != "penalty_choice"}
    assert Structure.from_dict(older).penalty_choice == MINIMUM
    with pytest.raises(ValueError, match="unknown penalty choice"):
        Structure.from_dict(smooth.as_dict() | {"penalty_choice": "smallest"})


def test_a_model_stored_before_the_structure_choice_still_loads(synthetic: Prepared) -> None:
    model = small_model().fit(synthetic.inputs, synthetic.error_um)
    assert model.inner_rmse_um_ == {} and model.structure_.estimator == "two-group ridge"
    old = {
        k: v for k, v in model.fitted_params().items() if k not in ("structure", "structure_choice")
    }
    hyperparams = {"sensors": None, "lag_taus_s": list(TAUS_S), "speed_powers": list(POWERS)}
    loaded = LagRidgeModel.from_params(hyperparams, json.loads(json.dumps(old)))
    assert loaded.lag_taus_s == list(TAUS_S) and loaded.uses_speed
    assert np.array_equal(loaded.predict(synthetic.inputs), model.predict(synthetic.inputs))


def test_a_lasso_structure_needs_no_speed_and_streams_its_lags(synthetic: Prepared) -> None:
    model = LagRidgeModel(structures=["lasso-30min"]).fit(synthetic.inputs, synthetic.error_um)
    assert not model.uses_speed and model.lag_taus_s == [1800.0]
    assert model.penalties_.keys() == {"l1_over_target_sigma"}
    assert 0 < np.count_nonzero(model.coef_) < model.coef_.size  # the L1 penalty zeroes terms
    stored = json.loads(json.dumps(model.fitted_params()))
    loaded = LagRidgeModel.from_params(model.hyperparams(), stored)
    part = synthetic.take(synthetic.data.run == "R2")
    batch = loaded.predict(part.inputs)
    stream = loaded.stream()
    assert np.max(np.abs(streamed(stream, part, speed=False) - batch)) < 1e-9
    lags = {"T1@lag1800s", "T2@lag1800s", "T3@lag1800s"}
    assert set(stream.export_state()) == {"time_s", *lags, "T1@input", "T2@input", "T3@input"}


def test_the_zero_intercept_lasso_passes_through_0_um_and_streams_its_speed_lags(
    synthetic: Prepared,
) -> None:
    model = LagRidgeModel(structures=["lasso-30min-zero"]).fit(synthetic.inputs, synthetic.error_um)
    assert model.intercept_um_ == 0.0 and model.uses_speed and model.lag_taus_s == [1800.0]
    at_rest = ModelInputs(np.zeros((1, 3)), synthetic.inputs.sensors, np.zeros(1))
    assert model.predict(at_rest)[0] == 0.0  # the cold machine at rest: every term is 0
    stored = json.loads(json.dumps(model.fitted_params()))
    assert stored["structure"]["intercept"] == "zero"
    loaded = LagRidgeModel.from_params(model.hyperparams(), stored)
    part = synthetic.take(synthetic.data.run == "R1")
    batch = loaded.predict(part.inputs)
    stream = loaded.stream()
    assert np.max(np.abs(streamed(stream, part) - batch)) < 1e-9
    # A structure stored before the intercept was part of it loads as a fitted intercept.
    older = {k: v for k, v in stored["structure"].items() if k != "intercept"}
    assert Structure.from_dict(older).intercept == "fitted"


def with_a_twin_of_t1(prepared: Prepared, seed: int = 5) -> ModelInputs:
    """The inputs with a fourth sensor T4 that reads T1 plus 0.01 °C of noise: two sensors
    on one housing, rising together."""
    x = prepared.inputs
    twin = x.rise_C[:, 0] + np.random.default_rng(seed).normal(0, 0.01, x.rise_C.shape[0])
    return ModelInputs(
        np.column_stack([x.rise_C, twin]),
        (*x.sensors, "T4"),
        x.speed_rpm,
        x.run_index,
        x.time_s,
        x.recording,
    )


def test_the_elastic_net_shares_weight_across_sensors_that_rise_together(
    synthetic: Prepared,
) -> None:
    """``ELASTIC_NET`` (no shipped structure uses it; ``benchmarks/lag_ridge_design.py``
    does) against the lasso, on the zero-intercept lasso's terms."""
    lasso = structure_named("lasso-30min-zero")
    enet = Structure("enet-30min-zero", (1800.0,), DEFAULT_SPEED_POWERS, ELASTIC_NET, "zero")
    assert Structure.from_dict(json.loads(json.dumps(enet.as_dict()))) == enet
    inputs, y = with_a_twin_of_t1(synthetic), synthetic.error_um
    one_group = np.zeros(y.size, dtype=int)
    twins = []
    for structure in (lasso, enet):
        (paths,) = candidate_paths(inputs, inputs.sensors, [structure], y, one_group)
        t1, t4 = paths.names.index("T1") + 1, paths.names.index("T4") + 1
        twins.append(np.array([(b[t1], b[t4]) for b in paths.path(paths.members)]))
    by_lasso, by_enet = twins
    # Along its penalty grid the lasso puts the twins' weight on one of them, and which one
    # carries it changes from one penalty to the next.
    alone = (np.abs(by_lasso).max(axis=1) > 0.5) & (np.abs(by_lasso).min(axis=1) < 0.05)
    assert alone.sum() >= 3
    assert set(np.argmax(np.abs(by_lasso[alone]), axis=1)) == {0, 1}
    # The elastic net shares it at every penalty: one sign, within 20 % of each other.
    assert np.all(by_enet[:, 0] * by_enet[:, 1] > 0)
    assert np.all(np.abs(by_enet).min(axis=1) >= 0.8 * np.abs(by_enet).max(axis=1))


def test_its_stream_crosses_a_logging_gap_as_the_batch_does_also_through_a_restart(
    synthetic: Prepared,
) -> None:
    model = small_model().fit(synthetic.inputs, synthetic.error_um)
    data = synthetic.data
    # R1 loses 30 min of rows around its 2 h speed change: a gap the lags must cross.
    keep = (data.run == "R1") & ~((data.time_s > 6600) & (data.time_s < 8400))
    part = synthetic.take(keep)
    assert np.diff(part.data.time_s).max() == 1800.0
    batch = model.predict(part.inputs)
    assert np.max(np.abs(streamed(model.stream(), part) - batch)) < 1e-9
    before_gap = int(np.flatnonzero(part.data.time_s <= 6600)[-1]) + 1
    first, rest = (
        part.take(np.arange(part.data.n_samples) < before_gap),
        part.take(np.arange(part.data.n_samples) >= before_gap),
    )
    stream = model.stream()
    streamed(stream, first)
    saved = json.loads(json.dumps(stream.export_state()))  # as a restarted gateway reads it
    restarted = model.stream()
    restarted.import_state(saved)
    assert np.max(np.abs(streamed(restarted, rest) - batch[before_gap:])) < 1e-9
    # A state saved by a release that kept no last input still loads; it holds the new
    # sample over the gap, so only the rows after the gap differ, and by less each row.
    older = model.stream()
    older.import_state({k: v for k, v in saved.items() if not k.endswith("@input")})
    off = np.abs(streamed(older, rest) - batch[before_gap:])
    assert off[0] > 1e-3 and off[-1] < off[0] / 10


def test_the_running_indicator_is_1_while_the_spindle_turns() -> None:
    inputs = ModelInputs(np.zeros((3, 1)), ("T1",), np.array([0.0, 500.0, 4000.0]))
    terms = lag_terms(inputs, ("T1",), (), (0.0, 1.0))
    assert terms[:, 1].tolist() == [0.0, 1.0, 1.0] and terms[:, 2].tolist() == [0.0, 0.5, 4.0]
    assert term_names(("T1",), (600.0,), (0.0,)) == [
        "T1",
        "running",
        "T1@lag600s",
        "running@lag600s",
    ]


def test_stored_as_explicit_json_and_reloaded_exactly(synthetic: Prepared, tmp_path: Path) -> None:
    store = ModelStore(tmp_path / "store")
    outcome = fit_and_store(synthetic, "lag-ridge", store)
    (path,) = outcome.saved.values()
    document = json.loads(path.read_text(encoding="utf-8"))
    params = document["params"]
    names = term_names(synthetic.inputs.sensors, params["lag_taus_s"], params["speed_powers"])
    assert params["terms"] == names and len(params["coefficients_um_per_unit"]) == len(names)
    assert len(params["standardisation"]["mean"]) == len(names)
    grid = params["penalty_grid"]
    for key, value in params["penalties"].items():
        name = key.rsplit(".", 1)[-1]  # a stack names each member's penalties
        assert value in grid["sensors" if name == "speed" else name] or any(
            value == pytest.approx(p * r)
            for p in grid["sensors"]
            for r in grid["speed_over_sensors"]
        )
    choice = params["structure_choice"]
    assert [c["name"] for c in choice["candidates"]] == list(STRUCTURE_NAMES)
    assert set(choice["inner_rmse_um"]) == set(STRUCTURE_NAMES)
    assert sum(choice["weights"].values()) == pytest.approx(1.0)
    assert params["structure"]["lag_taus_s"] == params["lag_taus_s"]
    model, _ = load_file(path)
    assert np.array_equal(model.predict(synthetic.inputs), outcome_model(synthetic, params))
    # Conditioning is of every term; the bias sensitivity is the steady state: the sum of
    # each sensor's direct and lagged coefficients.
    conditioning = document["conditioning"]
    assert len(conditioning["vif"]) == len(names)
    coef = dict(zip(names, params["coefficients_um_per_unit"], strict=True))
    for sensor in synthetic.inputs.sensors:
        by_hand = coef[sensor] + sum(coef[f"{sensor}@lag{t:g}s"] for t in params["lag_taus_s"])
        assert conditioning["sensitivity_um_per_C"][sensor] == pytest.approx(by_hand, abs=1e-6)


def outcome_model(prepared: Prepared, params: dict) -> np.ndarray:
    """The stored model's prediction from its JSON numbers alone."""
    terms = lag_terms(
        prepared.inputs, tuple(params["sensors"]), params["lag_taus_s"], params["speed_powers"]
    )
    return params["intercept_um"] + terms @ np.asarray(params["coefficients_um_per_unit"])


def test_the_bank_steps_it_with_lag_states_that_survive_a_restart(
    synthetic: Prepared, tmp_path: Path
) -> None:
    store = ModelStore(tmp_path / "store")
    fit_and_store(synthetic, "lag-ridge", store)
    bank = ModelBank.from_store(store.root)
    (banked,) = bank.models.values()
    assert isinstance(banked, BankedAugmented)
    assert banked.sensors == frozenset({"T1", "T2", "T3"})
    model, _ = load_file(store.path_of(banked.model_id))
    run = synthetic.data.run == "R1"  # one cold recording
    part = synthetic.take(run)
    batch = model.predict(part.inputs)
    state_file = tmp_path / "m1-effect-state.json"
    states = EffectStates(bank.augmented(), state_file)
    streamed = []
    for k in range(part.data.n_samples):
        if k == 200:  # the gateway stops and starts again: the lags carry on from the file
            states.save()
            states = EffectStates(ModelBank.from_store(store.root).augmented(), state_file)
        rises = dict(zip(part.inputs.sensors, part.inputs.rise_C[k], strict=True))
        time_s = float(part.data.time_s[k])
        streamed.append(
            states.advance(time_s, rises, float(part.data.speed_rpm[k]))[banked.model_id]
        )
    assert np.max(np.abs(np.array(streamed) - batch)) < 1e-9
    # A cycle without one of its sensors predicts nothing and keeps the states.
    before = states.streams[banked.model_id].export_state()
    assert states.advance(1e6, {"T1": 1.0, "T2": 1.0}, 3000.0)[banked.model_id] is None
    assert states.streams[banked.model_id].export_state() == before


def test_the_runtime_refuses_it_when_a_small_bias_moves_it_too_far(
    synthetic: Prepared, tmp_path: Path
) -> None:
    store = ModelStore(tmp_path / "store")
    outcome = fit_and_store(synthetic, "lag-ridge", store)
    (model_id,) = outcome.saved
    worst = outcome.conditioning[model_id].worst_single_um
    assert worst > 0.2
    with pytest.raises(ValueError, match=rf"'{model_id}', which is refused: a bias of ±0\.5"):
        load_bank(machine(store.root, model_id, limit_um=worst / 2))
    assert model_id in load_bank(machine(store.root, model_id, limit_um=worst * 2))


def test_steady_state_rows_have_every_lag_at_its_input() -> None:
    inputs = ModelInputs(np.array([[1.0, 2.0]]), ("T1", "T2"), np.array([2000.0]))
    terms = lag_terms(inputs, ("T1", "T2"), TAUS_S, POWERS)
    assert terms[0].tolist() == [1.0, 2.0, 2.0, 4.0] * 3


def test_fl_thermal_ch1_held_out_with_nested_penalties(tmp_path: Path) -> None:
    out = tmp_path / "fit.json"
    store = tmp_path / "store"
    method = ("--method", "lag-ridge", "--target", "ch1_um")
    done = gateway_in_process("fit", FL_THERMAL, *method, "--json", out, "--store", store)
    assert done.returncode == 0, done.stderr
    assert "condition number" in done.stdout
    result = json.loads(out.read_text(encoding="utf-8"))
    pooled = result["validations"]["all"]["pooled"]
    # Measured 1.76 µm, the structures stacked on nested inner folds (two-group ridge alone:
    # 1.75 µm; plain mlr on the same rises: 6.86 µm); the target is 2.5 µm. An outside
    # review's 1.68 µm (one penalty, the speed as n only) is reached by none of its readings
    # in benchmarks/reviewer_readings.py (2.36 … 3.08 µm nested).
    assert pooled["rmse_um"] < 1.9
    per_cycle = result["validations"]["all"]["per_fold"]
    assert len(per_cycle) == 6 and max(c["rmse_um"] for c in per_cycle.values()) < 3.3
    assert (store / "lag-ridge-ch1_um-all.json").exists()


def test_fl_thermal_ch5_held_out_with_the_structure_chosen_on_the_training_cycles(
    tmp_path: Path,
) -> None:
    out, store = tmp_path / "fit.json", tmp_path / "store"
    done = gateway_in_process(
        "fit", FL_THERMAL, "--method", "lag-ridge", "--target", "ch5_um", "--json", out,
        "--store", store,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    pooled = json.loads(out.read_text(encoding="utf-8"))["validations"]["all"]["pooled"]
    # Measured 2.33 µm, the family fixed before its first held-out run (two-group ridge
    # alone: 4.90 µm); below the 2.5 µm target and the outside review's 2.99 µm.
    assert pooled["rmse_um"] < 2.5
    params = json.loads((store / "lag-ridge-ch5_um-all.json").read_text(encoding="utf-8"))["params"]
    # On all six cycles the nested choice takes the lasso on the sensors and the speed with
    # their 30 min lags, through 0 µm (inner RMSE 2.31 µm; lasso-30min 3.05, the ridges 4.67
    # and 4.90 µm).
    choice = params["structure_choice"]
    assert choice["weights"]["lasso-30min-zero"] > 0.5
    assert params["intercept_um"] == 0.0
    inner = choice["inner_rmse_um"]
    assert inner["lasso-30min-zero"] < min(v for k, v in inner.items() if k != "lasso-30min-zero")


def test_replay_fl_thermal_ch5_on_lag_ridge_a_probe_every_hour(tmp_path: Path) -> None:
    out = tmp_path / "replay.json"
    done = gateway_in_process(
        "replay", FL_THERMAL, "--target", "ch5_um", "--model", "lag-ridge", "--base", "lagged",
        "--probe-interval-min", "60", "--json", out,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text(encoding="utf-8"))
    assert result["model"] == "lag-ridge" and "lag-ridge terms" in result["base"]["description"]
    assert 2.0 < result["offline"]["rmse_um"] < 2.6  # lag-ridge without probes: 2.33 µm
    (online,) = result["online"]
    # Measured 2.31 µm, every choice (penalty, level weight, q, R, k) made without the held-out
    # cycle on a grid fixed beforehand; the 2.0 µm target is not met on ch5 by this
    # base (its own fit without probes: 4.16 µm), nor does it beat lag-ridge's 2.33 µm offline.
    assert online["rmse_um"] < 2.45
    assert online["rmse_um"] < 0.6 * online["base_rmse_um"]
    for figures in online["per_run"].values():
        chosen = figures["chosen"]
        assert chosen["ridge"] in (1e-4, 1e-3, 1e-2, 1e-1, 1.0)
        assert chosen["filter"]["outlier_sigma"] in (4.0, 6.0, 8.0)


def test_replay_fl_thermal_ch5_on_the_declared_lag_ridge_model_meets_the_targets(
    tmp_path: Path,
) -> None:
    out = tmp_path / "replay.json"
    done = gateway_in_process(
        "replay", FL_THERMAL, "--target", "ch5_um", "--model", "lag-ridge", "--base", "declared",
        "--probe-interval-min", "30", "--probe-interval-min", "60", "--json", out,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text(encoding="utf-8"))
    at_30, at_60 = result["online"]
    # Measured 1.46 and 1.88 µm (targets 1.5 and 2.0 µm): the lag-ridge fit of each training
    # set (its family fixed before its first held-out run) with the bias filter chosen on the
    # training cycles. Without probes: 2.33 µm.
    assert at_30["probe_interval_min"] == 30.0 and at_30["rmse_um"] < 1.5
    # The 60-min target with a margin of 0.05 µm (measured 1.88).
    assert at_60["probe_interval_min"] == 60.0 and at_60["rmse_um"] < 2.0 - 0.05
    assert at_60["rmse_um"] < 0.85 * result["offline"]["rmse_um"]


def test_replay_refuses_to_store_a_lag_ridge_base(tmp_path: Path) -> None:
    done = gateway_in_process(
        "replay", FL_THERMAL, "--target", "ch5_um", "--model", "lag-ridge",
        "--store", tmp_path / "store",
    )  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "error: --store with --model lag-ridge is not built: save the offline model with "
        "fit --method lag-ridge --store DIR"
    ]
    assert not (tmp_path / "store").exists()


def test_analyze_takes_lag_ridge_as_its_base_and_its_result_streams(tmp_path: Path) -> None:
    from models.analysis import augmented
    from models.online.streaming import StreamingAugmented

    # ch5: nothing is found inside lag-ridge there, so the result is stored (on ch1 the
    # unsensed heat path is found inside it, which the store cannot hold yet).
    out, store = tmp_path / "analysis.json", tmp_path / "store"
    done = gateway_in_process(
        "analyze", FL_THERMAL, "--target", "ch5_um", "--model", "lag-ridge",
        "--json", out, "--store", store, "--no-progress",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text(encoding="utf-8"))
    # Measured 2.32 µm before any effect; the target is 2.5 µm.
    assert result["before"]["rmse_um"] < 2.5
    (path,) = (store / augmented.FOLDER).glob("*.json")
    document = augmented.load(path)
    assert document["base"]["method"] == "lag-ridge"
    prepared = prepare(load_runs(FL_THERMAL, target="ch5_um"))
    batch = augmented.predict(document, prepared)
    stream = StreamingAugmented(document)
    assert np.max(np.abs(streamed(stream, prepared) - batch)) < 1e-9
    assert "base.time_s" in stream.export_state()
