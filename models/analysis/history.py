"""Residual analysis of a logged history: the error known only at probe rows.

In production the gateway logs the temperatures and the speed every cycle, but the
real error only when the probe cycle measured it: the probe value plus the
compensation the CNC applied then is the machine's thermal error at that instant
(contracts §7). :func:`analyse_history` runs :mod:`models.analysis.search` on such a
history: the effect terms (lags since the recording's reference, time since the
start, speed terms) are computed on the continuous history, every cycle, while
the fit and every held-out figure use the probe rows only (``fit_rows``).

The error is taken as measured, not as a rise: a probe measures the error itself
against its calibrated artefact, there is no at-rest probe reading to subtract.
The temperatures are rises from the history's start (one recording), as the
runtime takes them. One history is one run, validated leave-one-block-out (five
contiguous blocks in time), as ``analyze`` does with one run.

The result, when an effect is believed, is a *proposal*: the effects with their
parameters, the held-out RMSE before and after on the logged probes, and the
augmented model (:mod:`models.analysis.augmented`) ready to be promoted.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from models.analysis import augmented
from models.data.dataset import MeasuredRuns
from models.data.features import prepare
from models.data.lag_terms import GAP_S

HISTORY_RUN = "logged-history"
TARGET = "error_um"
GRID_STEP_S = 15.0  # the analysis's time grid (History.on_grid)


@dataclass(frozen=True)
class History:
    """Cycle-aligned arrays of a logged history (units in the names)."""

    time_s: np.ndarray  # (n,)
    speed_rpm: np.ndarray  # (n,)
    sensors: tuple[str, ...]
    temperatures_C: np.ndarray  # (n, k), NaN where a reading was not good
    error_um: np.ndarray  # (n,) measured error at probe rows, NaN elsewhere
    ambient_C: np.ndarray | None = None

    @property
    def n_samples(self) -> int:
        return int(self.time_s.size)

    @property
    def probe_rows(self) -> np.ndarray:
        return np.isfinite(self.error_um)

    def complete(self) -> History:
        """Rows where the speed and every temperature are known (what a model can use)."""
        keep = np.isfinite(self.speed_rpm) & np.all(np.isfinite(self.temperatures_C), axis=1)
        if self.ambient_C is not None:
            keep &= np.isfinite(self.ambient_C)
        return History(
            self.time_s[keep],
            self.speed_rpm[keep],
            self.sensors,
            self.temperatures_C[keep],
            self.error_um[keep],
            None if self.ambient_C is None else self.ambient_C[keep],
        )

    def on_grid(self, step_s: float) -> History:
        """The history on an even time grid of ``step_s``, from its first to its last row.

        Temperatures are interpolated linearly between their good readings, the speed
        held from the last reading (linear across a logging gap longer than
        :data:`models.data.lag_terms.GAP_S`, as the lags take it on a file and in the
        runtime's streams), and each probe's error moved to the nearest grid
        row (at most ``step_s``/2 away; of two probes on one row the later stays). An
        even grid lets the lag terms run as one filter (:func:`models.data.lag_terms.
        first_order_lag`), where jittered cycle times would take its slower
        uneven path; a grid of 15 s changes a lag of τ ≥ 5 min by a fraction of its input's
        change over 15 s.
        """
        rows = self.complete()
        if rows.n_samples < 2:
            return rows
        grid = np.arange(rows.time_s[0], rows.time_s[-1] + step_s / 2, step_s)
        temps = np.column_stack(
            [
                np.interp(grid, rows.time_s, rows.temperatures_C[:, j])
                for j in range(len(self.sensors))
            ]
        )
        held = np.clip(np.searchsorted(rows.time_s, grid, side="right") - 1, 0, None)
        error = np.full(grid.size, np.nan)
        probe = rows.probe_rows
        nearest = np.clip(
            np.rint((rows.time_s[probe] - grid[0]) / step_s).astype(int), 0, grid.size - 1
        )
        error[nearest] = rows.error_um[probe]
        ambient = None if rows.ambient_C is None else np.interp(grid, rows.time_s, rows.ambient_C)
        following = np.minimum(held + 1, rows.n_samples - 1)
        in_gap = rows.time_s[following] - rows.time_s[held] > GAP_S
        speed = np.where(in_gap, np.interp(grid, rows.time_s, rows.speed_rpm), rows.speed_rpm[held])
        return History(grid, speed, self.sensors, temps, error, ambient)

    def as_runs(self, source: str = "logged history") -> MeasuredRuns:
        numeric = {
            name: np.ascontiguousarray(self.temperatures_C[:, j], dtype=float)
            for j, name in enumerate(self.sensors)
        }
        if self.ambient_C is not None:
            numeric["ambient_C"] = np.asarray(self.ambient_C, dtype=float)
        numeric[TARGET] = np.asarray(self.error_um, dtype=float)
        return MeasuredRuns(
            source=source,
            run=np.full(self.n_samples, HISTORY_RUN, dtype=object),
            time_s=np.asarray(self.time_s, dtype=float),
            speed_rpm=np.asarray(self.speed_rpm, dtype=float),
            sensors=tuple(s for s in self.sensors),
            target=TARGET,
            numeric=numeric,
        )

    def write_csv(self, path: str) -> None:
        """The measured-run CSV of the history (one run; ``error_um`` empty between probes),
        what ``analyze --probe-rows`` reads."""
        header = ["run", "time_s", "speed_rpm", *self.sensors, TARGET]
        with open(path, "w", encoding="utf-8", newline="") as out:
            out.write(",".join(header) + "\n")
            for i in range(self.n_samples):
                cells = [HISTORY_RUN, f"{self.time_s[i]:.3f}", _cell(self.speed_rpm[i], 1)]
                cells += [_cell(v, 2) for v in self.temperatures_C[i]]
                cells.append(_cell(self.error_um[i], 4))
                out.write(",".join(cells) + "\n")

    def save(self, path: str) -> None:
        """One .npz file (the background analysis reads it in its own process)."""
        arrays: dict[str, Any] = {
            "time_s": self.time_s,
            "speed_rpm": self.speed_rpm,
            "sensors": np.array(self.sensors),
            "temperatures_C": self.temperatures_C,
            "error_um": self.error_um,
        }
        if self.ambient_C is not None:
            arrays["ambient_C"] = self.ambient_C
        np.savez(path, **arrays)

    @classmethod
    def load(cls, path: str) -> History:
        with np.load(path, allow_pickle=False) as data:
            return cls(
                time_s=data["time_s"],
                speed_rpm=data["speed_rpm"],
                sensors=tuple(str(s) for s in data["sensors"]),
                temperatures_C=data["temperatures_C"],
                error_um=data["error_um"],
                ambient_C=data["ambient_C"] if "ambient_C" in data.files else None,
            )


def analyse_history(
    history: History,
    method: str = "mlr",
    sensors: tuple[str, ...] | None = None,
    software_version: str = "unknown",
    model_prefix: str = "monitor",
    step_s: float | None = GRID_STEP_S,
) -> dict[str, Any]:
    """The analysis of the module docstring; a plain-JSON summary (and the model, if any).

    The history is put on an even grid of ``step_s`` first (:meth:`History.on_grid`;
    None: as logged). Returns ``{"effect": "none", …}`` when nothing is believed,
    else the proposal's content with ``"document"``, the augmented model.
    """
    # Here, not at the top: the search brings scipy.stats (2 s to import), which the
    # gateway's start (this module is the monitor's) should not wait for.
    from models.analysis.search import analyze

    usable = history.complete() if step_s is None else history.on_grid(step_s)
    probes = int(usable.probe_rows.sum())
    data = usable.as_runs()
    prepared = prepare(data, sensors, "recording-start")
    # The probe measured the error itself: no reference reading to subtract.
    prepared = replace(prepared, error_um=np.asarray(data.error_um, dtype=float))
    fit_rows = np.isfinite(prepared.error_um)
    result, accepted, analysis = analyze(prepared, method, sensors, fit_rows=fit_rows)
    summary: dict[str, Any] = {
        "effect": result.effect,
        "effects": [
            {"effect": a.family.effect, "params": a.params, "label": a.family.label}
            for a in accepted
        ],
        "before": result.before.as_dict(),
        "after": result.after.as_dict(),
        "validation": result.validation,
        "rows": usable.n_samples,
        "probes": probes,
        "history_s": float(usable.time_s[-1] - usable.time_s[0]) if usable.n_samples else 0.0,
        "steps": [
            {
                "effect": s.effect,
                "params": s.params,
                "before_rmse_um": s.before.rmse_um,
                "after_rmse_um": s.after.rmse_um,
            }
            for s in result.steps
        ],
    }
    if accepted:
        model_id = f"{model_prefix}-{method}-" + "-".join(result.effects)
        summary["document"] = augmented.build_augmented_document(
            analysis, accepted, result, model_id, software_version
        )
    return summary


def _cell(value: float, decimals: int) -> str:
    return "" if not np.isfinite(value) else f"{value:.{decimals}f}"
