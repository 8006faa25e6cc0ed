"""The ``score`` command's work: a stored model on a new recording, as the gateway runs it.

A plant fits in March and records a validation run in April. ``score`` applies
the March model to the April file without refitting anything and reports its
error per run and pooled. It predicts the way the running gateway does:

- the model is loaded and checked by the store's own loaders (format, checksum,
  signature, probe rows) and banked as :mod:`gateway.live.bank.model_bank` banks it: a plain
  model predicts each row from that row's rises; a model whose terms remember the
  history (``lag-ridge``, an ``analyze --store`` result) is stepped sample by sample
  through the same stream the live loop steps, its lag states carried warm across
  the runs of one continuous recording and started afresh at each new recording
  (a cold start, where a gateway takes its temperature reference);
- rises and the error are taken by the reference rules the model was fitted with
  (its stored ``reference`` policy, :mod:`models.data.references`), so a figure here is
  comparable with the held-out figure ``fit`` or ``analyze`` stored;
- inputs that leave what the model was fitted on (a rise beyond any training
  rise, a speed the training never reached: :mod:`models.training_range`) are named,
  since a figure inside the training span says nothing about them.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from gateway.live.bank.model_bank import Banked, BankedAugmented, BankedModel
from gateway.offline.targets import combined
from models.analysis import augmented
from models.base import ModelInputs
from models.data.dataset import AMBIENT_COLUMN, HEADER_LINE, DataError, MeasuredRuns, read_header
from models.data.features import Prepared, prepare
from models.data.references import first_rows
from models.data.targets import load_targets, view
from models.data.unit_ranges import SENSOR_PATTERN
from models.fit.interval import (
    COVERAGE_BAND,
    band_half_widths,
    coverage,
    span_excess,
    widened_um,
)
from models.fit.metrics import accuracy
from models.store import FORMAT as PLAIN_FORMAT
from models.store import ModelStore, StoreError, load_file
from models.training_range import Excursion, outside


@dataclass(frozen=True)
class ScoredModel:
    """A model as the gateway banks it, with what ``score`` reports about it."""

    banked: Banked
    path: Path
    kind: str  # "stored" or "augmented"
    method: str
    target: str
    policy: str  # the reference policy it was fitted with
    training_range: dict[str, Any] | None
    fitted_on: str  # the training file and runs, for the header line
    heldout_rmse_um: float | None  # the held-out figure stored at fit time
    #: the calibrated interval stored at fit time (:mod:`models.fit.interval`); None: unknown
    interval: dict[str, Any] | None = None


def find_model(spec: str, store_dir: Path | None) -> Path:
    """``--model``: a model file, or a model id looked up in ``--store`` (plain, then
    augmented/)."""
    path = Path(spec)
    if path.is_file():
        return path
    if store_dir is None:
        raise ValueError(
            f"--model {spec}: no such model file; give --store DIR to look a model id up"
        )
    if not store_dir.is_dir():
        what = "is a file" if store_dir.exists() else "no such folder"
        raise ValueError(f"--store {store_dir}: {what}; a model store folder was expected")
    for candidate in (
        ModelStore(store_dir).path_of(spec),
        store_dir / augmented.FOLDER / f"{spec}.json",
    ):
        if candidate.is_file():
            return candidate
    have = sorted(p.stem for p in store_dir.glob("*.json"))
    have += sorted(p.stem for p in (store_dir / augmented.FOLDER).glob("*.json"))
    raise ValueError(
        f"--model {spec}: no model of that id in {store_dir} (have: {', '.join(have) or 'none'})"
    )


def load_model(path: Path) -> ScoredModel:
    """Load and check the file with the store's loaders; bank it as the gateway would."""
    try:
        format_name = json.loads(path.read_text(encoding="utf-8")).get("format")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError) as exc:
        raise StoreError(f"{path}: not a readable JSON model file ({exc})") from None
    if format_name == PLAIN_FORMAT:
        return _plain(path)
    if format_name == augmented.FORMAT:
        return _augmented(path)
    raise StoreError(
        f"{path}: not a model file (format {format_name!r}, expected {PLAIN_FORMAT!r} "
        f"or {augmented.FORMAT!r})"
    )


def _plain(path: Path) -> ScoredModel:
    model, document = load_file(path)
    if callable(getattr(model, "stream", None)):  # its terms carry lag states
        banked: Banked = BankedAugmented.from_plain(model, document)
    else:
        banked = BankedModel(document.model_id, model, document)
    pooled = (document.validation or {}).get("pooled") or {}
    training = document.training_data
    return ScoredModel(
        banked=banked,
        path=path,
        kind="stored",
        method=document.method,
        target=document.target.get("name", "error_um"),
        policy=str(document.reference.get("policy", "auto")),
        training_range=document.training_range,
        fitted_on=f"{training.file} (runs {', '.join(training.runs)})",
        heldout_rmse_um=pooled.get("rmse_um"),
        interval=document.interval,
    )


