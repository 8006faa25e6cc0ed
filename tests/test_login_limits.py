"""The lockout of failed logins: one definition (gateway.limits.LoginLimits), built from the
``login_*`` keys of ``scada`` and ``web`` by one function that the SCADA server's and the
console's wiring both call."""

from __future__ import annotations

from pathlib import Path

from gateway.config import load_config, login_limits
from gateway.limits import LoginLimits
from gateway.scada.login_throttle import ThrottlePolicy
from tests.cli import ROOT


def test_both_sections_build_their_login_limits_in_one_place(tmp_path: Path) -> None:
    text = (ROOT / "config.yaml").read_text(encoding="utf-8")
    sections = (
        "scada:\n  login_max_failures: 3\n  login_window_s: 20\n  login_lockout_s: 10\n"
        "  login_max_lockout_s: 40\n"
        "web:\n  login_max_failures: 7\n  login_lockout_s: 5\n"
    )
    path = tmp_path / "config.yaml"
    path.write_text(text.replace("\nmachines:\n", f"\n{sections}machines:\n", 1), "utf-8")
    config = load_config(path)
    assert config.scada is not None and config.web is not None
    assert login_limits(config.scada) == LoginLimits(
        max_failures=3, window_s=20.0, lockout_s=10.0, max_lockout_s=40.0
    )
    assert login_limits(config.web) == LoginLimits(max_failures=7, lockout_s=5.0)
    assert ThrottlePolicy is LoginLimits  # the servers' policy is that one definition
