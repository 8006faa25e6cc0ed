"""`python -m gateway demo --effect drift`: the monitor finds the effect, the demo promotes it.

The machine hides a drift the models lack (their training runs had none). The
demo's monitor phase (days of machine time, physics in-process) must propose
``drift``; the demo promotes it as an operator would; the next day's figures
without probes, with the online correction and after promotion are printed and
written, and the compensated run over the protocols uses the promoted model.
"""

from __future__ import annotations

import json
from pathlib import Path

from tests.cli import gateway


def test_demo_with_a_hidden_drift_proposes_promotes_and_reports(tmp_path: Path) -> None:
    out = tmp_path / "demo.json"
    result = gateway(
        "demo", "--effect", "drift", "--json", out, "--speedup", 1500, "--cycle-s", 30,
        "--workdir", tmp_path / "demo", timeout_s=400,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    report = json.loads(out.read_text())
    monitor = report["monitor"]
    assert monitor["proposal"] is not None, monitor
    assert monitor["proposal"]["effects"][0]["effect"] == "drift"
    for key in ("without_probes", "online_correction", "after_promotion"):
        assert f"{key}_rmse_um" in report and f"{key}_peak_um" in report
    assert report["after_promotion_rmse_um"] <= 0.7 * report["without_probes_rmse_um"], report
    assert report["online_correction_rmse_um"] < report["without_probes_rmse_um"], report
    for label in ("without probes", "with online correction", "after promotion"):
        assert label in result.stdout
    # The protocol run used the promoted model.
    assert any(m.startswith("monitor-") for m in report["models_used"]), report["models_used"]
    assert report["compensated_rmse_um"] <= 0.3 * report["uncompensated_rmse_um"], report
