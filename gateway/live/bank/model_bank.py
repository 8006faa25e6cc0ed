"""The fitted models a machine can use, loaded and checked once at start-up.

Every file of the store is loaded through :func:`models.store.load_file` (which
refuses damaged or incompatible files, and an unsigned or wrongly signed one unless the
store is declared unsigned: :mod:`models.signing`), and a file whose model id is not
its file name (:func:`models.store.check_named_after`). Augmented models (a declared model plus
the effects residual analysis added, ``<store>/augmented/*.json``) are loaded
through :func:`models.analysis.augmented.load` (format and checksum) and checked by
building their sample-by-sample form (:mod:`models.online.streaming`); their lag
states are carried by the machine loop, not here. The regime rules name models
of both kinds by id; when a sensor a model needs goes bad, the bank offers a
*fallback*: another stored model that does without that sensor, preferring one
fitted for the same regime, then the one with the lowest held-out RMSE.

A machine compensates one quantity per axis (one target, in one unit), so every model of
a store must predict the same target in the same unit: a fallback fitted for
another probe channel would put another channel's error into the macro. The bank
refuses a store whose models disagree, naming each model and its target. A machine
with several axes (``compensation.axes``) keeps every axis's models in one bank:
there each target name must come in one unit, and an axis takes its model and its
fallbacks among the models of its own target only (:meth:`ModelBank.usable`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from models import signing
from models.analysis import augmented
from models.base import ThermalModel
from models.data.dataset import AMBIENT_COLUMN
from models.estimators.sensor_relations import SensorRelations
from models.fit.conditioning import bias_sensitivity
from models.online.streaming import StreamingAugmented
from models.store import StoredModel, check_named_after, load_file, probe_inputs

log = logging.getLogger(__name__)

#: ``load_file``'s verdicts in this process, by file version and signing key: a store
#: shared by many machines (1000 in one configuration) is read and checked once, not
#: once per machine; a file changed since (or another key) is read again.
_checked_files: dict[tuple[Any, ...], tuple[ThermalModel, StoredModel]] = {}


def load_checked(path: Path, signing_key: bytes | None) -> tuple[ThermalModel, StoredModel]:
    """:func:`models.store.load_file`, once per version of ``path`` per process.

    ``signing_key`` is the store's (:func:`models.signing.key_for_store`), looked up
    once per store by the caller: resolving paths per file cost 3 s for 1000 machines.
    The version is the file's device, inode, change time and size (a file replaced
    or rewritten since is read again).
    """
    stat = path.stat()
    key = (stat.st_dev, stat.st_ino, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_size, signing_key)
    if key not in _checked_files:
        _checked_files[key] = load_file(path)
    return _checked_files[key]


#: ``BankedModel.bias_sensitivity_um_per_C`` by model object (kept, so its id stays its own).
_sensitivities: dict[int, tuple[ThermalModel, StoredModel, dict[str, float]]] = {}


#: ``BankedModel.relations`` by stored document (kept, so its id stays its own): fitting
#: the relations from their moments took 33 ms a model, 6.7 s CPU for 1000 machines.
_relations: dict[int, tuple[StoredModel, SensorRelations | None]] = {}


@dataclass(frozen=True)
class Target:
    """What a model predicts: the measured error column it was fitted to, and its unit."""

    name: str
    unit: str

    def __str__(self) -> str:
        return f"{self.name} ({self.unit})"


@dataclass(frozen=True)
class BankedModel:
    """A plain model: predicts from one cycle's rises."""

    model_id: str
    model: ThermalModel
    document: StoredModel

    @property
    def sensors(self) -> frozenset[str]:
        return frozenset(self.model.sensors_used_)

    @property
    def regime(self) -> str | None:
        return self.document.regime

    @property
    def target(self) -> Target:
        return Target(self.document.target.get("name", "?"), self.document.target.get("unit", "?"))

    @property
    def held_out_rmse_um(self) -> float:
        pooled = self.document.validation.get("pooled") or {}
        return float(pooled.get("rmse_um", float("inf")))

    def relations(self) -> SensorRelations | None:
        """The training sensors' relations (:meth:`StoredModel.relations`), built once per
        stored document: machines sharing a store share them (read-only but for the
        subsets each solves once and keeps)."""
        known = _relations.get(id(self.document))
        if known is None or known[0] is not self.document:
            known = _relations[id(self.document)] = (self.document, self.document.relations())
        return known[1]

    def bias_sensitivity_um_per_C(self) -> dict[str, float]:
        """µm per °C of bias on each sensor, from the model itself on its probe rows
        (worked out once per model object: machines sharing a store share them)."""
        known = _sensitivities.get(id(self.model))
        if known is None or known[0] is not self.model or known[1] is not self.document:
            found = bias_sensitivity(self.model, probe_inputs(self.document))
            known = _sensitivities[id(self.model)] = (self.model, self.document, found)
        return dict(known[2])


