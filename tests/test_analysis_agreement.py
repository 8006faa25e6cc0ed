"""The terminal table, the HTML report and the JSON of ``analyze`` show the same figures.

Each output is parsed back (the text by its columns, the page with
:mod:`html.parser`, the JSON with :mod:`json`) and every figure is compared:
held-out RMSEs, both gains, p-values, time constants, the headline, the per-run
table and the next step. Run on a simulated recording and on data/fl_thermal.csv,
through the real command line.
"""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from models.analysis import render as analysis_render
from models.analysis.format import P_FLOOR, p_text
from models.analysis.result import AnalysisResult, CandidateResult, StepResult
from models.fit.metrics import accuracy
from simulator.params import load_params
from simulator.programs import load_programs
from simulator.record import DEFAULT_PROGRAMS, record, write_recording
from tests.cli import ROOT, gateway_in_process
from tests.test_analysis_report import one_step_result

FL_THERMAL = ROOT / "data" / "fl_thermal.csv"
CANDIDATE_COLUMNS = (
    "mark",
    "effect",
    "parameters",
    "rmse",
    "change",
    "shape",
    "folds",
    "p",
    "believed",
    "reason",
)


# --------------------------------------------------------------------------- parsers


def number(cell: str) -> float:
    return float(cell.replace("−", "-"))


def text_rounds(stdout: str) -> list[list[dict[str, str]]]:
    """Candidate rows of every round of the terminal table, as column → cell."""
    rounds: list[list[dict[str, str]]] = []
    lines = stdout.splitlines()
    for i, line in enumerate(lines):
        if not re.match(r"round \d+: held-out RMSE before", line):
            continue
        rows = []
        for row in lines[i + 2 :]:  # skip the header
            if row.lstrip().startswith("→"):
                break
            cells = re.split(r"\s{2,}", row.strip())
            if cells[0] != "*":
                cells = ["", *cells]
            rows.append(dict(zip(CANDIDATE_COLUMNS, cells, strict=True)))
        rounds.append(rows)
    return rounds


def text_table(stdout: str, first_header: str) -> list[list[str]]:
    """The data rows of the text table whose header starts with ``first_header``."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith(first_header))
    rows = []
    for line in lines[start + 1 :]:
        if not line.strip():
            break
        rows.append(re.split(r"\s{2,}", line.strip()))
    return rows


class Page(HTMLParser):
    """Tables (by class) as rows of cell texts, and the text of elements by class."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tables: dict[str, list[list[list[str]]]] = {}
        self.texts: dict[str, str] = {}
        self.chosen_rows = 0
        self._table: str | None = None
        self._row: list[str] | None = None
        self._cell: list[str] | None = None
        self._text_class: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        cls = dict(attrs).get("class")
        if tag == "table":
            self._table = cls or ""
            self.tables.setdefault(self._table, []).append([])
        elif tag == "tr" and self._table is not None:
            self._row = []
            self.chosen_rows += cls == "chosen"
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []
        elif cls in ("summary", "next-step"):
            self._text_class = cls
            self.texts[cls] = ""

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None and self._row is not None:
            self._row.append("".join(self._cell))
            self._cell = None
        elif tag == "tr" and self._row is not None and self._table is not None:
            self.tables[self._table][-1].append(self._row)
            self._row = None
        elif tag == "table":
            self._table = None
        elif tag in ("p", "span"):
            self._text_class = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)
        elif self._text_class is not None:
            self.texts[self._text_class] += data


def parse_page(path: Path) -> Page:
    page = Page()
    page.feed(path.read_text(encoding="utf-8"))
    return page


# --------------------------------------------------------------------------- the check


