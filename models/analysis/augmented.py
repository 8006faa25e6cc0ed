"""The model a residual analysis ends with: the declared model plus the effects it added.

Stored as its own JSON document (``<store>/augmented/<model_id>.json``) next to
the plain models, with its provenance: the base model, the effects in the
order they were added with their parameters, the data fingerprint and the
held-out error before and after. It is kept in a sub-folder because its effect
terms need time and filter states (lags since the reference): the runtime's
model bank loads it apart from the plain models, and the machine loop runs it
sample by sample (:mod:`models.online.streaming`), carrying those states.

Every reader checks ``format_version`` (:data:`SUPPORTED_VERSIONS`) and names the
file: a document of a newer format is refused, never run as if it were an older
one. With a signing key (:mod:`models.signing`) :func:`save` signs and
:func:`load` requires the signature, over the bytes the checksum covers.

``predict`` rebuilds every term from a prepared data set exactly as the
analysis did, so a stored document can be checked against fresh data.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from models import signing
from models.analysis.result import AnalysisResult
from models.base import ThermalModel
from models.data.features import Prepared
from models.data.lag_terms import candidate_families
from models.estimators.registry import METHODS, make_model
from models.json_files import write_json_atomic
from models.store import StoreError, data_fingerprint, refuse_non_finite, safe_model_id
from models.training_range import training_range

if TYPE_CHECKING:  # the search (and scipy.stats, 2 s to import) only where an analysis runs
    from models.analysis.search import Accepted, ResidualAnalysis

FORMAT = "thermal-gateway-augmented-model"
#: 2: a ridge or PLS base is one term, its penalised prediction (see :func:`stored_base`).
FORMAT_VERSION = 2
#: the format versions this software reads (1: before ridge and PLS bases were one term)
SUPPORTED_VERSIONS = (1, 2)
FOLDER = "augmented"


def fit_augmented(
    analysis: ResidualAnalysis, accepted: list[Accepted]
) -> tuple[ThermalModel, np.ndarray, list[dict[str, Any]]]:
    """Base model fitted on the analysis's rows, then every coefficient refitted jointly with
    the effects.

    Returns the base model (its structure), the coefficients (intercept, base
    terms, effect terms) and the effects as stored. The base is fitted with
    ``fit_rows`` on the whole recording: a base with lag terms (lag-ridge) builds them
    over every row, so the rows left out (a held-out run, the rows between probes)
    still carry the heat of the rows before them.
    """
    base, design, effects = _augmented_design(analysis, accepted)
    return base, _coefficients(analysis, design), effects


def augmented_prediction(analysis: ResidualAnalysis, accepted: list[Accepted]) -> np.ndarray:
    """The fitted augmented model's prediction (µm) on every row of the analysis's data,
    the rows it was not fitted on included (a held-out run). An effect found inside a
    lag-ridge base is that base refitted with the effect as an input."""
    inside = getattr(analysis, "inside", None)
    if inside is not None:
        from models.analysis.inside import fitted_inside_prediction

        return fitted_inside_prediction(analysis, inside)
    _, design, _ = _augmented_design(analysis, accepted)
    return design @ _coefficients(analysis, design)


def _coefficients(analysis: ResidualAnalysis, design: np.ndarray) -> np.ndarray:
    """Least squares on the rows with a known target (every row unless probe rows only)."""
    rows = analysis.fit_rows
    coef, *_ = np.linalg.lstsq(design[rows], analysis.y[rows], rcond=None)
    return coef


def _augmented_design(
    analysis: ResidualAnalysis, accepted: list[Accepted]
) -> tuple[ThermalModel, np.ndarray, list[dict[str, Any]]]:
    prepared = analysis.prepared
    base = make_model(analysis.method, analysis.base.sensors).fit_rows(
        prepared.inputs, prepared.error_um, analysis.fit_rows
    )
    columns = [np.ones((prepared.data.n_samples, 1)), base.design_matrix(prepared.inputs)]
    effects = []
    for a in accepted:
        block = a.family.variants[a.overall].build()
        columns.append(block)
        effects.append({"effect": a.family.effect, "params": a.params, "terms": block.shape[1]})
    return base, np.column_stack(columns), effects


def build_augmented_document(
    analysis: ResidualAnalysis,
    accepted: list[Accepted],
    result: AnalysisResult,
    model_id: str,
    software_version: str,
) -> dict[str, Any]:
    base, coef, effects = fit_augmented(analysis, accepted)
    prepared = analysis.prepared
    document: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model_id": safe_model_id(model_id),
        "base": {
            "method": base.method,
            "hyperparams": base.hyperparams(),
            "params": base.fitted_params(),
        },
        "effects": effects,
        "effect_sensors": list(analysis.base.used_sensors),
        "coefficients": {
            "intercept_um": float(coef[0]),
            "all_um_per_unit": [float(c) for c in coef],
            "order": "intercept, the base model's terms, then each effect's terms in order",
        },
        "target": {"name": prepared.data.target, "unit": "µm"},
        "reference": prepared.plan.describe(),
        "provenance": {
            "base_model": base.method,
            "effects_added": [e["effect"] for e in effects],
            "source_file": Path(prepared.data.source).name,
            "data_sha256": data_fingerprint(prepared.inputs, prepared.error_um),
            "rows": prepared.data.n_samples,
            "runs": list(prepared.data.run_ids),
            "training_range": training_range(prepared.inputs),
            "validation": result.validation,
            "before": result.before.as_dict(),
            "after": result.after.as_dict(),
            "steps": [step.as_dict() | {"candidates": None} for step in result.steps],
        },
        "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "software_version": software_version,
    }
    document = json.loads(json.dumps(document, ensure_ascii=False))
    document["sha256"] = _checksum(document)
    return document


def save(document: dict[str, Any], store_dir: str | Path) -> Path:
    """Write ``document`` into the store's augmented folder, signed (the key made on first use)
    unless the store is declared unsigned."""
    refuse_non_finite(document)
    path = Path(store_dir) / FOLDER / f"{document['model_id']}.json"
    document = sign(document, signing.key_for_store(store_dir, create=True))
    return write_json_atomic(path, document)


def load(path: str | Path, key: bytes | None = None) -> dict[str, Any]:
    """Read a stored augmented model and check its format, version, checksum and signature
    (``key``, default the key of the store the file is in)."""
    path = Path(path)
    document = _read_object(path)
    if key is None:
        try:
            key = signing.key_for_store(path.parent.parent)
        except signing.SigningError as exc:
            raise StoreError(str(exc)) from None
    check(document, str(path), key)
    return document


def check(document: dict[str, Any], where: str, key: bytes | None) -> None:
    """Raise StoreError (naming ``where``) unless ``document`` is an augmented model of a
    supported format version, whole (checksum) and, with ``key``, signed by it."""
    if document.get("format") != FORMAT:
        raise StoreError(f"{where}: not an augmented model (format {document.get('format')!r})")
    version = document.get("format_version")
    if version not in SUPPORTED_VERSIONS:
        raise StoreError(
            f"{where}: format_version {version!r} is not supported (this software reads "
            f"versions {', '.join(map(str, SUPPORTED_VERSIONS))}); a newer gateway wrote it"
        )
    if document.get("sha256") != _checksum(document):
        raise StoreError(f"{where}: checksum mismatch: the file was changed after it was written")
    try:
        signing.verify(document, key, canonical_bytes(document), where)
    except signing.SigningError as exc:
        raise StoreError(str(exc)) from None


def _read_object(path: Path) -> dict[str, Any]:
    """The JSON object in ``path``, unchecked; StoreError (naming the file) otherwise."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as err:
        raise StoreError(f"{path}: cannot read an augmented model: {err}") from None
    if not isinstance(document, dict):
        raise StoreError(f"{path}: a JSON object was expected at the top level")
    return document