@dataclass(frozen=True)
class BankedAugmented:
    """An augmented model: its prediction needs lag states carried from cycle to cycle.

    ``sensors`` are the machine sensors it needs, the ambient sensor included
    when it has an ``ambient`` term (``ambient_sensor`` names it).
    """

    model_id: str
    document: dict[str, Any]
    sensors: frozenset[str]
    ambient_sensor: str | None
    regime: str | None = None
    #: µm per °C of bias per sensor, for a plain model stepped with lag states
    #: (:meth:`from_plain`); None for an ``analyze`` result (judged by its analysis).
    sensitivity_um_per_C: dict[str, float] | None = None
    #: the calibrated interval and the training span of a stored plain model
    #: (:mod:`gateway.live.interval`); None for an ``analyze`` result or a file without them.
    interval: dict[str, Any] | None = None
    training_range: dict[str, Any] | None = None

    @classmethod
    def from_plain(cls, model: ThermalModel, document: StoredModel) -> BankedAugmented:
        """A plain model whose own terms carry lag states (``lag-ridge``), stepped like an
        augmented model: its prediction is the one base term, no effects."""
        wrapped = {
            "model_id": document.model_id,
            "base": {
                "method": document.method,
                "hyperparams": document.hyperparams,
                "params": document.params,
            },
            "effects": [],
            "effect_sensors": list(model.sensors_used_),
            "coefficients": {
                "intercept_um": 0.0,
                "all_um_per_unit": [0.0, 1.0],
                "order": "intercept, the model's prediction",
            },
            "target": dict(document.target),
            "provenance": {"after": (document.validation or {}).get("pooled")},
            "sha256": document.sha256,
        }
        stream = StreamingAugmented(wrapped)
        return cls(
            model_id=stream.model_id,
            document=wrapped,
            sensors=frozenset(stream.sensors),
            ambient_sensor=None,
            regime=document.regime,
            sensitivity_um_per_C=bias_sensitivity(model, probe_inputs(document)),
            interval=document.interval,
            training_range=document.training_range,
        )

    @classmethod
    def from_document(cls, document: dict[str, Any], ambient_sensor: str) -> BankedAugmented:
        stream = StreamingAugmented(document)  # refuses effects or coefficients it cannot run
        needed = set(stream.sensors)
        if stream.uses_ambient:
            needed.add(ambient_sensor)
        return cls(
            model_id=stream.model_id,
            document=document,
            sensors=frozenset(needed),
            ambient_sensor=ambient_sensor if stream.uses_ambient else None,
        )

    @property
    def target(self) -> Target:
        target = self.document.get("target") or {}
        return Target(str(target.get("name", "?")), str(target.get("unit", "?")))

    @property
    def held_out_rmse_um(self) -> float:
        after = self.document.get("provenance", {}).get("after") or {}
        return float(after.get("rmse_um", float("inf")))

    def stream(self) -> StreamingAugmented:
        """A fresh sample-by-sample form of this model (no state yet)."""
        return StreamingAugmented(self.document)


