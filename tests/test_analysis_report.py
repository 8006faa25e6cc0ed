"""The HTML report of an analysis: readable figures, escaped text, every plot present and valid."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.image import imread

from gateway.offline.report import write_report
from models.analysis.result import AnalysisResult, CandidateResult, StepResult
from models.fit.metrics import accuracy

MODEL = "mlr_T1_T3"
EVIL_REASON = "gain <b>& too small"


def _candidate(
    effect: str, params: dict, rmse: float, before: float, believed: bool, reason: str
) -> CandidateResult:
    return CandidateResult(
        effect=effect,
        params=params,
        label=f"{effect} term",
        rmse_um=rmse,
        gain_pct=100.0 * (1.0 - rmse / before),
        folds_improved=3 if believed else 1,
        folds=3,
        p_value=1.234e-5 if believed else 0.4321,
        believed=believed,
        reason=reason,
        n_terms=1,
        rmse_before_um=before,
        alpha=0.01 / 3,
    )


def _runs(names: list[str], n_per_run: int) -> tuple[np.ndarray, np.ndarray]:
    """Run labels as an object array (as read from CSV) and each run's time from 0 to 4 h."""
    run = np.array([name for name in names for _ in range(n_per_run)], dtype=object)
    time_s = np.tile(np.linspace(0.0, 4 * 3600.0, n_per_run), len(names))
    return run, time_s


def _lag_result(names: list[str], n_per_run: int = 300) -> AnalysisResult:
    """A model that lacks a thermal lag; step 1 adds it, step 2 finds nothing more."""
    run, time_s = _runs(names, n_per_run)
    rng = np.random.default_rng(1)
    hours = time_s / 3600.0
    measured = 20.0 * (1.0 - np.exp(-hours)) + rng.normal(0.0, 0.5, time_s.size)
    lag_signal = 30.0 * (1.0 - np.exp(-hours / 0.5))  # °C, a lagged temperature
    predicted_before = measured - 0.3 * (lag_signal - lag_signal.mean())
    predicted_after = measured - rng.normal(0.0, 0.5, time_s.size)
    before, after = accuracy(measured, predicted_before), accuracy(measured, predicted_after)

    step1 = StepResult(
        number=1,
        effect="thermal_lag",
        params={"tau_s": 1800.0},
        before=before,
        after=after,
        candidates=(
            _candidate(
                "thermal_lag",
                {"tau_s": 1800.0},
                after.rmse_um,
                before.rmse_um,
                True,
                "all rules passed",
            ),
            _candidate(
                "speed_direct", {}, before.rmse_um * 0.95, before.rmse_um, False, EVIL_REASON
            ),
        ),
        predicted_before_um=predicted_before,
        predicted_after_um=predicted_after,
        signal=lag_signal,
        signal_label="T1 lagged (°C)",
    )
    step2 = StepResult(
        number=2,
        effect="none",
        params={},
        before=after,
        after=after,
        candidates=(
            _candidate(
                "drift",
                {"per_h": 1},
                after.rmse_um * 0.99,
                after.rmse_um,
                False,
                "only 1/3 folds improved",
            ),
        ),
        predicted_before_um=predicted_after,
        predicted_after_um=predicted_after,
    )
    return AnalysisResult(
        model=MODEL,
        target="error_um",
        sensors=("T1", "T3"),
        validation="leave-one-run-out (3 folds)",
        reference={"kind": "run_start", "rows": 5},
        rules={"min_gain_pct": 5.0, "max_p": 0.01},
        before=before,
        after=after,
        steps=(step1, step2),
        time_s=time_s,
        run=run,
        measured_um=measured,
        predicted_before_um=predicted_before,
        predicted_after_um=predicted_after,
        source="data/spindle.csv",
        data_fingerprint="sha256:abc123",
        skipped_rows="4 rows with an empty cell",
        stored_model={"name": "spindle-A", "version": 3},
    )


def _nothing_missing_result() -> AnalysisResult:
    """One run, one step that adds nothing."""
    run, time_s = _runs(["only-run"], 200)
    measured = np.sin(time_s / 3600.0) * 5.0
    predicted = measured - 0.2 * np.cos(time_s / 600.0)
    acc = accuracy(measured, predicted)
    step = StepResult(
        number=1,
        effect="none",
        params={},
        before=acc,
        after=acc,
        candidates=(
            _candidate(
                "ambient",
                {"sensor": "ambient_C"},
                acc.rmse_um * 1.01,
                acc.rmse_um,
                False,
                "worse held out",
            ),
            _candidate(
                "unsensed_heat",
                {"tau_s": 600.0},
                acc.rmse_um * 0.99,
                acc.rmse_um,
                False,
                "p too large",
            ),
        ),
        predicted_before_um=predicted,
        predicted_after_um=predicted,
    )
    return one_step_result(
        step, time_s, run, measured, (predicted, predicted), model="linear_T2", sensors=("T2",)
    )


