"""The measured-run CSV format both independent generators write (what ``load_runs`` reads)."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd


def write_runs_csv(frame: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write ``frame`` as a measured-run CSV (two decimals, LF, UTF-8); its path."""
    out = Path(path)
    frame.to_csv(out, index=False, float_format="%.2f", lineterminator="\n", encoding="utf-8")
    return out
