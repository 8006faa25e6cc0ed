"""The ``replay`` command's work: load, replay every probe interval, table and JSON (§6)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from gateway.offline.targets import TargetRuns, combined, each_target, say_heading
from models.analysis import augmented
from models.base import ThermalModel
from models.data.dataset import MeasuredRuns
from models.data.features import Prepared, prepare
from models.data.targets import load_targets
from models.estimators.registry import make_model
from models.fit.forward import disagreement, forward_validate
from models.fit.forward_progress import counted
from models.fit.metrics import accuracy
from models.online import declared_fits
from models.online.replay import (
    DEFAULT_KINDS,
    declared_heldout,
    filter_choice,
    fit_for_store,
    offline_accuracy,
    replay_interval,
)
from models.store import data_fingerprint, safe_model_id

BASE_DESCRIPTIONS = {
    "lagged": (
        "the declared model's sensors plus first-order lags of them (one or two τ), ridge, "
        "fitted on the level and on the changes over the probe interval; τ set, penalty and "
        "level weight chosen by inner leave-one-run-out"
    ),
    "lagged lag-ridge": (
        "the lag-ridge terms (every sensor and n, n^1.5, n², n^2.5 with their lags at ten τ, "
        "5 min … 24 h), ridge, fitted on the level and on the changes over the probe interval; "
        "penalty and level weight chosen by inner leave-one-run-out on a grid fixed beforehand"
    ),
    "declared": "the declared model as fit fits it",
    "augmented": (
        "the structure of the analyze result given (base model, effects and parameters), "
        "every coefficient refitted without the held-out run"
    ),
}

#: Said when the augmented model was analysed on the file being replayed.
SAME_FILE_NOTE = (
    "note: the augmented model's effects were chosen on this file, held-out runs "
    "included; only its coefficients are refitted without each held-out run"
)


def run_replay(
    data_csv: Path,
    target: str,
    method: str,
    sensors: Sequence[str] | None,
    intervals_min: Sequence[float],
    base: str,
    augmented_file: Path | None,
    say: Callable[[str], None],
    store_dir: Path | None = None,
    version: str = "unknown",
    filter_kinds: Sequence[str] = (),
    progress: bool = False,
    note: Callable[[str], None] | None = None,
    loaded: TargetRuns | None = None,
) -> dict[str, Any]:
    """Replay DATA_CSV at every interval; print a table; return the JSON of contracts §6.

    ``filter_kinds``: the kinds the nested choice may pick; none given means
    ``DEFAULT_KINDS`` (models/online/replay.py). ``note``: where notes on the data go
    (default ``say``; the command gives stderr)."""
    filter_kinds = tuple(filter_kinds) or DEFAULT_KINDS
    if store_dir is not None and method == "lag-ridge":  # refused before the long replay
        raise ValueError(
            "--store with --model lag-ridge is not built: save the offline model with "
            "fit --method lag-ridge --store DIR"
        )
    started = time.perf_counter()
    document = None
    if augmented_file is not None:
        document = augmented.load(augmented_file)
        method = document["base"]["method"]
        base = "augmented"
    data, prepared = _runs_of(loaded, data_csv, target, sensors, intervals_min, note or say)
    described = "lagged lag-ridge" if base == "lagged" and method == "lag-ridge" else base
    say(
        f"{data_csv.name}: {data.n_samples} rows, {len(data.run_ids)} runs, target {target} (µm), "
        f"model {method}; base: {BASE_DESCRIPTIONS[described]}"
    )
    if document is not None and Path(document["provenance"]["source_file"]).name == data_csv.name:
        (note or say)(SAME_FILE_NOTE)
    if base == "declared":  # every base fit of every interval, once, on every core
        declared_fits.prefill(prepared, method, sensors, progress)
    loro_predicted = declared_heldout(prepared, method, sensors)
    offline = offline_accuracy(prepared, method, sensors, loro_predicted)
    forward = forward_figure(data, prepared, method, sensors, loro_predicted, progress)
    online = [
        replay_interval(
            prepared,
            m,
            base=base,
            method=method,
            sensors=sensors,
            document=document,
            kinds=filter_kinds,
            progress=progress,
        )
        for m in intervals_min
    ]
    rows = [r.as_dict() for r in online]
    _say_table(method, offline, rows, say)
    _say_interval(offline.get("interval"), say)
    _say_forward(forward, say)
    stored = None
    if store_dir is not None:
        if base != "lagged":
            raise ValueError(
                "--store saves the lagged base; it cannot be combined with --base "
                "declared or --augmented"
            )
        store_args = (method, sensors, offline, store_dir, version, say, filter_kinds)
        stored = store_lagged(prepared, intervals_min[0], *store_args)
    elapsed = time.perf_counter() - started
    say(f"leave-one-run-out, causal; {elapsed:.1f} s")
    return {
        "target": target,
        "model": method,
        "validation": "leave-one-run-out",
        "base": {"kind": base, "description": BASE_DESCRIPTIONS[described]},
        "augmented_model": None if document is None else document["model_id"],
        "offline": offline,
        "forward": forward,
        "online": rows,
        "filter_kinds_offered": list(filter_kinds),
        "reference": prepared.plan.describe(),
        "stored_model": stored,
        "elapsed_s": round(elapsed, 2),
    }


def forward_figure(
    data: MeasuredRuns,
    prepared: Prepared,
    method: str,
    sensors: Sequence[str] | None,
    loro_predicted: np.ndarray,
    progress: bool = False,
) -> dict[str, Any] | None:
    """The declared model's forward figure (each later recording, or run, predicted by the
    model fitted on the earlier ones only, started as a new recording, no probes) and how
    it compares with its leave-one-run-out figure on the same runs, as ``fit`` reports it
    (None: too few runs)."""

    def factory() -> ThermalModel:
        return make_model(method, sensors)

    with counted(factory, prepared, progress) as made:
        forward = forward_validate(made, prepared, data, sensors)
    if forward is None:
        return None
    agreement = disagreement(forward, loro_predicted, prepared.error_um, prepared.data.run)
    return {
        **forward.as_dict(),
        "model": method,
        "of": "the declared model, fitted as fit fits it, without probes",
        "against_loro": agreement.as_dict(),
        "note": agreement.sentence(),
    }


def _say_forward(forward: dict[str, Any] | None, say: Callable[[str], None]) -> None:
    """The forward figure beside the leave-one-run-out ones: pooled, then per unit."""
    if forward is None:
        say("forward: too few runs for a forward figure")
        return
    say(
        f"forward (no probes; each later {forward['unit']} predicted by the {forward['model']} "
        f"model fitted on the earlier ones only, started as a new recording): "
        f"{forward['pooled']['rmse_um']:.2f} µm"
    )
    for unit, figures in forward["per_fold"].items():
        say(f"  {unit:<14} {figures['rmse_um']:6.2f} µm")
    prefix = "warning: " if forward["against_loro"]["disagree"] else ""
    say(f"{prefix}{forward['note']}")


def _runs_of(
    loaded: TargetRuns | None,
    data_csv: Path,
    target: str,
    sensors: Sequence[str] | None,
    intervals_min: Sequence[float],
    note: Callable[[str], None],
) -> tuple[MeasuredRuns, Prepared]:
    """The target's runs and their preparation: ``loaded`` (read and prepared once for
    several targets, :func:`run_replay_targets`), or DATA_CSV read for this target alone."""
    if loaded is not None:
        return loaded.data, loaded.prepared
    data = _load_replayable(data_csv, [target], sensors, intervals_min, note)
    return data, prepare(data, sensors)


def run_replay_targets(
    data_csv: Path,
    targets: Sequence[str],
    method: str,
    sensors: Sequence[str] | None,
    intervals_min: Sequence[float],
    say: Callable[[str], None],
    note: Callable[[str], None] | None = None,
    **options: Any,
) -> dict[str, Any]:
    """:func:`run_replay` for each target (DATA_CSV read once, the rises taken once), one
    section each; ``options``: run_replay's own (base, augmented_file, store_dir, ...).
    The command's JSON (:func:`gateway.offline.targets.combined`)."""
    data = _load_replayable(data_csv, targets, sensors, intervals_min, note or say)
    progress = bool(options.get("progress"))
    results: dict[str, dict[str, Any]] = {}
    for one in each_target(data, targets, sensors, progress=progress, readings=True):
        say_heading(one, data, targets, say, note or say)
        results[one.target] = run_replay(
            data_csv,
            one.target,
            method,
            sensors,
            intervals_min,
            say=say,
            note=note,
            loaded=one,
            **options,
        )
    return combined(results, {"model": method})