def one_step_result(
    step: StepResult,
    time_s: np.ndarray,
    run: np.ndarray,
    measured_um: np.ndarray,
    predicted_um: tuple[np.ndarray, np.ndarray],
    **fields: Any,
) -> AnalysisResult:
    """A leave-one-run-out result of the one ``step`` (predictions before and after it);
    ``fields`` give or override the rest (model, sensors, rules, tolerance …)."""
    values: dict[str, Any] = {
        "target": "error_um",
        "validation": "leave-one-run-out",
        "reference": {},
        "rules": {"max_p": 0.01},
    }
    return AnalysisResult(
        before=step.before,
        after=step.after,
        steps=(step,),
        time_s=time_s,
        run=run,
        measured_um=measured_um,
        predicted_before_um=predicted_um[0],
        predicted_after_um=predicted_um[1],
        **(values | fields),
    )


def _images(index: Path) -> dict[str, np.ndarray]:
    """Every <img src> of the page, checked to be a real PNG and read back."""
    sources = re.findall(r'<img src="([^"]+)"', index.read_text(encoding="utf-8"))
    images = {}
    for src in sources:
        path = index.parent / src
        assert path.is_file(), src
        assert path.read_bytes().startswith(b"\x89PNG"), src
        image = imread(path)
        assert image.ndim == 3 and image.shape[2] in (3, 4), src
        assert float(image[..., :3].std()) > 0.01, f"{src} is blank"
        images[src] = image
    return images


def test_report_with_one_added_effect(tmp_path: Path) -> None:
    result = _lag_result(["run-B", "run-A"])
    index = write_report(result, tmp_path / "report")
    assert index == tmp_path / "report" / "index.html"
    page = index.read_text(encoding="utf-8")

    assert MODEL in page
    for effect in ("thermal_lag", "speed_direct", "drift"):
        assert effect in page
    assert f"{result.before.rmse_um:.2f}" in page
    assert f"{result.after.rmse_um:.2f}" in page
    assert f"Held-out RMSE {result.before.rmse_um:.2f} µm → {result.after.rmse_um:.2f} µm" in page
    assert "by adding thermal_lag (τ = 30 min); tolerance 2.50 µm: met." in page
    assert "1.23e-05" in page and "3/3" in page
    assert page.count('class="chosen"') == 1
    # Runs are listed in order of first appearance, not sorted.
    assert page.index("run-B (300 rows)") < page.index("run-A (300 rows)")
    assert "sha256:abc123" in page and "spindle-A" in page and "max_p: 0.01" in page

    # A reason from the data must not inject markup.
    assert "gain &lt;b&gt;&amp; too small" in page
    assert "<b>&" not in page

    images = _images(index)
    assert set(images) == {
        "residual_runs.png",
        "measured_vs_predicted.png",
        "step1_signal.png",
        "candidates.png",
    }
    height, width = images["residual_runs.png"].shape[:2]
    assert 900 <= width <= 1100 and 400 <= height <= 700  # 10 in wide, two runs stacked
    height, width = images["step1_signal.png"].shape[:2]
    assert (height, width) == (500, 800)
    assert not (index.parent / "step2_signal.png").exists()


def test_report_when_nothing_is_missing(tmp_path: Path) -> None:
    result = _nothing_missing_result()
    index = write_report(result, tmp_path)
    page = index.read_text(encoding="utf-8")

    assert "linear_T2" in page
    assert "No effect is missing: no candidate passed the rules (none)." in page
    assert "Step 1: nothing added" in page
    assert "ambient" in page and "unsensed_heat" in page and "τ = 10 min" in page
    assert f"{result.before.rmse_um:.2f}" in page
    assert 'class="chosen"' not in page

    images = _images(index)
    assert set(images) == {"residual_runs.png", "measured_vs_predicted.png", "candidates.png"}
    assert not list(tmp_path.glob("step*_signal.png"))


def test_many_runs_are_laid_out_in_a_grid(tmp_path: Path) -> None:
    result = _lag_result([f"r{i:02d}" for i in range(13)], n_per_run=20)
    index = write_report(result, tmp_path)
    height, width = _images(index)["residual_runs.png"].shape[:2]
    # One column of 13 runs would be over 2400 px tall; a 4 × 4 grid is not.
    assert height < 1200 and width > 1100
