"""The measured-run CSV format both independent generators write (what ``load_runs`` reads)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

#: A generator's ``generate_runs(effect=, seed=, programs=)``.
Generate = Callable[..., pd.DataFrame]


def write_runs_csv(frame: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write ``frame`` as a measured-run CSV (two decimals, LF, UTF-8); its path."""
    out = Path(path)
    frame.to_csv(out, index=False, float_format="%.2f", lineterminator="\n", encoding="utf-8")
    return out


def runs_csv_writer(generate: Generate) -> Callable[..., Path]:
    """The generator's ``write_csv(path, effect, seed, programs)``: its runs as a CSV file."""

    def write_csv(
        path: str | os.PathLike[str],
        effect: str = "none",
        seed: int = 0,
        programs: Sequence[str] | None = None,
    ) -> Path:
        """Write the measured-run CSV and return its path."""
        return write_runs_csv(generate(effect=effect, seed=seed, programs=programs), path)

    return write_csv