def _augmented(path: Path) -> ScoredModel:
    document = augmented.load(path)
    banked = BankedAugmented.from_document(document, AMBIENT_COLUMN)
    provenance = document.get("provenance", {})
    after = provenance.get("after") or {}
    return ScoredModel(
        banked=banked,
        path=path,
        kind="augmented",
        method=str(document["base"]["method"]),
        target=str(document.get("target", {}).get("name", "error_um")),
        policy=str(document.get("reference", {}).get("policy", "auto")),
        training_range=provenance.get("training_range"),
        fitted_on=(
            f"{provenance.get('source_file', '?')} (runs {', '.join(provenance.get('runs', []))})"
        ),
        heldout_rmse_um=after.get("rmse_um"),
    )


def needed_sensors(scored: ScoredModel) -> list[str]:
    """The temperature columns the model reads, in its own order (its ambient input apart)."""
    banked = scored.banked
    if isinstance(banked, BankedModel):
        return list(banked.model.sensors_used_)
    return [s for s in banked.stream().sensors if s != AMBIENT_COLUMN]


def predictions(scored: ScoredModel, prepared: Prepared, progress: bool = False) -> np.ndarray:
    """The model's prediction at every row, µm (NaN where a stream had no complete input);
    ``progress``: a bar over the rows a stream steps through (stderr)."""
    if isinstance(scored.banked, BankedModel):
        inputs = prepared.inputs
        plain = ModelInputs(
            rise_C=inputs.rise_C, sensors=inputs.sensors, speed_rpm=inputs.speed_rpm
        )
        return np.asarray(scored.banked.model.predict(plain), dtype=float)
    return streamed(scored.banked, prepared, progress)