def assert_agree(stdout: str, page: Page, payload: dict) -> None:
    """Every figure of the three outputs is the same."""
    rounds_json = payload["rounds"]
    rounds_text = text_rounds(stdout)
    rounds_html = page.tables["candidates"]
    assert len(rounds_json) == len(rounds_text) == len(rounds_html) >= 1
    chosen = 0
    for json_round, text_rows, html_rows in zip(rounds_json, rounds_text, rounds_html, strict=True):
        header, *html_rows = html_rows
        assert header == list(analysis_render.CANDIDATE_HEADER[1:])
        html_by_effect = {row[0]: row for row in html_rows}
        text_by_effect = {row["effect"]: row for row in text_rows}
        assert set(html_by_effect) == set(text_by_effect)
        assert set(text_by_effect) == {c["effect"] for c in json_round["candidates"]}
        for cand in json_round["candidates"]:
            text = text_by_effect[cand["effect"]]
            # The page shows the same strings, column for column (it has no mark column).
            assert html_by_effect[cand["effect"]] == [text[c] for c in CANDIDATE_COLUMNS[1:]]
            assert number(text["rmse"]) == pytest.approx(cand["rmse_um"], abs=0.0051)
            assert number(text["change"]) == pytest.approx(-cand["rmse_gain_pct"], abs=0.051)
            assert number(text["shape"]) == pytest.approx(-cand["gain_pct"], abs=0.051)
            assert cand["shape_gain_pct"] == cand["gain_pct"]
            gain = 100 * (1 - cand["rmse_um"] / cand["rmse_before_um"])
            assert cand["rmse_gain_pct"] == pytest.approx(gain, abs=0.05)  # from 4-decimal RMSEs
            assert text["p"] == cand["p_value_text"] != "0"
            assert cand["p_value"] >= P_FLOOR
            if cand["p_value_text"].startswith("<"):
                assert cand["p_value"] == P_FLOOR
            else:
                assert float(text["p"]) == pytest.approx(cand["p_value"], rel=0.006)
            assert text["parameters"] == (cand["params_text"] or "—")
            if "tau_s" in cand["params"]:
                assert cand["tau_min"] == pytest.approx(cand["params"]["tau_s"] / 60)
                assert f"τ = {cand['tau_min']:g} min" in text["parameters"]
            assert text["believed"] == ("yes" if cand["believed"] else "no")
            assert text["reason"] == cand["reason"]
            if text["mark"] == "*":
                chosen += 1
                assert cand["effect"] == json_round["effect"]
                assert cand["rmse_um"] == json_round["rmse_um"]
                assert cand["rmse_gain_pct"] == json_round["rmse_gain_pct"]
    assert chosen == page.chosen_rows == len(payload["steps"])

    # The headline: one sentence, the same everywhere, its figures those of the JSON.
    headline = payload["headline"]
    assert page.texts["summary"] == headline
    assert headline in stdout.splitlines()
    before, after = payload["before"]["rmse_um"], payload["after"]["rmse_um"]
    assert f"{before:.2f} µm" in headline
    assert f"tolerance {payload['tolerance_um']:.2f} µm" in headline
    assert ("not met" in headline) == (not payload["within_tolerance"])
    assert payload["within_tolerance"] == (after <= payload["tolerance_um"])
    if payload["steps"]:
        change = re.search(r"\(([−+]\d+\.\d) %\)", headline)
        assert change is not None, headline
        assert number(change.group(1)) == pytest.approx(-payload["rmse_gain_pct"], abs=0.051)
        assert payload["rmse_gain_pct"] == pytest.approx(100 * (1 - after / before), abs=0.01)
        if len(payload["steps"]) == 1:  # the headline and its step's row are one figure
            step_row = next(r for r in rounds_text[0] if r["mark"] == "*")
            assert step_row["change"] == change.group(1)

    # The accuracy and per-run tables.
    html_accuracy = page.tables["accuracy"][0][1:]
    assert text_table(stdout, "RMSE (µm)") == html_accuracy
    for row, key in zip(html_accuracy, ("before", "after"), strict=True):
        assert number(row[1]) == pytest.approx(payload[key]["rmse_um"], abs=0.0051)
        assert number(row[3]) == pytest.approx(payload[key]["max_abs_um"], abs=0.0051)
    html_runs = page.tables["runs"][0][1:]
    assert text_table(stdout, "run ") == html_runs
    assert [row[0] for row in html_runs] == [r["run"] for r in payload["per_run"]]
    for row, run in zip(html_runs, payload["per_run"], strict=True):
        assert number(row[3]) == pytest.approx(run["rmse_after_um"], abs=0.0051)
        assert number(row[4]) == pytest.approx(run["share_of_error_after_pct"], abs=0.051)
    assert sum(r["share_of_error_after_pct"] for r in payload["per_run"]) == pytest.approx(
        100, abs=0.05
    )

    # The next step.
    assert page.texts["next-step"] == payload["next_step"]["text"]
    assert f"next: {payload['next_step']['text']}" in stdout.splitlines()


