"""Choose the spindle-speed regime and the model to compensate with, from σ tables.

Source: Miao, Lü, Miao, Dang (2015), "Selection of optimum spindle speed to thermal
error compensation of machine tools", §5–6 (paper 002). Runs K1–K3 use a speed
*spectrum* (variable speed), K4–K6 a *constant* speed; model Yi is fitted on run Ki.
σ_ij is the standard deviation of model Yi's residuals on run Kj (Table 3).

Absolute evaluation (Table 4), for each block (model regime, data regime) of
σ values (3 × 3 = 9 in the paper)::

    MN = (1/n) Σ σ                      (mean)
    SD = sqrt((1/n) Σ (σ − MN)²)         (population standard deviation, ddof = 0)

Relative evaluation (eq. 7–8, Tables 5–6): for each model i, MN_i and SD_i are the
mean and population SD of σ_i· over the runs of the model's OWN regime (Y1: K1–K3,
Y4: K4–K6); for two models i ≠ j of the same regime::

    CoMN_ij = (MN_i − MN_j) / MN_j · 100 %
    CoSD_ij = (SD_i − SD_j) / SD_j · 100 %

Decision (accuracy first, robustness second): MN* is the lowest MN of the regime;
the candidates are the models with (MN_i − MN*) / MN* · 100 < tolerance_pct (plus
any model whose MN equals MN*); the best model is the candidate with the lowest SD,
ties broken by the lowest MN, then by name. On the paper's data this gives Y2 for
the spectrum regime (all three MNs within 1 %, Y2 has SD 0.050 µm) and Y6 for the
constant regime (Y6's MN 1.520 µm is 3.7 % better than the next, Y5).

Nothing is rounded in the computation; only :func:`format_report` rounds.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "COLUMNS",
    "RegimeReport",
    "SigmaFileError",
    "SigmaRow",
    "format_report",
    "rank_regimes",
    "read_sigma_csv",
    "sigma_matrix",
]

#: Required CSV columns (long format of paper 002, Table 3).
COLUMNS: tuple[str, ...] = ("model", "model_regime", "data", "data_regime", "sigma_um")


@dataclass(frozen=True)
class SigmaRow:
    """One cell of Table 3: σ (µm) of model ``model``'s residuals on run ``data``."""

    model: str
    model_regime: str
    data: str
    data_regime: str
    sigma_um: float


class SigmaFileError(ValueError):
    """A σ CSV file is malformed.

    The message reads ``FILE:LINE: column 'X': what was expected, what was found``
    (``column 'X': `` is left out when no single column is at fault). Line numbers
    are 1-based file lines; the header is line 1.
    """

    def __init__(self, path: str | Path, line: int, message: str, column: str | None = None):
        self.path = str(path)
        self.line = line
        self.column = column
        where = f"column {column!r}: " if column is not None else ""
        super().__init__(f"{self.path}:{line}: {where}{message}")


# --------------------------------------------------------------------------- reading


def read_sigma_csv(path: str | Path) -> list[SigmaRow]:
    """Read a long-format σ table (header ``model,model_regime,data,data_regime,sigma_um``).

    Extra columns are ignored; blank lines are skipped. Raises :class:`SigmaFileError`
    for an empty file, a missing column (line 1), a row with the wrong number of
    fields, an empty name, an empty / non-numeric / negative / non-finite σ, a model
    listed under two model regimes, a run listed under two data regimes, and a
    duplicate (model, data) pair.
    """
    path = Path(path)
    rows: list[SigmaRow] = []
    seen = _Seen()
    header: list[str] | None = None
    header_line = 1
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        for record in reader:
            if not record or all(not f.strip() for f in record):
                continue  # blank lines, before the header too
            if header is None:
                header, header_line = _read_header(path, reader.line_num, record), reader.line_num
                continue
            rows.append(_read_row(path, reader.line_num, header, record, seen))
    if header is None:
        raise SigmaFileError(
            path, 1, f"expected a header with columns {', '.join(COLUMNS)}, found an empty file"
        )
    if not rows:
        raise SigmaFileError(
            path, header_line, "expected at least one data row after the header, found none"
        )
    return rows