def sign_unsigned(store_dir: str | Path, key: bytes) -> list[Path]:
    """Sign every unsigned augmented model of the store (``models sign``), each checked whole
    first; one with a wrong signature is refused (StoreError). Returns the files signed."""
    signed = []
    for path in sorted((Path(store_dir) / FOLDER).glob("*.json")):
        document = _read_unsigned(path, key)
        if document is not None:
            write_json_atomic(path, sign(document, key))
            signed.append(path)
    return signed


def _read_unsigned(path: Path, key: bytes) -> dict[str, Any] | None:
    """The augmented model in ``path`` if it is unsigned and whole; None if it is validly
    signed with ``key``; StoreError otherwise."""
    document = _read_object(path)
    if signing.FIELD in document:
        check(document, str(path), key)
        return None
    check(document, str(path), None)
    return document


def sign(document: dict[str, Any], key: bytes | None) -> dict[str, Any]:
    """``document`` signed with ``key`` (unchanged without one)."""
    return signing.sign(document, key, canonical_bytes(document))


def stored_base(document: Mapping[str, Any]) -> ThermalModel:
    """The base model of a stored augmented model, as its terms were fitted.

    Documents before format 2 with a ridge or PLS base stored the coefficients of
    the base's sensors refitted by least squares (the analysis undid the penalty):
    their base terms are those rises, an mlr on the same sensors.
    """
    info = document["base"]
    method = info["method"]
    if method not in METHODS:
        raise StoreError(f"{document.get('model_id')}: unknown base method {method!r}")
    if document.get("format_version", 1) < 2 and method in ("ridge", "pls"):
        method = "mlr"
    return METHODS[method].from_params(info["hyperparams"], info["params"])


