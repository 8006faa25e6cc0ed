"""Loading measured runs: good files load exactly, every bad one is refused precisely."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.data.dataset import DataError, load_runs

HEADER = "run,time_s,speed_rpm,T1,T2,ambient_C,error_um,note\n"
GOOD_ROWS = [
    "K1,0,0,20.0,21.0,20.0,0.0,cold\n",
    "K1,180,2000,20.5,21.2,20.1,1.5,warm\n",
    "K1,360,2000,21.0,21.4,20.1,2.5,warm\n",
    "K2,0,4000,20.1,21.0,20.2,0.1,cold\n",
    "K2,180,4000,21.1,21.6,20.2,3.0,warm\n",
]


def write(tmp_path: Path, text: str, name: str = "runs.csv") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def refused(path: Path, **kwargs) -> DataError:
    with pytest.raises(DataError) as caught:
        load_runs(path, **kwargs)
    return caught.value


def test_good_file_loads_every_column(tmp_path: Path) -> None:
    data = load_runs(write(tmp_path, HEADER + "".join(GOOD_ROWS)))
    assert data.n_samples == 5
    assert data.run_ids == ("K1", "K2")
    assert data.sensors == ("T1", "T2")
    np.testing.assert_array_equal(data.speed_rpm, [0, 2000, 2000, 4000, 4000])
    np.testing.assert_array_equal(data.error_um, [0.0, 1.5, 2.5, 0.1, 3.0])
    np.testing.assert_array_equal(data.ambient_C, [20.0, 20.1, 20.1, 20.2, 20.2])
    assert list(data.labels["note"]) == ["cold", "warm", "warm", "cold", "warm"]
    assert [s for _, s in data.run_slices()] == [slice(0, 3), slice(3, 5)]
    np.testing.assert_array_equal(data.lines, [2, 3, 4, 5, 6])
    assert data.skipped == ()


def test_missing_column_names_file_line_and_column(tmp_path: Path) -> None:
    path = write(tmp_path, "run,time_s,T1,error_um\nK1,0,20,0\n")
    error = refused(path)
    assert (error.path, error.line, error.column) == (str(path), 1, "speed_rpm")
    assert str(error).startswith(f"{path}:1: column 'speed_rpm': missing required column")


def test_missing_error_column_suggests_target(tmp_path: Path) -> None:
    path = write(tmp_path, "run,time_s,speed_rpm,T1,ch5_um\nK1,0,0,20,0\n")
    error = refused(path)
    assert error.column == "error_um" and "--target" in str(error)


def test_text_in_numeric_cell(tmp_path: Path) -> None:
    rows = list(GOOD_ROWS)
    rows[2] = "K1,360,2000,21.0,hot,20.1,2.5,warm\n"
    path = write(tmp_path, HEADER + "".join(rows))
    error = refused(path)
    assert (error.line, error.column) == (4, "T2")
    assert "expected a finite number, found 'hot'" in str(error)
    assert str(error).startswith(f"{path}:4: column 'T2'")


def test_a_stray_control_byte_is_shown_not_hidden(tmp_path: Path) -> None:
    """A control byte is invisible on a terminal: the message shows it escaped."""
    rows = list(GOOD_ROWS)
    rows[2] = "K1,360,2000,21.0,\x0121.5,20.1,2.5,warm\n"
    error = refused(write(tmp_path, HEADER + "".join(rows)))
    assert (error.line, error.column) == (4, "T2")
    assert "expected a finite number, found '\\x0121.5'" in str(error), str(error)


def test_non_finite_number_is_refused(tmp_path: Path) -> None:
    rows = list(GOOD_ROWS)
    rows[1] = "K1,180,2000,20.5,21.2,20.1,inf,warm\n"
    error = refused(write(tmp_path, HEADER + "".join(rows)))
    assert (error.line, error.column) == (3, "error_um")


def test_time_going_backwards_within_a_run(tmp_path: Path) -> None:
    rows = list(GOOD_ROWS)
    rows[2] = "K1,100,2000,21.0,21.4,20.1,2.5,warm\n"
    error = refused(write(tmp_path, HEADER + "".join(rows)))
    assert (error.line, error.column) == (4, "time_s")
    assert "time does not increase within run 'K1': 100 s after 180 s at line 3" in str(error)


def test_time_may_restart_at_a_new_run(tmp_path: Path) -> None:
    data = load_runs(write(tmp_path, HEADER + "".join(GOOD_ROWS)))
    assert data.time_s[3] == 0.0


def test_run_split_in_two_places_is_refused(tmp_path: Path) -> None:
    rows = [*GOOD_ROWS, "K1,900,0,20,21,20,0,late\n"]
    error = refused(write(tmp_path, HEADER + "".join(rows)))
    assert (error.line, error.column) == (7, "run")
    assert "contiguous" in str(error)


def test_empty_file(tmp_path: Path) -> None:
    path = write(tmp_path, "")
    error = refused(path)
    assert (error.line, error.column) == (1, None)
    assert str(error) == f"{path}:1: the file is empty; a header row was expected"


def test_header_only(tmp_path: Path) -> None:
    error = refused(write(tmp_path, HEADER))
    assert error.line == 2 and "no data rows" in str(error)


def test_unknown_target(tmp_path: Path) -> None:
    path = write(tmp_path, HEADER + "".join(GOOD_ROWS))
    error = refused(path, target="ch9_um")
    assert (error.line, error.column) == (1, "ch9_um")
    assert "unknown --target" in str(error)


def test_unknown_sensor(tmp_path: Path) -> None:
    error = refused(write(tmp_path, HEADER + "".join(GOOD_ROWS)), sensors=["T1", "T7"])
    assert error.column == "T7" and "temperature columns: T1, T2" in str(error)


def test_duplicate_column(tmp_path: Path) -> None:
    error = refused(write(tmp_path, "run,time_s,speed_rpm,T1,T1,error_um\nK1,0,0,1,1,0\n"))
    assert (error.line, error.column) == (1, "T1") and "twice" in str(error)


def test_row_with_wrong_field_count(tmp_path: Path) -> None:
    rows = list(GOOD_ROWS)
    rows[1] = "K1,180,2000,20.5,21.2,20.1,1.5,warm,extra\n"
    error = refused(write(tmp_path, HEADER + "".join(rows)))
    assert error.line == 3 and "expected 8 fields as in the header, found 9" in str(error)


def test_empty_cells_are_skipped_and_reported(tmp_path: Path) -> None:
    rows = list(GOOD_ROWS)
    rows[1] = "K1,180,2000,,21.2,20.1,1.5,warm\n"
    data = load_runs(write(tmp_path, HEADER + "".join(rows) + "\n"))
    assert data.n_samples == 4
    (skipped,) = data.skipped
    assert skipped.count == 2 and skipped.first_lines == (3, 7)
    assert "skipped 2 row(s): an empty cell" in skipped.describe()


def test_missing_file(tmp_path: Path) -> None:
    error = refused(tmp_path / "nope.csv")
    assert "file not found" in str(error)


def test_label_per_run_refuses_a_run_with_two_labels(tmp_path: Path) -> None:
    data = load_runs(write(tmp_path, HEADER + "".join(GOOD_ROWS)))
    with pytest.raises(DataError) as caught:
        data.label_per_run("note")
    assert caught.value.line == 3 and "changes its note from 'cold' to 'warm'" in str(caught.value)


def reversed_copy(source: Path, target: Path) -> int:
    """``source`` with every speed of its last run negated (a control signing M04 as minus);
    the number of rows negated."""
    lines = source.read_text(encoding="utf-8").splitlines()
    last_run = lines[-1].split(",")[0]
    negated = 0
    for index, line in enumerate(lines[1:], start=1):
        cells = line.split(",")
        if cells[0] == last_run and float(cells[2]) > 0:
            cells[2] = f"-{cells[2]}"
            lines[index] = ",".join(cells)
            negated += 1
    target.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return negated


def test_a_negative_speed_counts_by_its_magnitude_noted_once(tmp_path: Path) -> None:
    """A reversed spindle heats as much as forward: the live loop takes the magnitude of a
    negative speed, so the measured runs do too (one note naming the first line)."""
    rows = [*GOOD_ROWS[:3], "K2,0,-4000,20.1,21.0,20.2,0.1,cold\n"]
    rows.append("K2,180,-4000,21.1,21.6,20.2,3.0,warm\n")
    data = load_runs(write(tmp_path, HEADER + "".join(rows)))
    np.testing.assert_array_equal(data.speed_rpm, [0, 2000, 2000, 4000, 4000])
    assert data.notes == (
        "column 'speed_rpm': line 5: a negative speed (-4000 r/min, turning in reverse); "
        "its magnitude is used",
    )


def test_fit_on_a_reversed_run_gives_the_model_of_the_forward_run(tmp_path: Path) -> None:
    """Through the command as a process: the same model as with the speeds unsigned."""
    from tests.cli import gateway
    from tests.synthetic import write_runs_csv

    forward = write_runs_csv(tmp_path / "forward.csv", seed=3)
    reverse = tmp_path / "reverse.csv"
    assert reversed_copy(forward, reverse) > 10
    documents = []
    for path in (forward, reverse):
        store = tmp_path / f"store-{path.stem}"
        result = gateway("fit", path, "--method", "mlr", "--store", store, "--no-progress")
        assert result.returncode == 0, result.stderr
        notes = [line for line in result.stderr.splitlines() if "turning in reverse" in line]
        assert len(notes) == (path == reverse), result.stderr
        (document,) = sorted(store.rglob("*.json"))
        documents.append(json.loads(document.read_text(encoding="utf-8")))
    for key in ("params", "validation", "regime"):
        assert documents[0][key] == documents[1][key], key
