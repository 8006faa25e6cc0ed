"""The model store: fitted models as JSON files in one folder, never pickle.

One file per model, ``<model_id>.json``, holding everything the runtime and an
auditor need: the method and its hyperparameters, every input with its unit, how
the temperature and error references are taken, the fitted numbers, the
training-data fingerprint, the regime label, validation figures and the creation
time.

Two guards on load, so that a damaged or incompatible file is refused instead of
compensating a machine wrongly:

- ``sha256``: a checksum of the file's canonical content (all keys but itself);
  any edited or corrupted number changes it.
- ``probe``: a few training rows' inputs and the predictions the fitted model
  made for them when it was saved. The loaded model must reproduce them exactly;
  this catches a file written by a different, incompatible version of the maths.

Optional fields ``error_reference`` and ``sensor_relations`` (absent in files
saved before they existed, which still load). ``error_reference``: the model's
error at zero rises and 0 r/min, i.e. the error's reference fitted as the
model's intercept (:mod:`models.data.references`). ``sensor_relations``: how the
training sensors' rises relate to each other (:mod:`models.estimators.sensor_relations`),
for the runtime's plausibility check. Both are covered by the checksum like
every other field and validated on load.

Writes go to a temporary file that is then renamed, so a crash mid-write never
leaves half a model behind.

``signature`` (:mod:`models.signing`): an HMAC of the bytes the checksum covers,
written by :meth:`ModelStore.save` (the key made on first use) and required by
:func:`load_file`, checked before the probe so that a forged model is refused for
its signature; the checksum proves the file is whole, the signature that it was
written by a holder of the key. Only a store declared unsigned
(``models.signing: false``) is neither signed nor checked.
"""

from __future__ import annotations

import hashlib
import json
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from models import signing
from models.base import ModelInputs, ThermalModel
from models.estimators.registry import METHODS
from models.estimators.sensor_relations import SensorRelations
from models.json_files import write_json_atomic
from models.training_range import training_range

FORMAT = "spindle-thermal-model"
FORMAT_VERSION = 1
PROBE_ROWS = 5


class StoreError(ValueError):
    """A model file that cannot be used, with the file and what is wrong."""


