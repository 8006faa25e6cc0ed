"""The calibrated prediction interval (models/fit/interval.py) and its coverage offline.

Coverage is always checked on data the calibration did not see: each leave-one-run-out
run against the width calibrated on the other runs (stored with the model), the FL
recording's later runs c5–c6 scored with the model fitted on c1–c4, and simulated
production programmes the fit never saw. The nominal interval is 90 %; a coverage
outside 85–95 % fails (the forward FL figure on c5–c6 is only bounded below: it
covers 96–100 %, and no width calibrated on c1–c4 can be in band there on every
channel, which ``score``'s half-widths for 85–95 % show; see docs/models/interval.md).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from gateway.live.bank.model_bank import BankedModel
from gateway.live.interval import assess
from models.fit.interval import (
    band_half_widths,
    calibrate,
    conformal_half_width,
    coverage,
    rule_check,
    span_excess,
    widened_um,
    with_probe_age,
)
from models.store import load_file
from simulator.params import load_params
from simulator.programs import production_program
from simulator.record import record
from tests import gateway_rig as rig
from tests.cli import gateway_in_process
from tests.test_store import resealed

ROOT = Path(__file__).resolve().parents[1]
FL = ROOT / "data" / "fl_thermal.csv"
BAND = (0.85, 0.95)


# --- pure maths ----------------------------------------------------------------------
def test_half_width_is_the_conformal_rank() -> None:
    values = np.arange(1.0, 101.0)  # |residuals| 1 … 100
    # ⌈(100 + 1) · 0.9⌉ = 91st smallest
    assert conformal_half_width(values, 0.9) == 91.0
    assert conformal_half_width(values[:20], 0.9) is None  # too few to place it


def test_band_half_widths_cover_85_and_95_percent_of_the_rows() -> None:
    values = np.concatenate([np.arange(1.0, 201.0)[::-1], [np.nan, np.inf]])
    low, high = band_half_widths(values)
    assert (low, high) == (170.0, 190.0)  # the 170th and 190th smallest of 200
    finite = values[np.isfinite(values)]
    assert coverage(finite, np.zeros(finite.size), low)["coverage"] == 0.85
    assert coverage(finite, np.zeros(finite.size), high)["coverage"] == 0.95
    assert band_half_widths(np.array([np.nan])) is None


def test_coverage_counts_rows_within_the_width() -> None:
    measured = np.array([0.0, 1.0, 2.0, 3.0, np.nan])
    found = coverage(measured, np.zeros(5), 1.5)
    assert found == {"coverage": 0.5, "mean_width_um": 3.0, "n_samples": 4}


def test_widening_beyond_the_span_and_per_bad_sensor() -> None:
    stored = {"rise_C": {"T1": [0.0, 10.0]}, "speed_rpm": [0.0, 6000.0]}
    assert span_excess(stored, {"T1": 10.4}, 6200.0) == (0.0, [])  # within the margin
    excess, names = span_excess(stored, {"T1": 5.0}, 8000.0)
    assert names == ["speed"] and math.isclose(excess, (8000 - 6300) / 6000)
    cal = {"half_width_um": 2.0, "outside_gain": 2.0, "bad_sensor_factor": 1.5}
    assert widened_um(cal, 0.0, 0) == 2.0
    assert math.isclose(widened_um(cal, 0.5, 1), 2.0 * 2.0 * 1.5)


def test_probe_age_widens_in_quadrature_by_the_filters_grown_variance() -> None:
    from models.online.correction import CorrectionParams, OnlineCorrection

    filter_ = OnlineCorrection(CorrectionParams(process_um2_per_h=2.0, decay_after_s=7200.0))
    assert filter_.added_variance_um2(100.0) == 0.0  # no probe yet: no correction applied
    assert filter_.update(0.0, 3.0).accepted
    assert filter_.added_variance_um2(0.0) == 0.0
    assert math.isclose(filter_.added_variance_um2(1800.0), 2.0 * 0.5)  # random walk: q·Δt
    # in silence the correction decays, and the variance it carries with it
    decayed = filter_.added_variance_um2(7200.0 + 3600.0)
    assert math.isclose(decayed, 2.0 * 3.0 * math.exp(-2.0))
    assert with_probe_age(1.0, 0.0, 0.9) == 1.0
    # every kind: the filter's own predicted covariance, H (F P Fᵀ + Q) Hᵀ − H P Hᵀ
    for params in (
        CorrectionParams(process_um2_per_h=0.5, reversion_tau_s=5400.0),
        CorrectionParams(kind="bias-rate", process_um2_per_h=0.3, rate_process_um2_per_h3=0.2),
        CorrectionParams(kind="bias-gain", process_um2_per_h=0.3, gain_process_per_h=0.01),
    ):
        one = OnlineCorrection(params)
        assert one.update(0.0, 2.0, predicted_um=8.0).accepted
        assert one.update(900.0, 2.5, predicted_um=9.0).accepted
        F, Q = one._transition(2000.0)
        H = one._h(7.0)
        grown = float(H @ (F @ one.P @ F.T + Q) @ H - H @ one.P @ H)
        assert math.isclose(one.added_variance_um2(2900.0, 7.0), grown, rel_tol=1e-9)
    assert math.isclose(with_probe_age(1.0, 1.0, 0.9), math.sqrt(1 + 1.6448536269514722**2))


def test_live_span_check_gives_the_offline_figures() -> None:
    """The loop's precomputed bounds (gateway/live/interval.py) agree with score's check."""
    from gateway.live.interval import excess_of

    stored = {"rise_C": {"T1": [0.0, 10.0], "T2": [-1.0, 0.2]}, "speed_rpm": [0.0, 6000.0]}
    rng = np.random.default_rng(1)
    for _ in range(500):
        rises = {"T1": float(rng.uniform(-5, 20)), "T2": float(rng.uniform(-3, 3))}
        speed = float(rng.uniform(0, 9000))
        live = excess_of(stored, rises, speed)
        offline = span_excess(stored, rises, speed)
        assert live[1] == offline[1] and math.isclose(live[0], offline[0], abs_tol=1e-12)


def test_calibration_is_normalised_by_the_folds_span() -> None:
    """A held-out run beyond the others' span counts as the extrapolation it was."""
    from models.base import ModelInputs

    rng = np.random.default_rng(0)
    runs = np.repeat(["a", "b", "c", "d"], 100)
    speed = np.repeat([1000.0, 2000.0, 3000.0, 6000.0], 100)
    inputs = ModelInputs(rng.uniform(0, 5, (400, 1)), ("T1",), speed)
    residual = rng.normal(0, 1, 400) * np.where(runs == "d", 3.0, 1.0)
    cal = calibrate(residual, np.zeros(400), runs, inputs)
    assert cal is not None
    plain = conformal_half_width(np.abs(residual), 0.9)
    assert plain is not None and cal["half_width_um"] < plain
    assert set(cal["per_run_coverage"]) == {"a", "b", "c", "d"}