@dataclass
class _Seen:
    """Where each model's regime, each run's regime and each (model, data) pair came first."""

    model_regime: dict[str, tuple[str, int]] = field(default_factory=dict)
    data_regime: dict[str, tuple[str, int]] = field(default_factory=dict)
    pair: dict[tuple[str, str], int] = field(default_factory=dict)


def _read_header(path: Path, line: int, record: list[str]) -> list[str]:
    header = [f.strip() for f in record]
    for col in COLUMNS:
        if col not in header:
            raise SigmaFileError(
                path,
                line,
                f"expected a header with columns {', '.join(COLUMNS)}, found {','.join(header)!r}",
                column=col,
            )
    return header


def _read_row(path: Path, line: int, header: list[str], record: list[str], seen: _Seen) -> SigmaRow:
    """One data row, checked against the header and the rows before it."""
    if len(record) != len(header):
        raise SigmaFileError(
            path, line, f"expected {len(header)} fields as in the header, found {len(record)}"
        )
    values = {col: record[header.index(col)].strip() for col in COLUMNS}
    for col in ("model", "model_regime", "data", "data_regime"):
        if not values[col]:
            raise SigmaFileError(path, line, "expected a name, found an empty field", col)
    sigma = _parse_sigma(path, line, values["sigma_um"])
    model, data = values["model"], values["data"]
    _check_same(
        path, line, "model_regime", "model", model, values["model_regime"], seen.model_regime
    )
    _check_same(path, line, "data_regime", "run", data, values["data_regime"], seen.data_regime)
    if (model, data) in seen.pair:
        raise SigmaFileError(
            path,
            line,
            f"expected one σ per (model, data) pair, found ({model}, {data}) again "
            f"(first on line {seen.pair[(model, data)]})",
            column="data",
        )
    seen.pair[(model, data)] = line
    return SigmaRow(model, values["model_regime"], data, values["data_regime"], sigma)


def _parse_sigma(path: Path, line: int, text: str) -> float:
    col = "sigma_um"
    if not text:
        raise SigmaFileError(path, line, "expected a number (µm), found an empty field", col)
    try:
        value = float(text)
    except ValueError:
        raise SigmaFileError(path, line, f"expected a number (µm), found {text!r}", col) from None
    if not math.isfinite(value):
        raise SigmaFileError(path, line, f"expected a finite number, found {text!r}", col)
    if value < 0:
        raise SigmaFileError(path, line, f"expected a standard deviation ≥ 0, found {text!r}", col)
    return value


def _check_same(
    path: Path,
    line: int,
    column: str,
    what: str,
    name: str,
    regime: str,
    seen: dict[str, tuple[str, int]],
) -> None:
    first = seen.setdefault(name, (regime, line))
    if first[0] != regime:
        raise SigmaFileError(
            path,
            line,
            f"expected {what} {name} to keep regime {first[0]!r} (line {first[1]}), "
            f"found {regime!r}",
            column=column,
        )


# --------------------------------------------------------------------------- matrix


def _validate(rows: Iterable[SigmaRow]) -> list[SigmaRow]:
    """Same consistency rules as the reader, for rows built in code (ValueError)."""
    rows = list(rows)
    if not rows:
        raise ValueError("no σ rows: nothing to rank")
    model_regime: dict[str, str] = {}
    data_regime: dict[str, str] = {}
    pairs: set[tuple[str, str]] = set()
    for r in rows:
        sigma = float(r.sigma_um)
        if not math.isfinite(sigma) or sigma < 0:
            raise ValueError(f"σ of ({r.model}, {r.data}) must be finite and ≥ 0, got {sigma!r}")
        if model_regime.setdefault(r.model, r.model_regime) != r.model_regime:
            raise ValueError(
                f"model {r.model} listed under regimes {model_regime[r.model]!r} "
                f"and {r.model_regime!r}"
            )
        if data_regime.setdefault(r.data, r.data_regime) != r.data_regime:
            raise ValueError(
                f"run {r.data} listed under regimes {data_regime[r.data]!r} and {r.data_regime!r}"
            )
        if (r.model, r.data) in pairs:
            raise ValueError(f"duplicate σ for (model {r.model}, run {r.data})")
        pairs.add((r.model, r.data))
    return rows


