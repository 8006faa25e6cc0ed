"""``compensation.when_uncertain``: a good section loads, a bad value is refused with
file, line and key path."""

from __future__ import annotations

from pathlib import Path

from gateway.config import load_config
from tests.test_config import GOOD, refusal, store, write_config

__all__ = ["store"]  # the fixture, shared with test_config


def with_gate(section: str) -> str:
    return GOOD.replace("clamp_um: 40", f"clamp_um: 40\n      when_uncertain: {section}")


def test_off_by_default_and_a_good_gate_loads(tmp_path: Path, store: Path) -> None:
    default = load_config(write_config(tmp_path, store)).machines[0].compensation
    assert default.when_uncertain is None
    path = write_config(tmp_path, store, with_gate("{above_um: 5, action: scale, scale: 0.25}"))
    gate = load_config(path).machines[0].compensation.when_uncertain
    assert gate is not None and (gate.above_um, gate.action, gate.scale) == (5.0, "scale", 0.25)


def test_a_width_of_zero_is_refused_on_its_line(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store, with_gate("{above_um: 0}"))
    assert refusal(path) == (
        f"{path}:16: machines[0].compensation.when_uncertain.above_um: "
        "Input should be greater than 0"
    )


def test_an_unknown_action_and_a_scale_with_hold_are_refused(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store, with_gate("{above_um: 5, action: drop}"))
    assert refusal(path).startswith(f"{path}:16: machines[0].compensation.when_uncertain.action:")
    path = write_config(tmp_path, store, with_gate("{above_um: 5, scale: 0.5}"))
    message = refusal(path)
    assert message.startswith(f"{path}:16: machines[0].compensation.when_uncertain.scale:")
    assert "applies to action 'scale' only" in message