def test_stored_rule_is_checked_run_by_run_on_both_schemes() -> None:
    """Each run against the rule calibrated without it: a forward run unlike the other
    forward run is not covered, and the check says so."""
    runs = np.repeat(["a", "b", "c", "d"], 40)
    loro = np.ones(160)
    forward_runs = np.repeat(["c", "d"], 40)
    forward = np.where(forward_runs == "d", 10.0, 1.0)
    found = rule_check(loro, runs, forward, forward_runs, 0.9)
    assert found is not None
    # run c: width max(1, 10) from d's forward residuals covers c; run d: width 1 does not
    assert found["forward"] == 0.5 and found["leave_one_run_out"] == 1.0
    assert found["both"] == (160 + 40) / 240 and found["n_samples"] == 240
    assert rule_check(loro, runs, None, None, 0.9) is None


# --- FL recording --------------------------------------------------------------------
def split_fl(folder: Path) -> tuple[Path, Path]:
    with FL.open(encoding="utf-8", newline="") as f:
        rows = list(csv.reader(f))
    paths = (folder / "c1-c4.csv", folder / "c5-c6.csv")
    for path, keep in zip(paths, (("c1", "c2", "c3", "c4"), ("c5", "c6")), strict=True):
        with path.open("w", encoding="utf-8", newline="") as f:
            csv.writer(f).writerows([rows[0], *(r for r in rows[1:] if r[0][:2] in keep)])
    return paths