def _rows_bar(n: int, what: str, progress: bool) -> tqdm:
    """A bar over ``n`` rows, redrawn at every 1 % of them (a fast loop still shows it move)."""
    return tqdm(range(n), desc=what, unit="row", disable=not progress, leave=False,
                mininterval=0, miniters=max(n // 100, 1))  # fmt: skip


def streamed(banked: BankedAugmented, prepared: Prepared, progress: bool = False) -> np.ndarray:
    """Every row stepped in order through the model's stream, as the live loop steps it;
    each recording (a cold start) starts a fresh stream, the runs within it carry on."""
    data, plan = prepared.data, prepared.plan
    names = list(prepared.inputs.sensors)
    rises = prepared.inputs.rise_C
    ambient = None if data.ambient_C is None else plan.rises(data.ambient_C)
    starts = first_rows(plan.recording)
    out = np.full(data.n_samples, np.nan)
    stream = banked.stream()
    for k in _rows_bar(data.n_samples, "rows stepped through the model", progress):
        if starts[k] == k:
            stream = banked.stream()
        row = dict(zip(names, map(float, rises[k]), strict=True))
        if ambient is not None:
            row[AMBIENT_COLUMN] = float(ambient[k])
        value = stream.step(
            float(data.time_s[k]), row, float(data.speed_rpm[k]), row.get(AMBIENT_COLUMN)
        )
        if value is not None:
            out[k] = value
    return out


def _require_model_sensors(data_csv: Path, scored: ScoredModel) -> None:
    """Refuse a file without a sensor the model reads, naming the model (the sensors are
    the model's, not a --sensors list the user gave)."""
    names = read_header(data_csv)
    missing = [s for s in needed_sensors(scored) if s not in names]
    if missing:
        present = [n for n in names if SENSOR_PATTERN.match(n)]
        raise DataError(
            data_csv,
            HEADER_LINE,
            missing[0],
            f"the model {scored.banked.model_id} reads sensor(s) {', '.join(missing)}, "
            f"which this file lacks (its temperature columns: {', '.join(present) or 'none'})",
        )


def run_figures(prepared: Prepared, predicted: np.ndarray) -> dict[str, dict[str, float | int]]:
    """RMSE, σ and max|e| (µm) of each run, then of every row pooled."""
    measured = prepared.error_um
    known = np.isfinite(predicted) & np.isfinite(measured)
    figures: dict[str, dict[str, float | int]] = {}
    for run_id, rows in prepared.data.run_slices():
        mask = known[rows]
        if mask.any():
            figures[run_id] = accuracy(measured[rows][mask], predicted[rows][mask]).as_dict()
    if not known.any():
        raise ValueError("the model predicted no row of this file (an input missing throughout)")
    figures["pooled"] = accuracy(measured[known], predicted[known]).as_dict()
    return figures


def half_widths(
    scored: ScoredModel, prepared: Prepared, progress: bool = False
) -> np.ndarray | None:
    """The interval's half-width at every row (µm), widened as the live loop widens it for
    inputs outside the training span; None when the model holds no calibration."""
    if scored.interval is None:
        return None
    inputs = prepared.inputs
    stored = scored.training_range or {}
    out = np.empty(inputs.n_samples)
    for k in _rows_bar(inputs.n_samples, "rows' interval widths", progress):
        rises = dict(zip(inputs.sensors, map(float, inputs.rise_C[k]), strict=True))
        excess, _ = span_excess(stored, rises, float(inputs.speed_rpm[k]))
        out[k] = widened_um(scored.interval, excess, 0)
    return out


def interval_figures(
    scored: ScoredModel, prepared: Prepared, predicted: np.ndarray, progress: bool = False
) -> dict[str, Any] | None:
    """Coverage (share of rows inside predicted ± half-width) and mean width, µm, per run
    and pooled; None when the model holds no calibration (interval unknown)."""
    widths = half_widths(scored, prepared, progress)
    if widths is None or scored.interval is None:
        return None
    measured = prepared.error_um
    stored = float(scored.interval["half_width_um"])
    # |residual| over the row's widening: the stored half-width each row needed.
    with np.errstate(divide="ignore", invalid="ignore"):
        needed = np.abs(measured - predicted) * stored / widths

    def of_rows(rows: slice) -> dict[str, Any]:
        found: dict[str, Any] = coverage(measured[rows], predicted[rows], widths[rows])
        found["half_width_um_for_85_95"] = band_half_widths(needed[rows])
        return found

    return {
        "nominal_coverage": scored.interval.get("nominal_coverage"),
        "half_width_um_stored": stored,
        "per_run": {run_id: of_rows(rows) for run_id, rows in prepared.data.run_slices()},
        "pooled": of_rows(slice(None)),
    }


def excursions(scored: ScoredModel, prepared: Prepared) -> list[Excursion]:
    """Inputs of this file outside the model's training span ([] when none is stored)."""
    if scored.training_range is None:
        return []
    inputs = prepared.inputs
    rises = {name: inputs.rise_C[:, j] for j, name in enumerate(inputs.sensors)}
    return outside(scored.training_range, rises, inputs.speed_rpm)


def score(
    data_csv: Path,
    model_spec: str,
    store_dir: Path | None,
    target: str | None,
    say: Callable[[str], None],
    note: Callable[[str], None] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Score the model on DATA_CSV; print the table (``say``) and the notes on the data
    (``note``, default ``say``: the command gives stderr); return the JSON result.
    ``progress``: bars over the rows (stderr)."""
    return score_targets(
        data_csv, [model_spec], store_dir, [target] if target else [], say, note, progress
    )


def score_targets(
    data_csv: Path,
    model_specs: Sequence[str],
    store_dir: Path | None,
    targets: Sequence[str],
    say: Callable[[str], None],
    note: Callable[[str], None] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Score each target with its model (:func:`pairs`), DATA_CSV read once with every
    target and sensor; one section each; one target: today's JSON, several: keyed by
    target under ``targets``. ``progress``: bars over the rows (stderr)."""
    note = note or say
    models = [load_model(find_model(spec, store_dir)) for spec in model_specs]
    paired = pairs(models, targets)
    for scored in models:
        _require_model_sensors(Path(data_csv), scored)
    sensors = list(dict.fromkeys(s for scored in models for s in needed_sensors(scored)))
    data = load_targets(data_csv, list(paired), sensors)
    for skipped in data.skipped:
        note(f"note: {skipped.describe()}")
    for text in data.notes:
        note(f"note: {data.source}: {text}")
    results: dict[str, dict[str, Any]] = {}
    for target, scored in paired.items():
        one = view(data, target, needed_sensors(scored))
        if len(paired) > 1:
            say(f"\n=== target {target} ({len(results) + 1} of {len(paired)}) ===")
            for skipped in one.skipped if one.n_samples != data.n_samples else ():
                note(f"note: {target}: {skipped.describe()}")
        results[target] = _score_one(scored, data_csv, one, say, note, progress)
    return combined(results)


def pairs(models: Sequence[ScoredModel], targets: Sequence[str]) -> dict[str, ScoredModel]:
    """Which model scores which target: one model, every target given (default its own);
    several models, each its own target, and each target given needs exactly one model
    that predicts it."""
    if len(models) == 1:
        return {target: models[0] for target in (targets or [models[0].target])}
    by_target: dict[str, ScoredModel] = {}
    for scored in models:
        if scored.target in by_target:
            raise ValueError(
                f"--model {by_target[scored.target].banked.model_id} and "
                f"{scored.banked.model_id} both predict {scored.target}: one model per target"
            )
        by_target[scored.target] = scored
    missing = [target for target in targets if target not in by_target]
    if missing:
        have = ", ".join(f"{m.banked.model_id} ({m.target})" for m in models)
        raise ValueError(f"--target {missing[0]}: no --model predicts it (models: {have})")
    return {target: by_target[target] for target in (targets or by_target)}


def _score_one(
    scored: ScoredModel,
    data_csv: Path,
    data: MeasuredRuns,
    say: Callable[[str], None],
    note: Callable[[str], None],
    progress: bool = False,
) -> dict[str, Any]:
    """Score one model on one target's runs; print its table; its JSON object."""
    if scored.banked.sensors & {AMBIENT_COLUMN} and data.ambient_C is None:
        raise ValueError(f"{data_csv}: the model needs an {AMBIENT_COLUMN} column; there is none")
    prepared = prepare(data, needed_sensors(scored), scored.policy)
    predicted = predictions(scored, prepared, progress)
    figures = run_figures(prepared, predicted)
    found = excursions(scored, prepared)
    interval = interval_figures(scored, prepared, predicted, progress)
    for line in report_lines(scored, prepared, figures, found) + interval_lines(interval):
        (note if line.startswith("note:") else say)(line)
    return {
        "model_id": scored.banked.model_id,
        "model_file": str(scored.path),
        "kind": scored.kind,
        "method": scored.method,
        "target": data.target,
        "data": str(data_csv),
        "reference": prepared.plan.describe(),
        "refit": False,
        "per_run": {k: v for k, v in figures.items() if k != "pooled"},
        "pooled": figures["pooled"],
        "heldout_rmse_um_at_fit": scored.heldout_rmse_um,
        "training_range_stored": scored.training_range is not None,
        "outside_training": [e.as_dict() for e in found],
        "interval": interval,
    }


def interval_lines(interval: dict[str, Any] | None) -> list[str]:
    """The interval's coverage per run and pooled, or a note that the model holds none."""
    if interval is None:
        return ["note: the model file holds no calibrated interval: its width is unknown"]
    nominal = float(interval["nominal_coverage"])
    stored = float(interval["half_width_um_stored"])
    low, high = COVERAGE_BAND
    band_header = f"± µm for {low:.0%}–{high:.0%}"
    header = f"{'interval':<16} {'rows':>6} {'coverage':>8} {'width µm':>9} {band_header:>17}"
    lines = [f"{header}  (nominal {nominal:.0%}, stored ± {stored:.2f})"]
    rows = {**interval["per_run"], "pooled": interval["pooled"]}
    for name, row in rows.items():
        band = row.get("half_width_um_for_85_95")
        band_text = f"{band[0]:.2f}–{band[1]:.2f}" if band else "–"
        lines.append(
            f"{name:<16} {row['n_samples']:>6} {row['coverage']:8.1%} "
            f"{row['mean_width_um']:9.2f} {band_text:>17}"
        )
    band = interval["pooled"].get("half_width_um_for_85_95")
    if band and not band[0] <= stored <= band[1]:
        side = "wider" if stored > band[1] else "narrower"
        lines.append(
            f"note: the stored half-width {stored:.2f} µm is {side} than these rows needed: "
            f"{band[0]:.2f}–{band[1]:.2f} µm would have covered {low:.0%}–{high:.0%} of them"
        )
    return lines


def report_lines(
    scored: ScoredModel,
    prepared: Prepared,
    figures: dict[str, dict[str, float | int]],
    found: list[Excursion],
) -> list[str]:
    """The header, one line per run and pooled, then what the figures cannot speak for."""
    data = prepared.data
    lines = [
        f"{Path(data.source).name}: {data.n_samples} rows, {len(data.run_ids)} runs, "
        f"{len(prepared.plan.recording_runs)} recording(s), target {data.target} (µm)",
        f"model {scored.banked.model_id} ({scored.method}, {scored.kind}), fitted on "
        f"{scored.fitted_on}; applied as the gateway runs it, no refit",
        f"{'run':<16} {'rows':>6} {'RMSE µm':>8} {'σ µm':>7} {'max|e| µm':>9}",
    ]
    for name, row in figures.items():
        lines.append(
            f"{name:<16} {row['n_samples']:>6} {row['rmse_um']:8.2f} {row['sigma_um']:7.2f} "
            f"{row['max_abs_um']:9.2f}"
        )
    if scored.heldout_rmse_um is not None:
        lines.append(f"held-out RMSE stored at fit: {scored.heldout_rmse_um:.2f} µm")
    if scored.training_range is None:
        lines.append(
            "note: the model file holds no training range (written by an earlier version): "
            "whether these data lie inside what it was fitted on is not checked"
        )
    for excursion in found:
        lines.append(f"warning: outside the training data: {excursion.describe()}")
    return lines