def stored_design(document: Mapping[str, Any], prepared: Prepared) -> np.ndarray:
    """The design (intercept, base terms, effect terms) of a stored augmented model."""
    base = stored_base(document)
    columns = [np.ones((prepared.data.n_samples, 1)), base.design_matrix(prepared.inputs)]
    effect_sensors = tuple(document.get("effect_sensors", base.sensors_used_))
    families = {f.effect: f for f in candidate_families(prepared, effect_sensors)}
    for effect in document["effects"]:
        family = families.get(effect["effect"])
        matches = (
            [] if family is None else [v for v in family.variants if v.params == effect["params"]]
        )
        if not matches:
            raise StoreError(
                f"this data cannot provide the effect {effect['effect']} {effect['params']}"
            )
        columns.append(matches[0].build())
    return np.column_stack(columns)


def predict(document: dict[str, Any], prepared: Prepared) -> np.ndarray:
    """Predicted error (µm) of a stored augmented model on prepared data."""
    design = stored_design(document, prepared)
    coef = np.asarray(document["coefficients"]["all_um_per_unit"], dtype=float)
    if design.shape[1] != coef.size:
        raise StoreError(f"{coef.size} coefficients stored for {design.shape[1]} terms")
    return design @ coef


def sealed(document: dict[str, Any]) -> dict[str, Any]:
    """``document`` as plain JSON with its checksum, as :func:`load` checks it (a signature
    it carries is kept: the checksum does not cover it)."""
    document = json.loads(json.dumps(document, ensure_ascii=False))
    document.pop("sha256", None)
    document["sha256"] = _checksum(document)
    return document


def canonical_bytes(document: dict[str, Any]) -> bytes:
    """What the checksum and the signature cover: every field but those two."""
    content = {k: v for k, v in document.items() if k not in ("sha256", signing.FIELD)}
    return json.dumps(content, sort_keys=True, ensure_ascii=False).encode("utf-8")


def _checksum(document: dict[str, Any]) -> str:
    return hashlib.sha256(canonical_bytes(document)).hexdigest()
