"""gateway.live.reference: the saved reference says whether it was taken with the spindle
turning."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gateway.live.reference import TemperatureReference


def test_a_reference_taken_turning_is_marked_and_the_mark_survives_a_restart(
    tmp_path: Path,
) -> None:
    state = tmp_path / "vmc-reference.json"
    first = TemperatureReference("first-reading", {}, state)
    first.observe({}, 6000.0)  # the gateway's first cycle: turning, no good reading yet
    first.observe({"T1": 31.0, "T2": 29.5}, 6000.0)
    assert first.taken_turning is True
    assert json.loads(state.read_text())["taken_turning"] is True
    again = TemperatureReference("first-reading", {}, state)
    assert again.taken_turning is True and again.values_C == {"T1": 31.0, "T2": 29.5}


def test_a_reference_taken_after_a_start_at_rest_is_cold(tmp_path: Path) -> None:
    state = tmp_path / "vmc-reference.json"
    reference = TemperatureReference("first-reading", {}, state)
    reference.observe({}, 0.0)  # at rest when the gateway started
    reference.observe({"T1": 20.0}, 6000.0)  # the first good reading after cycle start
    assert reference.taken_turning is False
    assert TemperatureReference("first-reading", {}, state).taken_turning is False


def test_a_file_without_the_mark_leaves_it_unknown_and_a_bad_mark_is_refused(
    tmp_path: Path,
) -> None:
    state = tmp_path / "vmc-reference.json"
    state.write_text(json.dumps({"reference_C": {"T1": 20.0}}))
    assert TemperatureReference("first-reading", {}, state).taken_turning is None
    state.write_text(json.dumps({"reference_C": {"T1": 20.0}, "taken_turning": "yes"}))
    with pytest.raises(ValueError, match=r"vmc-reference.json: 'taken_turning' must be true or"):
        TemperatureReference("first-reading", {}, state)
