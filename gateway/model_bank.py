"""The fitted models a machine can use, loaded and checked once at start-up.

Every file of the store is loaded through :func:`models.store.load_file` (which
refuses damaged or incompatible files). The regime rules name models by id;
when a sensor a model needs goes bad, the bank offers a *fallback*: another
stored model that does without that sensor, preferring one fitted for the same
regime, then the one with the lowest held-out RMSE.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from models.base import ThermalModel
from models.store import StoredModel, load_file

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BankedModel:
    model_id: str
    model: ThermalModel
    document: StoredModel

    @property
    def sensors(self) -> frozenset[str]:
        return frozenset(self.model.sensors_used_)

    @property
    def held_out_rmse_um(self) -> float:
        pooled = self.document.validation.get("pooled") or {}
        return float(pooled.get("rmse_um", float("inf")))


class ModelBank:
    def __init__(self, models: Iterable[BankedModel]) -> None:
        self.models = {m.model_id: m for m in models}

    @classmethod
    def from_store(cls, folder: Path) -> ModelBank:
        if not folder.is_dir():
            raise ValueError(f"model store {folder}: no such folder")
        loaded = []
        for path in sorted(folder.glob("*.json")):
            model, document = load_file(path)
            loaded.append(BankedModel(document.model_id, model, document))
        if not loaded:
            raise ValueError(f"model store {folder}: no model files (*.json)")
        return cls(loaded)

    def __contains__(self, model_id: str) -> bool:
        return model_id in self.models

    def get(self, model_id: str) -> BankedModel:
        try:
            return self.models[model_id]
        except KeyError:
            raise KeyError(
                f"model '{model_id}' is not in the store (have: {sorted(self.models)})"
            ) from None

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

    def usable(self, model_id: str | None, good: set[str]) -> BankedModel | None:
        """``model_id`` if all its sensors are good, else the best fallback, else None."""
        preferred = self.models.get(model_id) if model_id else None
        if preferred is not None and preferred.sensors <= good:
            return preferred
        regime = preferred.document.regime if preferred is not None else None
        candidates = [m for m in self.models.values() if m.sensors <= good]
        if not candidates:
            return None
        return min(
            candidates, key=lambda m: (m.document.regime != regime, m.held_out_rmse_um, m.model_id)
        )
