"""Where rises are measured from (continuous recordings vs runs that start cold), and the
error's reference: as measured, an own origin only where a run at rest reads one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.data.dataset import load_runs
from models.data.features import prepare
from models.data.references import (
    REFERENCE_WINDOW_S,
    ZERO_TOLERANCE_UM,
    plan_references,
    reference_rows,
    rises,
)
from models.fit.workflow import fit_and_store
from models.store import ModelStore, load_file
from tests.test_store import resealed

DATA = Path(__file__).resolve().parent.parent / "data"


def write_runs(tmp_path: Path, starts: list[float], n: int = 4, dt: float = 60.0) -> Path:
    lines = ["run,time_s,speed_rpm,T1,error_um"]
    for r, start in enumerate(starts):
        for k in range(n):
            lines.append(f"R{r},{start + k * dt},1000,{20 + r + k},{k}")
    path = tmp_path / "runs.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_runs_whose_clock_runs_on_form_one_recording(tmp_path: Path) -> None:
    # R0 covers 0..180 s; R1 starts 60 s later (one interval) → same recording;
    # R2 restarts its clock at 0 → a new recording that starts cold.
    data = load_runs(write_runs(tmp_path, [0, 240, 0]))
    plan = plan_references(data, "auto")
    assert plan.recording_runs == (("R0", "R1"), ("R2",))
    np.testing.assert_array_equal(plan.recording, [0] * 8 + [1] * 4)


def test_a_gap_longer_than_three_intervals_starts_a_new_recording(tmp_path: Path) -> None:
    # R1 starts 181 s after R0's last sample (> 3 × 60 s).
    data = load_runs(write_runs(tmp_path, [0, 180 + 181]))
    assert plan_references(data, "auto").recording_runs == (("R0",), ("R1",))
    data = load_runs(write_runs(tmp_path, [0, 180 + 180]))
    assert plan_references(data, "auto").recording_runs == (("R0", "R1"),)


def test_explicit_policies(tmp_path: Path) -> None:
    data = load_runs(write_runs(tmp_path, [0, 240, 0]))
    assert plan_references(data, "run-start").recording_runs == (("R0",), ("R1",), ("R2",))
    assert plan_references(data, "recording-start").recording_runs == (("R0", "R1", "R2"),)
    with pytest.raises(ValueError, match="unknown reference policy 'cold'"):
        plan_references(data, "cold")


def test_rises_subtract_the_first_sample_of_each_recording() -> None:
    values = np.array([[20.0, 1.0], [21.0, 3.0], [22.5, 4.0], [30.0, 7.0], [31.0, 9.0]])
    recording = np.array([0, 0, 0, 1, 1])
    first = np.array([True, False, False, True, False])
    expected = np.array([[0.0, 0.0], [1.0, 2.0], [2.5, 3.0], [0.0, 0.0], [1.0, 2.0]])
    np.testing.assert_array_equal(rises(values, recording, first), expected)
    np.testing.assert_array_equal(rises(values[:, 1], recording, first), expected[:, 1])


def test_the_reference_is_the_mean_of_the_leading_samples_at_rest() -> None:
    values = np.array([[20.0, 0.2], [20.2, -0.2], [20.1, 0.3], [23.0, 4.0], [24.0, 5.0]])
    recording = np.array([0, 0, 0, 0, 0])
    time_s = np.arange(5) * 60.0
    speed_rpm = np.array([0.0, 0.0, 0.0, 3000.0, 3000.0])
    rows = reference_rows(recording, time_s, speed_rpm)
    np.testing.assert_array_equal(rows, [True, True, True, False, False])
    reference = values[:3].mean(axis=0)
    np.testing.assert_allclose(rises(values, recording, rows), values - reference)


def test_reference_rows_stop_at_the_window_and_at_a_spindle_already_turning() -> None:
    # Recording 0 rests for 20 min: only its first REFERENCE_WINDOW_S count.
    # Recording 1 starts at speed: its first sample alone, even after a later stop.
    time_s = np.r_[np.arange(21) * 60.0, np.arange(4) * 60.0]
    speed_rpm = np.r_[np.zeros(21), [2000.0, 0.0, 0.0, 0.0]]
    recording = np.r_[np.zeros(21, dtype=int), np.ones(4, dtype=int)]
    rows = reference_rows(recording, time_s, speed_rpm)
    assert rows[:21].sum() == int(REFERENCE_WINDOW_S // 60) + 1
    np.testing.assert_array_equal(rows[21:], [True, False, False, False])


def test_fl_thermal_cycles_are_one_recording() -> None:
    data = load_runs(DATA / "fl_thermal.csv", target="ch5_um")
    plan = plan_references(data, "auto")
    assert plan.recording_runs == (data.run_ids,)
    assert len(data.run_ids) == 6
    # The spindle starts after 7.5 min (31 samples at rest): those are the reference.
    moving = int(np.argmax(data.speed_rpm > 0))
    assert moving == 31
    np.testing.assert_array_equal(np.flatnonzero(plan.reference_rows), np.arange(moving))


def write_openings(tmp_path: Path, runs: dict[str, tuple[float, list[float]]]) -> Path:
    """Runs on separate days (their clocks restart): name → (error origin µm, speeds)."""
    lines = ["run,time_s,speed_rpm,T1,error_um"]
    for name, (origin, speeds) in runs.items():
        for k, speed in enumerate(speeds):
            lines.append(f"{name},{k * 60},{speed:g},{20 + 0.1 * k},{origin + 0.5 * k}")
    path = tmp_path / "openings.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_the_error_is_kept_as_measured_unless_a_run_at_rest_reads_an_origin_of_its_own(
    tmp_path: Path,
) -> None:
    # at-speed: opens turning, its first reading (7 µm) is growth, not an origin;
    # zeroed: opens at rest reading 0.3 µm (within 1 µm of zero): as measured;
    # offset: opens at rest reading 15 µm: that lead-in mean is its origin.
    at_rest = [0, 0, 0, 2000, 2000]
    path = write_openings(
        tmp_path,
        {"at-speed": (7.0, [3000] * 5), "zeroed": (0.3, at_rest), "offset": (15.0, at_rest)},
    )
    data = load_runs(path)
    plan = plan_references(data)
    assert plan.recording_runs == (("at-speed",), ("zeroed",), ("offset",))
    lead_in_mean = 15.0 + 0.5 * np.mean([0, 1, 2])
    np.testing.assert_allclose(plan.error_origin_um, [0.0, 0.0, lead_in_mean])
    np.testing.assert_array_equal(plan.own_origin, [False, False, True])
    expected = data.error_um - np.r_[np.zeros(10), np.full(5, lead_in_mean)]
    np.testing.assert_allclose(plan.error(data.error_um), expected)
    assert plan.describe()["error_reference"]["origin_um"] == [0.0, 0.0, lead_in_mean]


def test_the_tolerance_separates_a_zeroed_probe_from_an_origin_of_its_own(tmp_path: Path) -> None:
    for origin, own in ((ZERO_TOLERANCE_UM - 0.6, False), (ZERO_TOLERANCE_UM - 0.4, True)):
        # lead-in readings origin, origin + 0.5, origin + 1.0: mean origin + 0.5
        data = load_runs(write_openings(tmp_path, {"R": (origin, [0, 0, 0, 1000])}))
        assert bool(plan_references(data).own_origin[0]) is own, origin


def test_prepared_target_is_the_error_as_measured_for_runs_opening_at_speed(
    tmp_path: Path,
) -> None:
    data = load_runs(write_openings(tmp_path, {"A": (4.0, [3000] * 4), "B": (2.0, [5000] * 4)}))
    prepared = prepare(data)
    np.testing.assert_array_equal(prepared.error_um, data.error_um)
    # the temperatures still rise from each recording's first sample
    np.testing.assert_allclose(prepared.inputs.rise_C[:, 0], np.tile(0.1 * np.arange(4), 2))


def test_stored_models_carry_the_error_reference_and_old_files_without_it_load(
    tmp_path: Path,
) -> None:
    path = write_openings(
        tmp_path, {"A": (0.0, [0, 0, 1000, 2000, 3000]), "B": (0.2, [0, 0, 3000, 2000, 1000])}
    )
    prepared = prepare(load_runs(path))
    store = ModelStore(tmp_path / "store")
    saved = fit_and_store(prepared, "mlr", store)
    model, document = load_file(saved.saved[next(iter(saved.saved))])
    assert document.error_reference is not None
    assert document.error_reference["intercept_um"] == pytest.approx(model.intercept_um_)
    assert document.error_reference["recording_origin_um"] == [0.0, 0.0]
    # A file written before the field existed: the same document without it, re-checksummed.
    raw = json.loads(Path(saved.saved[document.model_id]).read_text(encoding="utf-8"))
    del raw["error_reference"]
    raw = resealed(raw, tmp_path)  # its checksum and signature made again
    old = tmp_path / "old.json"
    old.write_text(json.dumps(raw), encoding="utf-8")
    reloaded, old_document = load_file(old)
    assert old_document.error_reference is None
    assert reloaded.intercept_um_ == model.intercept_um_
