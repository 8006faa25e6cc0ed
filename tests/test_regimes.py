"""Tests for models.fit.ranking against paper 002 (Miao et al. 2015), Tables 3–6."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from models.fit.ranking import (
    RegimeReport,
    SigmaFileError,
    SigmaRow,
    format_report,
    rank_regimes,
    read_sigma_csv,
    sigma_matrix,
)

TABLE3 = Path(__file__).parent.parent / "data" / "seed002_table3_sigma.csv"
HEADER = "model,model_regime,data,data_regime,sigma_um\n"

# Table 4: (model regime, data regime) -> (MN, SD) in µm.
TABLE4 = {
    ("spectrum", "spectrum"): (3.38, 0.16),
    ("spectrum", "constant"): (2.92, 0.77),
    ("constant", "spectrum"): (5.17, 0.38),
    ("constant", "constant"): (1.75, 0.64),
}
# Tables 5–6, in the paper's printed order: (a, b, CoMN %, CoSD %).
TABLE5 = [
    ("Y1", "Y2", 0.69, 327.0),
    ("Y2", "Y1", -0.68, -76.6),
    ("Y1", "Y3", 0.99, 18.4),
    ("Y3", "Y1", -0.98, -15.5),
    ("Y2", "Y3", 0.30, -72.3),
    ("Y3", "Y2", -0.30, 260.0),
]
TABLE6 = [
    ("Y4", "Y5", 37.2, 240.0),
    ("Y5", "Y4", -27.1, -70.6),
    ("Y4", "Y6", 42.3, 1209.0),
    ("Y6", "Y4", -29.7, -92.4),
    ("Y5", "Y6", 3.7, 285.0),
    ("Y6", "Y5", -3.6, -74.0),
]


@pytest.fixture(scope="module")
def rows() -> list[SigmaRow]:
    return read_sigma_csv(TABLE3)


@pytest.fixture(scope="module")
def report(rows: list[SigmaRow]) -> RegimeReport:
    return rank_regimes(rows)


# --------------------------------------------------------------------------- paper data


def test_reads_table3(rows: list[SigmaRow]) -> None:
    assert len(rows) == 36
    assert rows[0] == SigmaRow("Y1", "spectrum", "K1", "spectrum", 3.12)
    models, data, sigma = sigma_matrix(rows)
    assert models == ["Y1", "Y2", "Y3", "Y4", "Y5", "Y6"]
    assert data == ["K1", "K2", "K3", "K4", "K5", "K6"]
    assert sigma.shape == (6, 6)
    assert not np.isnan(sigma).any()
    assert sigma[5, 3] == pytest.approx(1.55)  # Y6 on K4


def test_table4_blocks(report: RegimeReport) -> None:
    got = {(b["model_regime"], b["data_regime"]): b for b in report.blocks}
    assert set(got) == set(TABLE4)
    for key, (mn, sd) in TABLE4.items():
        assert got[key]["n"] == 9
        assert got[key]["mn_um"] == pytest.approx(mn, abs=0.01), key
        assert got[key]["sd_um"] == pytest.approx(sd, abs=0.01), key


def test_tables5_6_pairwise(report: RegimeReport) -> None:
    expected = TABLE5 + TABLE6
    # The paper's order: for i < j, (i, j) then (j, i).
    assert [(p["a"], p["b"]) for p in report.pairwise] == [(a, b) for a, b, _, _ in expected]
    for p, (a, b, comn, cosd) in zip(report.pairwise, expected, strict=True):
        assert p["comn_pct"] == pytest.approx(comn, abs=0.1), (a, b)
        assert p["cosd_pct"] == pytest.approx(cosd, rel=0.01), (a, b)
    assert {p["regime"] for p in report.pairwise[:6]} == {"spectrum"}
    assert {p["regime"] for p in report.pairwise[6:]} == {"constant"}


def test_models_own_regime(report: RegimeReport) -> None:
    assert report.models["Y1"]["regime"] == "spectrum"
    assert report.models["Y1"]["n_runs"] == 3
    # Y1 over K1–K3: (3.12 + 3.63 + 3.46) / 3 = 3.4033…
    assert report.models["Y1"]["mn_um"] == pytest.approx(10.21 / 3)
    # Y6 over K4–K6: (1.55 + 1.59 + 1.42) / 3 = 1.52
    assert report.models["Y6"]["mn_um"] == pytest.approx(1.52)
    assert report.models["Y2"]["sd_um"] == pytest.approx(0.0497, abs=5e-4)


def test_best_per_regime(report: RegimeReport) -> None:
    assert report.best == {"spectrum": "Y2", "constant": "Y6"}
    assert report.tolerance_pct == 1.0
    assert "Y1, Y2, Y3 within 1 %" in report.decisions["spectrum"]
    assert "lowest SD wins: Y2" in report.decisions["spectrum"]
    assert "accuracy decides: Y6" in report.decisions["constant"]


def test_tolerance_changes_spectrum_choice(rows: list[SigmaRow]) -> None:
    # Spectrum MNs: Y1 3.4033, Y2 3.38, Y3 3.37 (the lowest). Gaps to Y3:
    # Y2 (3.38 − 3.37)/3.37 = 0.297 %, Y1 0.99 %; both ≥ 0.1 %, so Y3 is the only
    # candidate and accuracy alone picks it. Constant: Y5 is 3.7 % behind Y6 → Y6.
    rep = rank_regimes(rows, tolerance_pct=0.1)
    assert rep.best == {"spectrum": "Y3", "constant": "Y6"}
    assert rep.tolerance_pct == 0.1
    # A wide tolerance lets SD decide in the constant regime too: Y6 still has the
    # lowest SD (0.073 µm), so the choice is unchanged.
    assert rank_regimes(rows, tolerance_pct=50.0).best == {"spectrum": "Y2", "constant": "Y6"}


def test_as_json_contract(report: RegimeReport) -> None:
    js = report.as_json()
    assert set(js) == {"blocks", "models", "pairwise", "best", "tolerance_pct", "decisions"}
    assert set(js["blocks"][0]) == {"model_regime", "data_regime", "mn_um", "sd_um"}
    assert set(js["models"]["Y1"]) == {"regime", "mn_um", "sd_um"}
    assert set(js["pairwise"][0]) == {"a", "b", "comn_pct", "cosd_pct"}
    assert type(js["blocks"][0]["mn_um"]) is float
    assert type(js["pairwise"][0]["cosd_pct"]) is float
    assert js["best"] == {"spectrum": "Y2", "constant": "Y6"}
    # Unrounded: the spectrum→spectrum MN is 30.46 / 9, not 3.38.
    assert js["blocks"][0]["mn_um"] == pytest.approx(30.46 / 9, abs=1e-12)
    assert json.loads(json.dumps(js)) == js


def test_format_report(report: RegimeReport) -> None:
    text = format_report(report)
    assert "spectrum      constant          2.92    0.76" in text
    assert "Y1–Y2" in text and "+326.9" in text
    assert "spectrum: Y2" in text and "constant: Y6" in text
    assert report.decisions["spectrum"] in text


# --------------------------------------------------------------------------- hand example


def test_hand_example() -> None:
    # One regime "c", runs R1, R2; models A and B.
    #   A: σ = 1, 3 → MN_A = 2, SD_A = sqrt(((1−2)² + (3−2)²)/2) = 1
    #   B: σ = 2, 6 → MN_B = 4, SD_B = sqrt(((2−4)² + (6−4)²)/2) = 2
    # Block (c, c): 1, 3, 2, 6 → MN = 3, SD = sqrt((4 + 0 + 1 + 9)/4) = sqrt(3.5)
    # CoMN_AB = (2 − 4)/4·100 = −50 %, CoMN_BA = (4 − 2)/2·100 = +100 %
    # CoSD_AB = (1 − 2)/2·100 = −50 %, CoSD_BA = (2 − 1)/1·100 = +100 %
    # A's MN is 50 % below B's → outside 1 % → A wins on accuracy.
    rows = [
        SigmaRow("A", "c", "R1", "c", 1.0),
        SigmaRow("A", "c", "R2", "c", 3.0),
        SigmaRow("B", "c", "R1", "c", 2.0),
        SigmaRow("B", "c", "R2", "c", 6.0),
    ]
    rep = rank_regimes(rows)
    assert rep.models["A"]["mn_um"] == pytest.approx(2.0)
    assert rep.models["A"]["sd_um"] == pytest.approx(1.0)
    assert rep.models["B"]["mn_um"] == pytest.approx(4.0)
    assert rep.models["B"]["sd_um"] == pytest.approx(2.0)
    (block,) = rep.blocks
    assert block["mn_um"] == pytest.approx(3.0)
    assert block["sd_um"] == pytest.approx(math.sqrt(3.5))
    assert [(p["a"], p["b"]) for p in rep.pairwise] == [("A", "B"), ("B", "A")]
    assert rep.pairwise[0]["comn_pct"] == pytest.approx(-50.0)
    assert rep.pairwise[1]["comn_pct"] == pytest.approx(100.0)
    assert rep.pairwise[0]["cosd_pct"] == pytest.approx(-50.0)
    assert rep.pairwise[1]["cosd_pct"] == pytest.approx(100.0)
    assert rep.best == {"c": "A"}
    # With a 200 % tolerance B (gap 100 %) becomes a candidate, but A still has the
    # lower SD (1 < 2), so A stays best — now decided by robustness.
    wide = rank_regimes(rows, tolerance_pct=200.0)
    assert wide.best == {"c": "A"}
    assert "lowest SD wins: A" in wide.decisions["c"]


def test_tolerance_lets_sd_decide() -> None:
    # A: σ 2.0, 2.0 → MN 2.00, SD 0 ; B: σ 1.98, 2.00 → MN 1.99, SD 0.01.
    # Gap of A to B: (2 − 1.99)/1.99 = 0.50 % → within 1 % → lowest SD → A.
    # With 0.1 % tolerance A is out → B (lowest MN).
    rows = [
        SigmaRow("A", "c", "R1", "c", 2.0),
        SigmaRow("A", "c", "R2", "c", 2.0),
        SigmaRow("B", "c", "R1", "c", 1.98),
        SigmaRow("B", "c", "R2", "c", 2.0),
    ]
    assert rank_regimes(rows).best == {"c": "A"}
    assert rank_regimes(rows, tolerance_pct=0.1).best == {"c": "B"}
    # CoSD against a zero SD is undefined: inf in the report, None in JSON.
    rep = rank_regimes(rows)
    ba = next(p for p in rep.pairwise if (p["a"], p["b"]) == ("B", "A"))
    assert math.isinf(ba["cosd_pct"])
    assert rep.as_json()["pairwise"][1]["cosd_pct"] is None


def test_sigma_matrix_missing_is_nan() -> None:
    rows = [
        SigmaRow("A", "c", "R1", "c", 1.0),
        SigmaRow("B", "c", "R2", "c", 2.0),
    ]
    models, data, sigma = sigma_matrix(rows)
    assert models == ["A", "B"] and data == ["R1", "R2"]
    assert sigma[0, 0] == 1.0 and sigma[1, 1] == 2.0
    assert np.isnan(sigma[0, 1]) and np.isnan(sigma[1, 0])


# --------------------------------------------------------------------------- refusals


def test_empty_rows_refused() -> None:
    with pytest.raises(ValueError, match="no σ rows"):
        rank_regimes([])


def test_model_without_own_regime_data_refused() -> None:
    rows = [
        SigmaRow("A", "c", "R1", "c", 1.0),
        SigmaRow("S", "s", "R1", "c", 2.0),  # regime "s" has no "s" runs
    ]
    with pytest.raises(ValueError, match=r"model S .*no σ on any run of its own regime"):
        rank_regimes(rows)


def test_bad_tolerance_refused() -> None:
    rows = [SigmaRow("A", "c", "R1", "c", 1.0)]
    with pytest.raises(ValueError, match="tolerance_pct"):
        rank_regimes(rows, tolerance_pct=-1.0)


def test_conflicting_rows_in_code_refused() -> None:
    rows = [SigmaRow("A", "c", "R1", "c", 1.0), SigmaRow("A", "c", "R1", "c", 2.0)]
    with pytest.raises(ValueError, match="duplicate"):
        sigma_matrix(rows)


# --------------------------------------------------------------------------- bad files


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_empty_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "empty.csv", "")
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}:1: ")
    assert "empty.csv" in msg and "empty file" in msg


def test_header_only(tmp_path: Path) -> None:
    path = _write(tmp_path, "header.csv", HEADER)
    with pytest.raises(SigmaFileError, match=r"header\.csv:1: .*found none"):
        read_sigma_csv(path)


def test_missing_column(tmp_path: Path) -> None:
    path = _write(tmp_path, "nocol.csv", "model,model_regime,data,sigma_um\nY1,s,K1,3.1\n")
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert "nocol.csv:1: " in msg
    assert "column 'data_regime'" in msg
    assert exc.value.line == 1 and exc.value.column == "data_regime"


def test_text_in_sigma(tmp_path: Path) -> None:
    path = _write(tmp_path, "text.csv", HEADER + "Y1,s,K1,s,3.1\nY1,s,K2,s,abc\n")
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert "text.csv:3: " in msg
    assert "column 'sigma_um'" in msg
    assert "'abc'" in msg


@pytest.mark.parametrize(("value", "what"), [("", "empty"), ("-0.5", "≥ 0"), ("nan", "finite")])
def test_bad_sigma_values(tmp_path: Path, value: str, what: str) -> None:
    path = _write(tmp_path, "bad.csv", HEADER + f"Y1,s,K1,s,{value}\n")
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert "bad.csv:2: column 'sigma_um'" in msg
    assert what in msg


def test_conflicting_model_regime(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        "conflict.csv",
        HEADER + "Y1,spectrum,K1,spectrum,3.1\nY1,constant,K2,spectrum,3.2\n",
    )
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert "conflict.csv:3: " in msg
    assert "column 'model_regime'" in msg
    assert "'spectrum'" in msg and "'constant'" in msg and "line 2" in msg


def test_conflicting_data_regime(tmp_path: Path) -> None:
    path = _write(
        tmp_path, "dconf.csv", HEADER + "Y1,spectrum,K1,spectrum,3.1\nY2,spectrum,K1,constant,3.2\n"
    )
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert "dconf.csv:3: " in msg
    assert "column 'data_regime'" in msg


def test_duplicate_pair(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        "dup.csv",
        HEADER + "Y1,s,K1,s,3.1\nY1,s,K2,s,3.2\nY1,s,K1,s,3.3\n",
    )
    with pytest.raises(SigmaFileError) as exc:
        read_sigma_csv(path)
    msg = str(exc.value)
    assert "dup.csv:4: " in msg
    assert "column 'data'" in msg
    assert "(Y1, K1)" in msg and "line 2" in msg


def test_wrong_field_count(tmp_path: Path) -> None:
    path = _write(tmp_path, "short.csv", HEADER + "Y1,s,K1,s\n")
    with pytest.raises(SigmaFileError, match=r"short\.csv:2: expected 5 fields"):
        read_sigma_csv(path)
