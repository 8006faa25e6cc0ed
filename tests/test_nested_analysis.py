"""The nested residual analysis (``analyze --nested``, ``--model auto``) on data the
independent shaft generator wrote (``tests/independent_shaft.py``: four of its runs, two
at rest and two opening at speed, logging gaps, clock-of-day time).

The property that makes the figure honest is checked directly: whatever the held-out
run's measured error is, its fold's choices and prediction do not change.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.analysis import augmented
from models.analysis.nested import AUTO_BASES, analyse_bases, nested_analysis
from models.analysis.search import Folds, analyze
from models.catalogue import METHOD_NAMES
from models.data.dataset import load_runs
from models.data.features import prepare
from tests import independent_shaft

ROOT = Path(__file__).resolve().parents[1]


#: Four of the shaft's five programmes, two opening at rest and two at speed: every
#: nested test analyses each base once per outer and inner fold.
PROGRAMS = ("rest-const", "speed-steps", "rest-spectrum", "speed-duty")


@pytest.fixture(scope="module")
def shaft_lag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("shaft")
    path = folder / "shaft-thermal_lag-1.csv"
    return independent_shaft.write_csv(path, "thermal_lag", 1, programs=PROGRAMS)


def test_auto_bases_are_every_method_plainest_first() -> None:
    assert sorted(AUTO_BASES) == sorted(METHOD_NAMES)
    assert AUTO_BASES[0] == "mlr"


def test_heldout_run_never_steers_its_own_fold(shaft_lag: Path) -> None:
    prepared = prepare(load_runs(shaft_lag))
    methods = ("mlr", "lag-ridge")
    first = nested_analysis(prepared, methods)
    # A probe that slipped by 40 µm, growing over the held-out run: a large change of the
    # scored data only.
    folds = Folds.of(prepared)
    k = 2
    rows = folds.rows[k]
    changed = prepared.error_um.copy()
    changed[rows] += np.linspace(0.0, 40.0, rows.size)
    second = nested_analysis(replace(prepared, error_um=changed), methods)
    run_before, run_after = first.runs[k], second.runs[k]
    assert run_after.chosen == run_before.chosen
    assert run_after.inner_rmse_um == run_before.inner_rmse_um
    assert run_after.effects == run_before.effects
    start = sum(r.rows for r in first.runs[:k])
    span = slice(start, start + rows.size)
    np.testing.assert_allclose(
        second.predicted_um["chosen"][span], first.predicted_um["chosen"][span]
    )
    # ... and the change did reach the folds that train on that run, and the score.
    assert any(
        second.runs[j].inner_rmse_um != first.runs[j].inner_rmse_um for j in range(4) if j != k
    )
    assert second.runs[k].rmse_um["chosen"] > first.runs[k].rmse_um["chosen"] + 5.0


def test_fold_prediction_is_the_analysis_of_the_training_runs_alone(shaft_lag: Path) -> None:
    """Fold k's prediction equals analysing the other runs as a file of their own would,
    fitting the augmented model there and predicting run k; the base the fold keeps is
    the one whose analysis there scored lowest."""
    prepared = prepare(load_runs(shaft_lag))
    nested = nested_analysis(prepared, ("mlr", "pca-quadratic"))
    folds = Folds.of(prepared)
    start = 0
    for k, run in enumerate(nested.runs):
        train = np.ones(prepared.data.n_samples, bool)
        train[folds.rows[k]] = False
        scores = {}
        for method in ("mlr", "pca-quadratic"):
            result, accepted, analysis = analyze(prepared, method, fit_rows=train)
            scores[method] = result.after.rmse_um
            predicted = augmented.augmented_prediction(analysis, accepted)[folds.rows[k]]
            span = slice(start, start + folds.rows[k].size)
            np.testing.assert_allclose(nested.predicted_um[method][span], predicted)
        assert run.chosen == min(scores, key=scores.get)
        assert run.inner_rmse_um == pytest.approx(scores)
        start += folds.rows[k].size
    pooled = np.sqrt(
        sum(r.rmse_um["chosen"] ** 2 * r.rows for r in nested.runs)
        / sum(r.rows for r in nested.runs)
    )
    assert nested.accuracy().rmse_um == pytest.approx(pooled)


def test_analyse_bases_keeps_the_lowest_and_ties_go_to_the_earlier(shaft_lag: Path) -> None:
    prepared = prepare(load_runs(shaft_lag))
    chosen, analyses = analyse_bases(prepared, ("mlr", "pca-quadratic"))
    low = min(a.heldout_rmse_um for a in analyses.values())
    assert analyses[chosen].heldout_rmse_um == low
    chosen_twice, _ = analyse_bases(prepared, ("mlr", "mlr"))
    assert chosen_twice == "mlr"


def test_too_few_runs_is_a_clear_error(tmp_path: Path) -> None:
    path = independent_shaft.write_csv(
        tmp_path / "two.csv", "none", 3, programs=("rest-const", "speed-steps")
    )
    with pytest.raises(ValueError, match="at least 3 runs"):
        nested_analysis(prepare(load_runs(path)), ("mlr",))


def test_cli_auto_and_nested_json(shaft_lag: Path, tmp_path: Path) -> None:
    out = tmp_path / "analysis.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "gateway",
            "analyze",
            str(shaft_lag),
            "--model",
            "auto",
            "--nested",
            "--json",
            str(out),
            "--store",
            str(tmp_path / "store"),
            "--report",
            str(tmp_path / "report"),
            "--no-progress",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    document = json.loads(out.read_text(encoding="utf-8"))
    choice = document["base_choice"]
    assert choice["models"] == list(AUTO_BASES)
    scores = choice["heldout_rmse_um"]
    assert choice["kept"] == min(AUTO_BASES, key=lambda m: (scores[m], AUTO_BASES.index(m)))
    assert document["model"] == choice["kept"]
    assert document["after"]["rmse_um"] == pytest.approx(scores[choice["kept"]], abs=1e-4)
    stored = augmented.load(document["stored_model"]["path"])  # the kept base is what is saved
    assert stored["base"]["method"] == choice["kept"]
    assert stored["model_id"].startswith(f"{choice['kept']}-error_um-")
    nested = document["nested"]
    assert [r["run"] for r in nested["runs"]] == list(dict.fromkeys(load_runs(shaft_lag).run_ids))
    for run in nested["runs"]:
        inner = run["inner_rmse_um"]
        assert run["chosen_model"] == min(AUTO_BASES, key=lambda m: (inner[m], AUTO_BASES.index(m)))
        assert run["rmse_um"]["chosen"] == run["rmse_um"][run["chosen_model"]]
    # One results object: the terminal, the HTML report and the JSON give the same figures.
    headline = f"nested held-out RMSE {nested['heldout']['rmse_um']:.2f} µm"
    page = (tmp_path / "report" / "index.html").read_text(encoding="utf-8")
    assert headline in done.stdout and headline in page
    for run in nested["runs"]:
        cells = f"<td>{run['run']}</td><td>{run['chosen_model']}</td>"
        assert cells + f'<td class="num">{run["rmse_um"]["chosen"]:.2f}</td>' in page
    kept_line = f"kept {choice['kept']}, its figures optimistic by this choice"
    assert kept_line in done.stdout and kept_line in page
    # The nested figure is on data no choice saw: here it is above the kept model's own.
    assert nested["heldout"]["rmse_um"] > document["after"]["rmse_um"]
