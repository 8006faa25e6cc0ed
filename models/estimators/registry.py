"""The fitting methods by the name used on the command line and in the store."""

from __future__ import annotations

from collections.abc import Sequence

from models.base import ThermalModel
from models.estimators.grey_mlr import GreyMlrModel
from models.estimators.lag_ridge import LagRidgeModel
from models.estimators.mlr import MlrModel
from models.estimators.pca_quadratic import PcaQuadraticModel
from models.estimators.ridge_pls import PlsModel, RidgeModel

METHODS: dict[str, type[ThermalModel]] = {
    MlrModel.method: MlrModel,
    GreyMlrModel.method: GreyMlrModel,
    PcaQuadraticModel.method: PcaQuadraticModel,
    RidgeModel.method: RidgeModel,
    PlsModel.method: PlsModel,
    LagRidgeModel.method: LagRidgeModel,
}


def make_model(method: str, sensors: Sequence[str] | None = None) -> ThermalModel:
    """A fresh, unfitted model of ``method`` using the declared sensors."""
    try:
        cls = METHODS[method]
    except KeyError:
        raise ValueError(f"unknown method '{method}'; expected one of {sorted(METHODS)}") from None
    return cls(sensors=sensors)