def _load_replayable(
    data_csv: Path,
    targets: Sequence[str],
    sensors: Sequence[str] | None,
    intervals_min: Sequence[float],
    note: Callable[[str], None],
) -> MeasuredRuns:
    """The runs of DATA_CSV (read once with every target), refused when no interval would
    take a single probe."""
    data = load_targets(data_csv, targets, sensors)
    for skipped in data.skipped:
        note(f"note: {skipped.describe()}")
    for text in data.notes:
        note(f"note: {data.source}: {text}")
    longest_min = max(
        (data.time_s[part][-1] - data.time_s[part][0]) / 60.0 for _, part in data.run_slices()
    )
    for interval in intervals_min:
        if interval > longest_min:
            raise ValueError(
                f"--probe-interval-min {interval:g}: no probe would be taken, the longest run "
                f"of {data_csv.name} lasts {longest_min:.0f} min"
            )
    return data


def _say_table(
    method: str,
    offline: dict[str, Any],
    rows: list[dict[str, Any]],
    say: Callable[[str], None],
) -> None:
    """The accuracy table (offline, then one line per interval) and each run's choice."""
    say(
        f"{'probe every':>12} {'RMSE µm':>8} {'between µm':>10} {'max µm':>8} "
        f"{'probes':>6} {'refused':>7}"
    )
    say(
        f"{'none (' + method + ')':>12} {offline['rmse_um']:8.2f} {'':>10} "
        f"{offline['max_abs_um']:8.2f} {'':>6} {'':>7}"
    )
    for row in rows:
        say(
            f"{row['probe_interval_min']:>8g} min {row['rmse_um']:8.2f} "
            f"{row['rmse_between_probes_um']:10.2f} {row['max_abs_um']:8.2f} "
            f"{row['probes']:6d} {row['probes_refused']:7d}"
        )
    for row in rows:
        say(f"chosen without the held-out run, probe every {row['probe_interval_min']:g} min:")
        for run, figures in row["per_run"].items():
            say(f"  {run:<14} {figures['rmse_um']:6.2f} µm  {describe_choice(figures['chosen'])}")