def run_analyze(tmp_path: Path, data: Path, *options: str) -> tuple[str, Page, dict]:
    out, report = tmp_path / "out.json", tmp_path / "report"
    done = gateway_in_process(
        "analyze",
        data,
        "--model",
        "mlr",
        "--json",
        out,
        "--report",
        report,
        "--no-progress",
        *options,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout, parse_page(report / "index.html"), json.loads(out.read_text("utf-8"))


def test_outputs_agree_on_a_simulated_recording(tmp_path: Path) -> None:
    data = tmp_path / "sim-thermal_lag.csv"
    runs = record(load_params(), [load_programs()[p] for p in DEFAULT_PROGRAMS], ["thermal_lag"], 1)
    write_recording(data, runs)
    stdout, page, payload = run_analyze(tmp_path, data, "--tolerance-um", "0.3")
    assert payload["effect"] == "thermal_lag"
    assert payload["tolerance_um"] == 0.3
    assert_agree(stdout, page, payload)
    assert payload["next_step"]["actions"][0] == "promote"


def test_outputs_agree_on_fl_thermal(tmp_path: Path) -> None:
    stdout, page, payload = run_analyze(tmp_path, FL_THERMAL, "--target", "ch5_um")
    assert payload["tolerance_um"] == 2.5
    assert_agree(stdout, page, payload)
    # The F-test's tail underflows on 11 000 rows: it reads "< 1e-16", never 0.
    assert "< 1e-16" in [c["p_value_text"] for c in payload["candidates"]]
    first = payload["candidates"][0]
    # The first round's thermal lag: shape gain and held-out RMSE gain are different figures.
    assert first["effect"] == "thermal_lag"
    assert abs(first["rmse_gain_pct"] - first["shape_gain_pct"]) > 1
    assert not payload["within_tolerance"]
    assert payload["next_step"]["actions"][0] == "promote"
    assert len(payload["next_step"]["actions"]) == 2


# --------------------------------------------------------------------------- unit checks


def test_p_values_never_print_as_zero() -> None:
    assert p_text(0.0) == "< 1e-16"
    assert p_text(3e-17) == "< 1e-16"
    assert p_text(1.234e-5) == "1.23e-05"
    assert p_text(float("nan")) == "—"


def _result(
    run_rmse_um: dict[str, float], effect: str = "none", tolerance_um: float = 2.5, **cand
) -> AnalysisResult:
    """Runs whose held-out residual has the given RMSE; one round that adds ``effect``."""
    n = 100
    names = list(run_rmse_um)
    run = np.array([name for name in names for _ in range(n)], dtype=object)
    time_s = np.tile(np.arange(n) * 60.0, len(names))
    signs = np.tile(np.where(np.arange(n) % 2 == 0, 1.0, -1.0), len(names))
    residual = signs * np.repeat([run_rmse_um[name] for name in names], n)
    measured = np.linspace(0.0, 20.0, run.size)
    before_pred = measured - 2 * residual
    after_pred = measured - residual if effect != "none" else before_pred
    before, after = accuracy(measured, before_pred), accuracy(measured, after_pred)
    values = {
        "effect": "thermal_lag",
        "params": {"tau_s": 5400.0},
        "label": "lags",
        "rmse_um": after.rmse_um if effect != "none" else 0.95 * before.rmse_um,
        "gain_pct": 30.0,
        "folds_improved": len(names),
        "folds": len(names),
        "p_value": 0.0,
        "believed": effect != "none",
        "reason": "r",
        "n_terms": 1,
        "rmse_before_um": before.rmse_um,
        "alpha": 0.002,
    } | cand
    step = StepResult(
        1,
        effect,
        {"tau_s": 5400.0} if effect != "none" else {},
        before,
        after,
        (CandidateResult(**values),),
        before_pred,
        after_pred,
    )
    return one_step_result(
        step,
        time_s,
        run,
        measured,
        (before_pred, after_pred),
        model="mlr",
        sensors=("T1",),
        rules={"min_gain_pct": 10.0},
        tolerance_um=tolerance_um,
    )


def actions(result: AnalysisResult) -> list[str]:
    return [step.action for step in result.next_steps]


def test_next_step_follows_its_rule() -> None:
    even = {"a": 1.0, "b": 1.1, "c": 0.9, "d": 1.0}
    # Effect added, within the tolerance: promote only.
    assert actions(_result(even, "thermal_lag")) == ["promote"]
    # Nothing added, within the tolerance: keep the model.
    assert actions(_result(even, believed=False, gain_pct=2.0)) == ["keep"]
    # Above the tolerance, the error spread over four runs, nothing nearly proven: a sensor.
    assert actions(_result(even, "thermal_lag", tolerance_um=0.5)) == ["promote", "add_sensor"]
    # One run of four holds most of the error left: record more cycles like it.
    dominant = {"a": 0.5, "b": 0.5, "c": 3.0, "d": 0.5}
    result = _result(dominant, "thermal_lag", tolerance_um=0.5)
    assert actions(result) == ["promote", "more_data"]
    assert "run c holds" in result.next_step_text
    # Too few runs to prove anything further.
    assert actions(_result({"a": 1.0, "b": 1.0}, tolerance_um=0.5, believed=False)) == ["more_data"]
    # A candidate that lowered both errors enough but failed the fold rule: more data.
    nearly = _result(even, tolerance_um=0.5, believed=False, folds_improved=1)
    assert actions(nearly) == ["more_data"]
    assert "τ = 90 min" in nearly.next_step_text
    # The same candidate with too small a shape gain is no evidence: a sensor.
    assert actions(_result(even, tolerance_um=0.5, believed=False, gain_pct=5.0)) == ["add_sensor"]


def test_a_run_name_cannot_inject_markup(tmp_path: Path) -> None:
    evil = "<script>alert(1)</script>"
    result = _result({evil: 1.0, "b&c": 1.0, "d": 1.0, "e": 1.0}, "thermal_lag")
    page = analysis_render.html_report(result, ())
    assert "<script>" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "b&amp;c" in page
    # The parsed page still shows the name as it is.
    path = tmp_path / "index.html"
    path.write_text(page, encoding="utf-8")
    assert parse_page(path).tables["runs"][0][1][0] == evil
