"""Paper 002's method: sensitive points by fuzzy clustering + grey grade, then MLR.

1. Cluster the candidate sensors by the shape of their temperature-rise series
   (fuzzy c-means, :mod:`models.estimators.parts.fcm`).
2. In each cluster keep the sensor with the largest grey absolute degree of
   incidence to the thermal error (:mod:`models.estimators.parts.grey_incidence`), one per cluster.
3. Multiple linear regression of the error on the rises of the kept sensors
   (:mod:`models.estimators.mlr`): e = b0 + Σ b_i ΔT_i.

Selecting few, mutually distinct sensors is what keeps the regression robust
against the collinearity of neighbouring sensors (Miao et al. 2015, §3).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from models.base import ModelInputs
from models.estimators.mlr import MlrModel
from models.estimators.parts.sensor_selection import SensorSelection, select_sensors


class GreyMlrModel(MlrModel):
    method = "grey-mlr"
    fixed_design = False  # the chosen sensors depend on the data

    def __init__(
        self,
        sensors: Sequence[str] | None = None,
        n_clusters: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(sensors)
        self.n_clusters = n_clusters
        self.seed = seed

    def hyperparams(self) -> dict[str, Any]:
        return {"sensors": self.sensors, "n_clusters": self.n_clusters, "seed": self.seed}

    def _fit(self, inputs: ModelInputs, error_um: np.ndarray) -> None:
        candidates = tuple(self.sensors) if self.sensors is not None else inputs.sensors
        self.selection_: SensorSelection = select_sensors(
            inputs.columns(candidates),
            candidates,
            error_um,
            n_clusters=self.n_clusters,
            segments=inputs.run_index,
            seed=self.seed,
        )
        chosen = MlrModel(self.selection_.selected).fit(inputs, error_um)
        self.intercept_um_ = chosen.intercept_um_
        self.coef_um_per_C_ = chosen.coef_um_per_C_
        self.sensors_used_ = chosen.sensors_used_

    def fitted_params(self) -> dict[str, Any]:
        params = super().fitted_params()
        if hasattr(self, "selection_"):
            params["selection"] = self.selection_.as_dict()
        return params

    def _load_params(self, params: dict[str, Any]) -> None:
        super()._load_params(params)
        self.selection_info_ = params.get("selection")