class Probe(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sensors: list[str]
    rise_C: list[list[float]]
    speed_rpm: list[float]
    predicted_um: list[float]


class TrainingData(BaseModel):
    model_config = ConfigDict(extra="forbid")
    file: str
    data_sha256: str
    rows: int
    runs: list[str]
    target: str


class StoredModel(BaseModel):
    """The file format (version 1). Unknown keys are refused, not ignored."""

    model_config = ConfigDict(extra="forbid")
    format: Literal["spindle-thermal-model"]
    format_version: Literal[1]
    model_id: str
    method: str
    hyperparams: dict[str, Any]
    inputs: dict[str, str]
    target: dict[str, str]
    reference: dict[str, Any]
    params: dict[str, Any]
    training_data: TrainingData
    regime: str
    validation: dict[str, Any]
    created_utc: str
    software_version: str
    probe: Probe
    sha256: str
    #: conditioning and bias sensitivity at fit time (:mod:`models.fit.conditioning`);
    #: absent in files written before it was recorded.
    conditioning: dict[str, Any] | None = None
    # Optional, so that files saved before it existed still load (see the module docstring).
    sensor_relations: dict[str, Any] | None = None
    #: the error's reference (:mod:`models.data.references`): the fitted model's error at zero
    #: rises and 0 r/min (its intercept) and each training recording's own origin; absent
    #: in files written when the error was rebased on each recording's leading readings.
    error_reference: dict[str, Any] | None = None
    #: the span of each input in the training rows (:mod:`models.training_range`), for
    #: ``score``; absent in files written before it was recorded.
    training_range: dict[str, Any] | None = None
    #: the calibrated prediction interval (:mod:`models.fit.interval`); absent in files
    #: written before it was recorded (interval unknown) or with too few held-out samples.
    interval: dict[str, Any] | None = None
    #: HMAC of the checksummed content (:mod:`models.signing`); absent in an unsigned store.
    signature: dict[str, Any] | None = None

    def relations(self) -> SensorRelations | None:
        """The training sensors' relations, or None for a file saved without them."""
        if self.sensor_relations is None:
            return None
        return SensorRelations.from_document(self.sensor_relations)


def data_fingerprint(inputs: ModelInputs, error_um: np.ndarray) -> str:
    """sha256 of the training arrays (names, rises, speed, error) — not of file formatting."""
    digest = hashlib.sha256()
    digest.update(json.dumps(list(inputs.sensors)).encode())
    for array in (inputs.rise_C, inputs.speed_rpm, np.asarray(error_um, dtype=float)):
        values = np.ascontiguousarray(array, dtype="<f8")
        digest.update(values.data.cast("B") if values.size else b"")  # no copy
    return digest.hexdigest()


def canonical_bytes(document: dict[str, Any]) -> bytes:
    """What the checksum and the signature cover: every field but those two, canonical JSON."""
    content = {k: v for k, v in document.items() if k not in ("sha256", signing.FIELD)}
    canonical = json.dumps(content, sort_keys=True, ensure_ascii=False, separators=(",", ":"))
    return canonical.encode()


def _checksum(document: dict[str, Any]) -> str:
    return hashlib.sha256(canonical_bytes(document)).hexdigest()


def safe_model_id(text: str) -> str:
    """A file-name-safe id: letters, digits, '-', '_' and '.' only."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.")
    if not cleaned:
        raise StoreError(f"cannot make a model id from '{text}'")
    return cleaned


def _probe(model: ThermalModel, inputs: ModelInputs) -> Probe:
    rows = np.unique(np.linspace(0, inputs.n_samples - 1, PROBE_ROWS).astype(int))
    # single rows without their history (no time), as probe_inputs reloads them
    sample = ModelInputs(inputs.rise_C[rows], inputs.sensors, inputs.speed_rpm[rows])
    return Probe(
        sensors=list(inputs.sensors),
        rise_C=sample.rise_C.tolist(),
        speed_rpm=sample.speed_rpm.tolist(),
        predicted_um=model.predict(sample).tolist(),
    )


def build_document(
    model: ThermalModel,
    *,
    model_id: str,
    inputs: ModelInputs,
    error_um: np.ndarray,
    target: str,
    source_file: str,
    runs: list[str],
    reference: dict[str, Any],
    regime: str,
    validation: dict[str, Any],
    software_version: str,
    conditioning: dict[str, Any] | None = None,
    sensor_relations: dict[str, Any] | None = None,
    interval: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The JSON document for a fitted model (checksum included).

    ``sensor_relations``: :meth:`models.estimators.sensor_relations.SensorRelations.as_document`
    of the training rises, stored for the runtime's plausibility check. ``interval``:
    :func:`models.fit.interval.calibrate` of the held-out residuals.
    """
    document: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model_id": safe_model_id(model_id),
        "method": model.method,
        "hyperparams": model.hyperparams(),
        "inputs": model.input_units(),
        "target": {
            "name": target,
            "unit": "µm",
            "meaning": "thermal Z error as measured; positive = tool towards table",
        },
        "reference": reference,
        "params": model.fitted_params(),
        "training_data": {
            "file": Path(source_file).name,
            "data_sha256": data_fingerprint(inputs, error_um),
            "rows": inputs.n_samples,
            "runs": runs,
            "target": target,
        },
        "regime": regime,
        "validation": validation,
        "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "software_version": software_version,
        "probe": _probe(model, inputs).model_dump(),
    }
    if conditioning is not None:
        document["conditioning"] = conditioning
    document["training_range"] = training_range(inputs)
    if sensor_relations is not None:
        document["sensor_relations"] = sensor_relations
    document["error_reference"] = error_reference_record(model, inputs.sensors, reference)
    if interval is not None:
        document["interval"] = interval
    # Round-trip through JSON so the checksum covers exactly what is written.
    document = json.loads(json.dumps(document, ensure_ascii=False))
    document["sha256"] = _checksum(document)
    return document


def error_reference_record(
    model: ThermalModel, sensors: tuple[str, ...], reference: dict[str, Any]
) -> dict[str, Any]:
    """The error's reference as stored with a model (field ``error_reference``)."""
    cold = ModelInputs(rise_C=np.zeros((1, len(sensors))), sensors=sensors, speed_rpm=np.zeros(1))
    origins = reference.get("error_reference", {}).get("origin_um", [])
    return {
        "intercept_um": float(model.predict(cold)[0]),
        "meaning": (
            "the model's error at zero rises and 0 r/min: the probe's zero on the cold machine "
            "at rest, fitted with the model on every training recording; the runtime "
            "compensates the prediction as it is and never rebases the error"
        ),
        "recording_origin_um": [float(v) for v in origins],
    }


def refuse_non_finite(document: dict[str, Any]) -> None:
    """Raise StoreError naming the first number in ``document`` that is NaN or infinite."""
    found = _first_non_finite(document, "")
    if found is not None:
        where, value = found
        raise StoreError(
            f"model '{document.get('model_id', '?')}' not saved: {where} is {value!r}; "
            "a model whose numbers or figures are not finite is never stored"
        )


def _first_non_finite(value: Any, where: str) -> tuple[str, float] | None:
    if isinstance(value, float):
        return None if np.isfinite(value) else (where, value)
    if isinstance(value, dict):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in value.items())
    elif isinstance(value, list | tuple):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for path, item in items:
        found = _first_non_finite(item, path)
        if found is not None:
            return found
    return None


def model_from_document(document: StoredModel) -> ThermalModel:
    cls = METHODS.get(document.method)
    if cls is None:
        raise StoreError(f"unknown method '{document.method}' (known: {sorted(METHODS)})")
    return cls.from_params(document.hyperparams, document.params)