def _say_interval(interval: dict[str, Any] | None, say: Callable[[str], None]) -> None:
    """The declared model's interval: coverage of each held-out run (width calibrated on the
    other runs) and pooled."""
    if interval is None:
        say("interval: too few held-out rows to calibrate one")
        return
    pooled = interval["heldout_coverage"]
    covered = "n/a" if pooled is None else f"{pooled:.1%}"
    say(
        f"interval {interval['nominal_coverage']:.0%} (no probes): ±{interval['half_width_um']:.2f}"
        f" µm, coverage {covered} pooled over the held-out runs"
    )
    for run, row in interval["per_run_coverage"].items():
        band = row.get("half_width_um_for_85_95")
        needed = f"  85–95 % at ±{band[0]:.2f}–{band[1]:.2f} µm" if band else ""
        say(
            f"  {run:<14} coverage {row['coverage']:6.1%}  width {row['mean_width_um']:6.2f} µm"
            f" (±{row['half_width_um']:.2f}){needed}"
        )


def store_lagged(
    prepared: Prepared,
    interval_min: float,
    method: str,
    sensors: Sequence[str] | None,
    offline: dict[str, float],
    store_dir: Path,
    version: str,
    say: Callable[[str], None],
    filter_kinds: Sequence[str] = DEFAULT_KINDS,
) -> dict[str, str]:
    """Fit the lagged base and the filter on every run; save them as one augmented model."""
    parts, params, chosen, heldout = fit_for_store(
        prepared, interval_min, method, sensors, kinds=filter_kinds
    )
    data = prepared.data
    after = accuracy(prepared.error_um, heldout)
    taus = "-".join(f"{t:g}" for t in chosen["lag_taus_s"])
    document = {
        "format": augmented.FORMAT,
        "format_version": augmented.FORMAT_VERSION,
        "model_id": safe_model_id(f"{method}-{data.target}-online-lags-{taus}"),
        **parts,
        "target": {"name": data.target, "unit": "µm"},
        "reference": prepared.plan.describe(),
        "online_correction": {
            "params": params.as_dict(),
            "probe_interval_min": interval_min,
            "chosen_by": "leave-one-run-out on every run of the source file (see models/"
            "online_replay.py): q and R estimated, kind (of those offered) and k the "
            "simplest within 2 % of the best",
        },
        "provenance": {
            "base_model": "mlr",
            "effects_added": [e["effect"] for e in parts["effects"]],
            "source_file": Path(data.source).name,
            "data_sha256": data_fingerprint(prepared.inputs, prepared.error_um),
            "rows": data.n_samples,
            "runs": list(data.run_ids),
            "validation": "leave-one-run-out",
            "before": {"rmse_um": offline["rmse_um"], "max_abs_um": offline["max_abs_um"]},
            "after": after.as_dict(),
            "choices": chosen,
            "steps": [],
        },
        "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "software_version": version,
    }
    document = augmented.sealed(document)
    path = augmented.save(document, store_dir)
    correction = describe_choice({"filter": filter_choice(params)})
    say(
        f"saved {document['model_id']} → {path} (held-out RMSE without probes "
        f"{after.rmse_um:.2f} µm; online correction: {correction})"
    )
    return {"model_id": document["model_id"], "path": str(path)}


def describe_choice(chosen: dict[str, Any]) -> str:
    """One line: the base's choices (if any) and the filter's parameters."""
    parts = []
    if "lag_taus_s" in chosen:
        taus = "+".join(f"{t:g}" for t in chosen["lag_taus_s"])
        parts.append(
            f"lags τ {taus} s, ridge {chosen['ridge']:g}, level weight {chosen['level_weight']:g}"
        )
    f = chosen.get("filter", {})
    if f:
        extra = ""
        if "rate_process_um2_per_h3" in f:
            extra = f", q_rate {f['rate_process_um2_per_h3']:.3g} µm²/h³"
        if "gain_process_per_h" in f:
            extra = f", q_gain {f['gain_process_per_h']:.3g} /h"
        parts.append(
            f"filter {f['kind']}: q {f['process_um2_per_h']:.3g} µm²/h{extra}, "
            f"R {f['probe_noise_um']:.3g} µm, k {f['outlier_sigma']:g}"
        )
    return "; ".join(parts)