Banked = BankedModel | BankedAugmented


def refuse_mixed_targets(models: Iterable[Banked], where: str = "model store") -> None:
    """Refuse models that do not all predict the same target in the same unit."""
    by_target: dict[Target, list[str]] = {}
    for model in models:
        by_target.setdefault(model.target, []).append(model.model_id)
    if len(by_target) > 1:
        listed = "; ".join(
            f"{target}: {', '.join(sorted(ids))}"
            for target, ids in sorted(by_target.items(), key=str)
        )
        raise ValueError(
            f"{where}: its models predict different targets ({listed}); a machine compensates "
            "one target, so keep only that target's models in its store"
        )


class ModelBank:
    def __init__(
        self, models: Iterable[Banked], where: str = "model store", several_targets: bool = False
    ) -> None:
        self.models: dict[str, Banked] = {}
        for model in models:
            if model.model_id in self.models:
                raise ValueError(f"model id '{model.model_id}' is in the store twice")
            self.models[model.model_id] = model
        #: Models of several targets (a multi-axis machine): one unit per target name.
        self.several_targets = several_targets
        if not several_targets:
            refuse_mixed_targets(self.models.values(), where)
        by_name: dict[str, list[Banked]] = {}
        for model in self.models.values():
            by_name.setdefault(model.target.name, []).append(model)
        for same_name in by_name.values():
            refuse_mixed_targets(same_name, where)
        #: Promoted models (:mod:`gateway.live.bank.promotion`): the id of the model each one serves
        #: in place of (None: every regime) → the promoted model's id.
        self.promoted: dict[str | None, str] = {}

    def set_promoted(self, promoted: Iterable[tuple[BankedAugmented, str | None]]) -> None:
        """Replace the promoted models: each serves in place of the model it names (or all).

        The caller has checked them (:func:`gateway.live.bank.promotion.check_promoted`); their
        ids must not be those of the store's own models.
        """
        for model_id in self.promoted.values():
            self.models.pop(model_id, None)
        self.promoted = {}
        for banked, replaces in promoted:
            self.models[banked.model_id] = banked
            self.promoted[replaces] = banked.model_id

    def serving(self, model_id: str | None) -> str | None:
        """The id of the model that serves where the regime rules name ``model_id``."""
        if model_id in self.promoted:
            return self.promoted[model_id]
        return self.promoted.get(None, model_id)

    @property
    def target(self) -> Target | None:
        """The one target every model predicts (None for an empty bank); for a bank of
        several targets, the first model's."""
        return next((m.target for m in self.models.values()), None)

    def targets_of(self, model_id: str | None = None) -> set[Target]:
        """What a model served in place of ``model_id`` must predict: that model's target,
        or (None, or a model not in the bank) any target of the bank's models."""
        if model_id is not None and model_id in self.models:
            return {self.models[model_id].target}
        return {m.target for m in self.models.values()}

    @classmethod
    def from_store(
        cls, folder: Path, ambient_sensor: str | None = None, several_targets: bool = False
    ) -> ModelBank:
        """Plain models from ``folder/*.json``, augmented ones from ``folder/augmented/*.json``.

        ``ambient_sensor``: the machine sensor feeding augmented models' ambient
        terms (default ``ambient_C``, which a machine without such a sensor lacks).
        ``several_targets``: a multi-axis machine's store (one unit per target name).
        """
        if not folder.is_dir():
            raise ValueError(f"model store {folder}: no such folder")
        loaded: list[Banked] = []
        signing_key = signing.key_for_store(folder)
        for path in sorted(folder.glob("*.json")):
            model, document = load_checked(path, signing_key)
            check_named_after(path, document.model_id)
            if callable(getattr(model, "stream", None)):  # its terms carry lag states
                loaded.append(BankedAugmented.from_plain(model, document))
            else:
                loaded.append(BankedModel(document.model_id, model, document))
        for path in sorted((folder / augmented.FOLDER).glob("*.json")):
            stored = augmented.load(path)
            check_named_after(path, str(stored.get("model_id")))
            loaded.append(BankedAugmented.from_document(stored, ambient_sensor or AMBIENT_COLUMN))
        if not loaded:
            raise ValueError(
                f"model store {folder}: no model files (*.json, {augmented.FOLDER}/*.json)"
            )
        return cls(loaded, where=f"model store {folder}", several_targets=several_targets)

    def __contains__(self, model_id: str) -> bool:
        return model_id in self.models

    def get(self, model_id: str) -> Banked:
        try:
            return self.models[model_id]
        except KeyError:
            raise KeyError(
                f"model '{model_id}' is not in the store (have: {sorted(self.models)})"
            ) from None

    def augmented(self) -> list[BankedAugmented]:
        return [m for m in self.models.values() if isinstance(m, BankedAugmented)]

    def check_sensors(self, available: Iterable[str]) -> None:
        """Refuse a store whose models need sensors the machine does not have."""
        available = set(available)
        for banked in self.models.values():
            missing = sorted(banked.sensors - available)
            if missing:
                raise ValueError(
                    f"model '{banked.model_id}' needs sensor(s) {missing} that no transmitter "
                    f"channel provides (channels: {sorted(available)})"
                )

    def refuse_sensitive(self, sensor_accuracy_C: float, limit_um: float) -> dict[str, str]:
        """Drop plain models that one sensor off by ``sensor_accuracy_C`` moves beyond ``limit_um``.

        A bias that small passes every range, rate and stuck check, so such a
        model would put an error of that size into the part unnoticed
        (:mod:`models.fit.conditioning`). Returns the refused ids with the reason.
        Augmented models are judged by the residual analysis that made them; a plain model
        with lag states (``lag-ridge``) by its steady-state sensitivity.
        """
        refused: dict[str, str] = {}
        for model_id, banked in list(self.models.items()):
            if isinstance(banked, BankedModel):
                sensitivity = banked.bias_sensitivity_um_per_C()
            elif banked.sensitivity_um_per_C is not None:
                sensitivity = banked.sensitivity_um_per_C
            else:
                continue
            if not sensitivity:
                continue
            worst = max(sensitivity, key=lambda s: abs(sensitivity[s]))
            error_um = sensor_accuracy_C * abs(sensitivity[worst])
            if error_um > limit_um:
                refused[model_id] = (
                    f"a bias of ±{sensor_accuracy_C:g} °C on {worst} moves it by "
                    f"{error_um:.1f} µm (limit models.max_bias_error_um {limit_um:g} µm)"
                )
                del self.models[model_id]
        return refused

    def usable(
        self, model_id: str | None, good: set[str], target: str | None = None
    ) -> Banked | None:
        """``model_id`` (or the model promoted in its place) if all its sensors are good,
        else the best fallback, else None. ``target``: only a model predicting that error
        column serves (one axis of a multi-axis machine); None: any (a one-target bank)."""
        served = self.serving(model_id)
        preferred = self.models.get(served) if served else None
        if target is not None and preferred is not None and preferred.target.name != target:
            preferred = self.models.get(model_id) if model_id else None  # promoted elsewhere
        if preferred is not None and target is not None and preferred.target.name != target:
            preferred = None
        if preferred is not None and preferred.sensors <= good:
            return preferred
        regime = preferred.regime if preferred is not None else None
        candidates = [
            m
            for m in self.models.values()
            if m.sensors <= good and (target is None or m.target.name == target)
        ]
        if not candidates:
            return None
        return min(candidates, key=lambda m: (m.regime != regime, m.held_out_rmse_um, m.model_id))