class ModelStore:
    """A folder of model files."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def path_of(self, model_id: str) -> Path:
        return self.root / f"{safe_model_id(model_id)}.json"

    def save(self, document: dict[str, Any]) -> Path:
        """Validate ``document`` as a loader would, then write it atomically.

        A model whose numbers or figures are not finite (an RMSE of ``inf``, a
        NaN coefficient) is refused: it would compensate a machine wrongly.
        """
        refuse_non_finite(document)
        StoredModel.model_validate(document)
        key = signing.key_for_store(self.root, create=True)
        document = signing.sign(document, key, canonical_bytes(document))
        return write_json_atomic(self.path_of(document["model_id"]), document, allow_nan=False)

    def load(self, model_id: str) -> tuple[ThermalModel, StoredModel]:
        path = self.path_of(model_id)
        model, document = load_file(path)
        check_named_after(path, document.model_id)
        return model, document

    def ids(self) -> list[str]:
        return sorted(p.stem for p in self.root.glob("*.json"))


def check_named_after(path: Path, model_id: str) -> None:
    """Raise StoreError unless the store's file ``path`` is named after the model it holds.

    The regime rules, the promoted entries (``replaces``) and the logs name a model by
    its id, and a store finds it by its file name: two files whose contents were
    swapped (or a file copied in under another name) would serve one model in the
    other's place, each checksum and signature still valid."""
    if path.stem != model_id:
        raise StoreError(
            f"{path}: holds model '{model_id}', not '{path.stem}': a store's file is named "
            f"after the model it holds ({model_id}.json); put the right file back, or rename it"
        )


def load_file(
    path: str | Path, *, check_signature: bool = True
) -> tuple[ThermalModel, StoredModel]:
    """Load, validate and self-check one model file (and its signature, with the key of its
    store: :func:`models.signing.key_for_store`; ``check_signature`` False only to sign an
    unsigned file, :func:`sign_unsigned_models`)."""
    path = Path(path)
    raw = _read_model_json(path)
    try:
        document = StoredModel.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"])
        raise StoreError(f"{path}: field '{where}': {first['msg']}") from None
    if _checksum(raw) != document.sha256:
        raise StoreError(
            f"{path}: checksum mismatch — the file was changed or damaged since it was saved"
        )
    try:
        if check_signature:
            key = signing.key_for_store(path.parent)
            signing.verify(raw, key, canonical_bytes(raw), str(path))
    except signing.SigningError as exc:
        raise StoreError(str(exc)) from None
    try:
        document.relations()
    except ValueError as exc:
        raise StoreError(f"{path}: field 'sensor_relations': {exc}") from None
    try:
        model = model_from_document(document)
    except (KeyError, TypeError, ValueError) as exc:
        raise StoreError(
            f"{path}: fitted numbers do not fit method '{document.method}': {exc}"
        ) from None
    probe = document.probe
    replay = model.predict(probe_inputs(document))
    if not np.array_equal(replay, np.asarray(probe.predicted_um, dtype=float)):
        raise StoreError(
            f"{path}: the model does not reproduce its saved probe predictions "
            f"(saved {probe.predicted_um}, now {replay.tolist()}); it was written by an "
            "incompatible version"
        )
    return model, document


def _read_model_json(path: Path) -> dict[str, Any]:
    """The file's JSON object, of this format and a format version read here (StoreError)."""
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StoreError(f"{path}: no such model file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StoreError(f"{path}: not a readable JSON model file ({exc})") from None
    if not isinstance(raw, dict):
        raise StoreError(f"{path}: a JSON object was expected at the top level")
    if raw.get("format") != FORMAT:
        raise StoreError(
            f"{path}: not a model file (format '{raw.get('format')}', expected '{FORMAT}')"
        )
    if raw.get("format_version") != FORMAT_VERSION:
        raise StoreError(
            f"{path}: format_version {raw.get('format_version')!r} is not supported "
            f"(this software reads version {FORMAT_VERSION})"
        )
    return raw


def sign_unsigned_models(store_dir: Path, key: bytes) -> list[Path]:
    """Sign every unsigned model file of the store with ``key`` (``models sign``): each must
    be whole, named after its model and reproduce its probe first. A file carrying a
    signature is left as it is, and one whose signature is wrong for ``key`` is refused
    (StoreError): signing it again would make a forged model valid. Returns the files signed."""
    signed = []
    for path in sorted(Path(store_dir).glob("*.json")):
        raw = _read_model_json(path)
        if signing.FIELD in raw:
            try:
                signing.verify(raw, key, canonical_bytes(raw), str(path))
            except signing.SigningError as exc:
                raise StoreError(f"{exc}; not signed again") from None
            continue
        _, document = load_file(path, check_signature=False)
        check_named_after(path, document.model_id)
        write_json_atomic(path, signing.sign(raw, key, canonical_bytes(raw)), allow_nan=False)
        signed.append(path)
    return signed


def probe_inputs(document: StoredModel) -> ModelInputs:
    """The saved probe rows as model inputs (a few training rows the model was fitted on)."""
    probe = document.probe
    return ModelInputs(
        rise_C=np.asarray(probe.rise_C, dtype=float).reshape(-1, len(probe.sensors)),
        sensors=tuple(probe.sensors),
        speed_rpm=np.asarray(probe.speed_rpm, dtype=float),
    )