@pytest.fixture(scope="module", params=["ch1_um", "ch3_um", "ch5_um"])
def fl_fit(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict:
    target = request.param
    folder = tmp_path_factory.mktemp(f"interval-fl-{target}")
    train, test = split_fl(folder)
    store = folder / "store"
    done = gateway_in_process("fit", train, "--target", target, "--store", store)
    assert done.returncode == 0, done.stderr
    out = folder / "score.json"
    model_id = f"lag-ridge-{target}-all"
    done = gateway_in_process("score", test, "--model", model_id, "--store", store, "--json", out)
    assert done.returncode == 0, done.stderr
    document = json.loads((store / f"{model_id}.json").read_text(encoding="utf-8"))
    return {
        "document": document,
        "score": json.loads(out.read_text()),
        "stdout": done.stdout,
        "stderr": done.stderr,
    }


@pytest.fixture(scope="module")
def fl_whole(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """The default fitted on the whole recording (its six cycles), the three channels in
    one command: each model's stored interval document."""
    store = tmp_path_factory.mktemp("interval-fl-whole") / "store"
    targets = ("--target", "ch1_um", "--target", "ch3_um", "--target", "ch5_um")
    done = gateway_in_process("fit", FL, *targets, "--store", store, "--no-progress")
    assert done.returncode == 0, done.stderr
    return {
        target: json.loads((store / f"lag-ridge-{target}-all.json").read_text("utf-8"))
        for target in ("ch1_um", "ch3_um", "ch5_um")
    }


@pytest.mark.parametrize("target", ["ch1_um", "ch3_um", "ch5_um"])
def test_fl_leave_one_cycle_out_coverage_in_band(fl_whole: dict, target: str) -> None:
    """Leave-one-cycle-out on the whole recording: each cycle against the width calibrated
    on the other five cycles' held-out residuals, pooled; and the stored rule likewise."""
    interval = fl_whole[target]["interval"]
    assert interval["nominal_coverage"] == 0.9
    assert len(interval["per_run_coverage"]) == 6
    assert BAND[0] <= interval["heldout_coverage"] <= BAND[1], interval
    assert BAND[0] <= interval["stored_rule_check"]["both"] <= BAND[1], interval


def test_fl_c1_c4_stored_rule_checked_in_band(fl_fit: dict) -> None:
    """Fitted on c1–c4 only: the stored rule (larger of the two quantiles) on c1–c4's own
    held-out predictions, each run against the rule calibrated on the others. (With four
    runs, each calibrated on three, the leave-one-run-out quantile alone is not checked
    here: the whole recording's six cycles check it above.)"""
    interval = fl_fit["document"]["interval"]
    assert interval["nominal_coverage"] == 0.9
    assert interval["half_width_um"] > 0
    check = interval["stored_rule_check"]
    assert check["n_samples"] == interval["n_samples"] + 2 * 1920  # c3 and c4 forward
    assert BAND[0] <= check["both"] <= BAND[1], check


def test_fl_forward_coverage_scored_on_c5_c6(fl_fit: dict) -> None:
    found = fl_fit["score"]["interval"]
    assert set(found["per_run"]) == {"c5_3500rpm", "c6_steps"}
    pooled = found["pooled"]
    assert pooled["n_samples"] == 1920 + 1485
    assert pooled["coverage"] >= BAND[0], found  # never narrower than promised
    assert pooled["mean_width_um"] >= 2 * fl_fit["document"]["interval"]["half_width_um"]
    assert "interval" in fl_fit["stdout"] and "coverage" in fl_fit["stdout"]


def test_fl_forward_score_says_which_widths_would_have_been_in_band(fl_fit: dict) -> None:
    """``score`` gives, per run and pooled, the stored half-widths that would have covered
    85 % and 95 % of the rows; the coverage it reports agrees with where the stored width
    lies against them, and a stored width outside them is named."""
    found = fl_fit["score"]["interval"]
    stored = found["half_width_um_stored"]
    for row in (*found["per_run"].values(), found["pooled"]):
        low, high = row["half_width_um_for_85_95"]
        assert 0 < low <= high
        assert (row["coverage"] >= BAND[1]) == (stored >= high), row
        assert (row["coverage"] < BAND[0]) == (stored < low), row
    low, high = found["pooled"]["half_width_um_for_85_95"]
    named = f"{low:.2f}–{high:.2f} µm would have covered"
    assert (named in fl_fit["stdout"] + fl_fit["stderr"]) == (not low <= stored <= high)


def test_fl_calibration_gives_each_schemes_band(fl_fit: dict) -> None:
    """The calibration's own held-out rows: the half-widths covering 85 % and 95 % of each
    scheme's residuals bracket that scheme's 90 % quantile."""
    interval = fl_fit["document"]["interval"]
    bands = interval["half_width_um_for_85_95"]
    for scheme, quantile in (("loro", "half_width_um_loro"), ("forward", "half_width_um_forward")):
        low, high = bands[scheme]
        assert low <= interval[quantile] <= high, (scheme, interval)
        assert low < high


# --- simulated production ------------------------------------------------------------
@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("interval-sim")
    store = rig.fit_store(folder)
    programs = [production_program(seed=s, duration_s=5 * 3600.0) for s in (31, 32)]
    data = folder / "production.csv"
    data.write_text(record(load_params(), programs, seed=7).to_csv(), encoding="utf-8")
    return store, data


@pytest.mark.parametrize("model_id", ["mlr-error_um-all", "mlr-error_um-variable"])
def test_unseen_production_coverage_in_band(
    simulated: tuple[Path, Path], tmp_path: Path, model_id: str
) -> None:
    store, data = simulated
    out = tmp_path / "score.json"
    done = gateway_in_process("score", data, "--model", model_id, "--store", store, "--json", out)
    assert done.returncode == 0, done.stderr
    found = json.loads(out.read_text())["interval"]
    assert BAND[0] <= found["pooled"]["coverage"] <= BAND[1], found
    for run in found["per_run"].values():
        assert BAND[0] <= run["coverage"] <= BAND[1], found


# --- models stored without a calibration ---------------------------------------------
def test_model_without_calibration_loads_and_has_no_interval(
    simulated: tuple[Path, Path], tmp_path: Path
) -> None:
    store, data = simulated
    old = tmp_path / "old"
    old.mkdir()
    raw = json.loads((store / "mlr-error_um-all.json").read_text(encoding="utf-8"))
    del raw["interval"]
    raw = resealed(raw, old)  # as a holder of the key wrote it before intervals existed
    (old / "mlr-error_um-all.json").write_text(json.dumps(raw), encoding="utf-8")
    model, document = load_file(old / "mlr-error_um-all.json")
    assert document.interval is None
    banked = BankedModel(document.model_id, model, document)
    state = assess(banked, 3.0, {"T1": 1.0}, 2000.0, 0)
    assert state.half_width_um is None and state.span == "inside"
    out = tmp_path / "score.json"
    done = gateway_in_process(
        "score", data, "--model", "mlr-error_um-all", "--store", old, "--json", out
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text())["interval"] is None
    assert "no calibrated interval" in done.stderr  # a note: on the notes stream


def test_replay_reports_the_interval_coverage_per_run_and_pooled(tmp_path: Path) -> None:
    out = tmp_path / "replay.json"
    done = gateway_in_process("replay", FL, "--target", "ch1_um", "--model", "mlr", "--json", out)
    assert done.returncode == 0, done.stderr
    interval = json.loads(out.read_text())["offline"]["interval"]
    assert set(interval["per_run_coverage"]) == {
        "c1_1250rpm",
        "c2_2500rpm",
        "c3_3750rpm",
        "c4_5000rpm",
        "c5_3500rpm",
        "c6_steps",
    }
    assert BAND[0] <= interval["heldout_coverage"] <= BAND[1], interval
    assert "coverage" in done.stdout and "pooled over the held-out runs" in done.stdout
    # Each run: the half-widths that would have covered 85 % and 95 % of it, which agree
    # with its coverage at the width calibrated on the other runs.
    for run, row in interval["per_run_coverage"].items():
        low, high = row["half_width_um_for_85_95"]
        assert 0 < low <= high, row
        assert (row["coverage"] >= BAND[1]) == (row["half_width_um"] >= high), (run, row)
        assert (row["coverage"] < BAND[0]) == (row["half_width_um"] < low), (run, row)
        assert f"85–95 % at ±{low:.2f}–{high:.2f} µm" in done.stdout