def sigma_matrix(rows: Iterable[SigmaRow]) -> tuple[list[str], list[str], np.ndarray]:
    """Pivot rows to (models, data runs, σ) with σ[i, j] = σ of model i on run j.

    Models and runs keep their first-appearance order; missing cells are NaN.
    Raises ValueError on empty input, duplicate pairs or conflicting regimes.
    """
    rows = _validate(rows)
    models = list(dict.fromkeys(r.model for r in rows))
    data = list(dict.fromkeys(r.data for r in rows))
    mi = {m: i for i, m in enumerate(models)}
    dj = {d: j for j, d in enumerate(data)}
    sigma = np.full((len(models), len(data)), np.nan)
    for r in rows:
        sigma[mi[r.model], dj[r.data]] = float(r.sigma_um)
    return models, data, sigma


# --------------------------------------------------------------------------- ranking


@dataclass(frozen=True)
class RegimeReport:
    """Result of :func:`rank_regimes` (paper 002, Tables 4–6 and the choice of model).

    - ``blocks``: one dict per (model regime, data regime) block with σ values:
      ``model_regime, data_regime, mn_um, sd_um, n`` (MN = mean, SD = population SD).
    - ``models``: name -> ``regime, mn_um, sd_um, n_runs`` over the model's own-regime runs.
    - ``pairwise``: ``a, b, regime, comn_pct, cosd_pct`` with
      CoMN = (MN_a − MN_b)/MN_b·100 and CoSD = (SD_a − SD_b)/SD_b·100, for every
      ordered pair of the same regime in the paper's order (a<b: (a, b) then (b, a));
      a division by zero gives ±inf (or NaN for 0/0).
    - ``best``: regime -> chosen model; ``decisions``: regime -> why, one sentence.
    """

    blocks: list[dict]
    models: dict[str, dict]
    pairwise: list[dict]
    best: dict[str, str]
    tolerance_pct: float
    decisions: dict[str, str]

    def as_json(self) -> dict:
        """JSON-ready dict with plain floats (non-finite ratios become ``None``).

        Keys: ``blocks`` (model_regime, data_regime, mn_um, sd_um), ``models``
        (name -> regime, mn_um, sd_um), ``pairwise`` (a, b, comn_pct, cosd_pct),
        ``best``, ``tolerance_pct``, ``decisions``.
        """
        return {
            "blocks": [
                {
                    "model_regime": b["model_regime"],
                    "data_regime": b["data_regime"],
                    "mn_um": _json_float(b["mn_um"]),
                    "sd_um": _json_float(b["sd_um"]),
                }
                for b in self.blocks
            ],
            "models": {
                name: {
                    "regime": m["regime"],
                    "mn_um": _json_float(m["mn_um"]),
                    "sd_um": _json_float(m["sd_um"]),
                }
                for name, m in self.models.items()
            },
            "pairwise": [
                {
                    "a": p["a"],
                    "b": p["b"],
                    "comn_pct": _json_float(p["comn_pct"]),
                    "cosd_pct": _json_float(p["cosd_pct"]),
                }
                for p in self.pairwise
            ],
            "best": dict(self.best),
            "tolerance_pct": float(self.tolerance_pct),
            "decisions": dict(self.decisions),
        }


