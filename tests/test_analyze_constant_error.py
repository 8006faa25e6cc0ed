"""``analyze`` on an error column that never changes within a run: one clear line, exit 2.

Such a column (a probe channel left unplugged, the wrong ``--target``) has nothing to
explain; the analysis used to divide 0 by 0 and leak numpy's RuntimeWarning with a
source line, then report a model that "meets the tolerance".
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.cli import gateway
from tests.synthetic import write_runs_csv


def with_error(source: Path, target: Path, value_of_run: dict[str, str]) -> Path:
    """``source`` with its error column (the last) set per run."""
    lines = source.read_text(encoding="utf-8").splitlines()
    rows = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        rows.append(",".join([*cells[:-1], value_of_run.get(cells[0], "0")]))
    target.write_text("\n".join(rows) + "\n", encoding="utf-8")
    return target


@pytest.mark.parametrize(
    "value_of_run",
    [{}, {"R1": "1.5", "R2": "-2", "R3": "0.25", "R4": "3"}],
    ids=["zero everywhere", "one value per run"],
)
def test_a_constant_error_column_is_refused_in_one_line(
    tmp_path: Path, value_of_run: dict[str, str]
) -> None:
    source = write_runs_csv(tmp_path / "runs.csv", seed=1)
    path = with_error(source, tmp_path / "constant.csv", value_of_run)
    result = gateway("analyze", path, "--no-progress")
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines() == [
        f"error: {path}: column 'error_um' does not change within any run: there is no "
        "thermal error to analyse (is it the measured error, see --target?)"
    ]
    assert "Warning" not in result.stdout + result.stderr