def _json_float(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _mn_sd(values: np.ndarray) -> tuple[float, float]:
    """Mean and population SD (ddof = 0) of a 1-D array without NaN."""
    return float(np.mean(values)), float(np.std(values, ddof=0))


def _relative_pct(a: float, b: float) -> float:
    """(a − b) / b · 100; ±inf when b = 0 and a ≠ 0, NaN when both are 0."""
    if b == 0.0:
        if a == 0.0:
            return math.nan
        return math.copysign(math.inf, a - b)
    return (a - b) / b * 100.0


def _gap_pct(mn: float, mn_best: float) -> float:
    """(MN_i − MN*) / MN* · 100, with 0 for a tie and inf when MN* = 0 < MN_i."""
    if mn == mn_best:
        return 0.0
    if mn_best == 0.0:
        return math.inf
    return (mn - mn_best) / mn_best * 100.0


def rank_regimes(rows: Sequence[SigmaRow], tolerance_pct: float = 1.0) -> RegimeReport:
    """Tables 4–6 of paper 002 and the best model per regime.

    ``tolerance_pct`` (≥ 0, default 1 %) is how close to the lowest MN a model must be
    for robustness (lowest SD) to decide instead of accuracy. Raises ValueError on
    empty or inconsistent rows, a bad tolerance, or a model without own-regime data.
    """
    tol = float(tolerance_pct)
    if not math.isfinite(tol) or tol < 0:
        raise ValueError(f"tolerance_pct must be a finite number ≥ 0, got {tolerance_pct!r}")
    rows = _validate(rows)
    table = _SigmaTable.of(rows)
    model_stats = _model_stats(table)
    best: dict[str, str] = {}
    decisions: dict[str, str] = {}
    for reg in table.model_regimes:
        best[reg], decisions[reg] = _decide(table.members(reg), model_stats, tol)
    return RegimeReport(
        blocks=_blocks(table),
        models=model_stats,
        pairwise=_pairwise(table, model_stats),
        best=best,
        tolerance_pct=tol,
        decisions=decisions,
    )


@dataclass(frozen=True)
class _SigmaTable:
    """The σ matrix with each model's and each run's regime, in first-seen order."""

    models: list[str]
    data: list[str]
    sigma: np.ndarray
    m_regime: dict[str, str]
    d_regime: dict[str, str]

    @classmethod
    def of(cls, rows: Sequence[SigmaRow]) -> _SigmaTable:
        models, data, sigma = sigma_matrix(rows)
        m_regime = {r.model: r.model_regime for r in rows}
        d_regime = {r.data: r.data_regime for r in rows}
        return cls(models, data, sigma, m_regime, d_regime)

    @property
    def model_regimes(self) -> list[str]:
        return list(dict.fromkeys(self.m_regime[m] for m in self.models))

    @property
    def data_regimes(self) -> list[str]:
        return list(dict.fromkeys(self.d_regime[d] for d in self.data))

    def members(self, regime: str) -> list[str]:
        return [m for m in self.models if self.m_regime[m] == regime]

    def values(self, models: Sequence[str], data_regime: str) -> np.ndarray:
        """The finite σ of ``models`` on the runs of ``data_regime``, flattened."""
        rows_idx = [self.models.index(m) for m in models]
        cols_idx = [j for j, d in enumerate(self.data) if self.d_regime[d] == data_regime]
        block = self.sigma[np.ix_(rows_idx, cols_idx)].ravel()
        return block[~np.isnan(block)]


def _blocks(table: _SigmaTable) -> list[dict]:
    """Table 4: absolute evaluation per (model regime, data regime) block."""
    blocks: list[dict] = []
    for mr in table.model_regimes:
        for dr in table.data_regimes:
            block = table.values(table.members(mr), dr)
            if block.size == 0:
                continue
            mn, sd = _mn_sd(block)
            blocks.append(
                {"model_regime": mr, "data_regime": dr, "mn_um": mn, "sd_um": sd, "n": block.size}
            )
    return blocks


def _model_stats(table: _SigmaTable) -> dict[str, dict]:
    """Per-model MN/SD over the model's own-regime runs."""
    stats: dict[str, dict] = {}
    for m in table.models:
        reg = table.m_regime[m]
        own = table.values([m], reg)
        if own.size == 0:
            raise ValueError(
                f"model {m} (regime {reg!r}) has no σ on any run of its own regime "
                f"(runs with data_regime {reg!r}); cannot rank regime {reg!r}"
            )
        mn, sd = _mn_sd(own)
        stats[m] = {"regime": reg, "mn_um": mn, "sd_um": sd, "n_runs": int(own.size)}
    return stats


def _pairwise(table: _SigmaTable, model_stats: dict[str, dict]) -> list[dict]:
    """Tables 5–6: relative evaluation, paper order (i<j: (i, j) then (j, i))."""
    pairwise: list[dict] = []
    for reg in table.model_regimes:
        members = table.members(reg)
        for ia, a in enumerate(members):
            for b in members[ia + 1 :]:
                for x, y in ((a, b), (b, a)):
                    sx, sy = model_stats[x], model_stats[y]
                    pairwise.append(
                        {
                            "a": x,
                            "b": y,
                            "regime": reg,
                            "comn_pct": _relative_pct(sx["mn_um"], sy["mn_um"]),
                            "cosd_pct": _relative_pct(sx["sd_um"], sy["sd_um"]),
                        }
                    )
    return pairwise


def _decide(members: list[str], model_stats: dict[str, dict], tol: float) -> tuple[str, str]:
    """Accuracy first, then robustness within the tolerance: the winner and why."""
    mn_best = min(model_stats[m]["mn_um"] for m in members)
    gaps = {m: _gap_pct(model_stats[m]["mn_um"], mn_best) for m in members}
    candidates = [m for m in members if gaps[m] == 0.0 or gaps[m] < tol]
    winner = min(candidates, key=lambda m: (model_stats[m]["sd_um"], model_stats[m]["mn_um"], m))
    return winner, _decision_sentence(winner, members, candidates, gaps, model_stats, mn_best, tol)


def _decision_sentence(
    winner: str,
    members: list[str],
    candidates: list[str],
    gaps: dict[str, float],
    stats: dict[str, dict],
    mn_best: float,
    tol: float,
) -> str:
    w = stats[winner]
    if len(members) == 1:
        return (
            f"{winner} is the only model of this regime "
            f"(MN {w['mn_um']:.3f} µm, SD {w['sd_um']:.3f} µm)"
        )
    if len(candidates) > 1:
        return (
            f"{', '.join(candidates)} within {tol:g} % of the best MN {mn_best:.3f} µm; "
            f"lowest SD wins: {winner} ({w['sd_um']:.3f} µm)"
        )
    others = [m for m in members if m != winner]
    nxt = min(others, key=lambda m: (stats[m]["mn_um"], m))
    return (
        f"{winner} has the lowest MN {w['mn_um']:.3f} µm and no other model is within "
        f"{tol:g} % (next: {nxt}, MN {stats[nxt]['mn_um']:.3f} µm, "
        f"+{gaps[nxt]:.1f} %); accuracy decides: {winner}"
    )


# --------------------------------------------------------------------------- text


def _pct(x: float, digits: int = 2) -> str:
    return f"{x:+.{digits}f}" if math.isfinite(x) else ("n/a" if math.isnan(x) else f"{x:+}")


def format_report(report: RegimeReport) -> str:
    """Readable text: Table-4-like blocks, per-model MN/SD, CoMN/CoSD per regime, best."""
    out: list[str] = []
    out.append("Absolute evaluation (paper 002, Table 4): σ per block, MN / population SD")
    out.append(f"  {'model regime':<14}{'data regime':<14}{'MN µm':>8}{'SD µm':>8}{'n':>4}")
    for b in report.blocks:
        out.append(
            f"  {b['model_regime']:<14}{b['data_regime']:<14}"
            f"{b['mn_um']:>8.2f}{b['sd_um']:>8.2f}{b['n']:>4d}"
        )
    out.append("")
    out.append("Per model, over its own-regime runs")
    out.append(f"  {'model':<8}{'regime':<12}{'MN µm':>8}{'SD µm':>8}{'runs':>6}")
    for name, m in report.models.items():
        out.append(
            f"  {name:<8}{m['regime']:<12}{m['mn_um']:>8.3f}{m['sd_um']:>8.3f}{m['n_runs']:>6d}"
        )
    regimes = list(dict.fromkeys(m["regime"] for m in report.models.values()))
    for reg in regimes:
        pairs = [p for p in report.pairwise if p["regime"] == reg]
        out.append("")
        out.append(f"Relative evaluation, {reg} (eq. 7–8): CoMN / CoSD in %")
        if not pairs:
            out.append("  (single model: no pairs)")
        for p in pairs:
            label = f"{p['a']}–{p['b']}"
            out.append(f"  {label:<12}{_pct(p['comn_pct']):>10}{_pct(p['cosd_pct'], 1):>10}")
    out.append("")
    out.append(f"Best model per regime (tolerance {report.tolerance_pct:g} % on MN)")
    for reg, model in report.best.items():
        out.append(f"  {reg}: {model} — {report.decisions[reg]}")
    return "\n".join(out) + "\n"
