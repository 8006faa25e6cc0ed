"""The estimator interface every thermal-error model follows.

Shaped like scikit-learn estimators: the constructor only stores hyperparameters,
``fit`` validates its inputs, learns and returns ``self``; learned state ends in
``_``; ``predict`` refuses an unfitted model. Every model also turns its fitted
numbers into plain JSON (``fitted_params``) and back (``from_params``), so the
model store never needs pickle.

Inputs are a :class:`ModelInputs`: temperature *rises* (°C above the reference
sample, see :mod:`models.data.references`) for named sensors, and the spindle speed in
r/min. The target is the thermal error in µm as measured; its reference is the
model's intercept.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

import numpy as np


class NotFittedError(RuntimeError):
    """``predict`` was called on a model that has not been fitted."""


@dataclass(frozen=True)
class ModelInputs:
    """What a model may look at, row-aligned.

    Attributes:
        rise_C: (n, p) temperature rise of each sensor above its reference, °C.
        sensors: the p sensor names, in column order of ``rise_C``.
        speed_rpm: (n,) spindle speed, r/min.
        run_index: (n,) integer run number of each row (0, 1, …), for methods
            that work on whole sequences (grey relational grade); ``None`` means
            one run.
        time_s: (n,) time of each row, s, for methods whose terms remember the
            history (first-order lags, :mod:`models.estimators.lag_ridge`); ``None`` means
            rows without a history (each one taken at a steady state).
        recording: (n,) recording number of each row (lags carry across the runs
            of one recording, :mod:`models.data.references`); ``None`` means one.
    """

    rise_C: np.ndarray
    sensors: tuple[str, ...]
    speed_rpm: np.ndarray
    run_index: np.ndarray | None = None
    time_s: np.ndarray | None = None
    recording: np.ndarray | None = None

    def __post_init__(self) -> None:
        rise = np.asarray(self.rise_C, dtype=float)
        if rise.ndim != 2 or rise.shape[1] != len(self.sensors):
            raise ValueError(
                f"rise_C must be (n, {len(self.sensors)}) for sensors {list(self.sensors)}, "
                f"got shape {rise.shape}"
            )
        speed = np.asarray(self.speed_rpm, dtype=float)
        if speed.shape != (rise.shape[0],):
            raise ValueError(f"speed_rpm must be ({rise.shape[0]},), got {speed.shape}")
        object.__setattr__(self, "rise_C", rise)
        object.__setattr__(self, "speed_rpm", speed)
        if self.run_index is not None:
            runs = np.asarray(self.run_index)
            if not np.issubdtype(runs.dtype, np.integer):
                runs = runs.astype(int)
            if runs.shape != (rise.shape[0],):
                raise ValueError(f"run_index must be ({rise.shape[0]},), got {runs.shape}")
            object.__setattr__(self, "run_index", runs)
        for name in ("time_s", "recording"):
            values = getattr(self, name)
            if values is not None and np.shape(values) != (rise.shape[0],):
                raise ValueError(f"{name} must be ({rise.shape[0]},), got {np.shape(values)}")

    @property
    def n_samples(self) -> int:
        return int(self.rise_C.shape[0])

    def columns(self, names: tuple[str, ...] | list[str]) -> np.ndarray:
        """(n, k) rises of the named sensors, in the order given."""
        missing = [name for name in names if name not in self.sensors]
        if missing:
            raise KeyError(f"sensor(s) {missing} not among the inputs {list(self.sensors)}")
        if tuple(names) == self.sensors:
            return self.rise_C  # every sensor in order: no copy of the whole matrix
        index = [self.sensors.index(name) for name in names]
        return self.rise_C[:, index]

    def take(self, rows: np.ndarray) -> ModelInputs:
        """The same inputs restricted to ``rows`` (a boolean mask or index array)."""
        return ModelInputs(
            rise_C=self.rise_C[rows],
            sensors=self.sensors,
            speed_rpm=self.speed_rpm[rows],
            run_index=None if self.run_index is None else self.run_index[rows],
            time_s=None if self.time_s is None else self.time_s[rows],
            recording=None if self.recording is None else self.recording[rows],
        )


class ThermalModel(ABC):
    """Base class: fit on (inputs, error_um), predict error_um.

    Subclasses set ``method`` (the name used on the command line and in the
    store), implement ``_fit``, ``_predict``, ``fitted_params`` and
    ``_load_params``, and list the sensors they actually use in
    ``sensors_used_`` after fitting.
    """

    method: ClassVar[str]
    #: True when ``design_matrix`` does not depend on the data the model was
    #: fitted on (plain regression on declared inputs), so residual analysis can
    #: share one design across validation folds.
    fixed_design: ClassVar[bool] = False

    sensors_used_: tuple[str, ...]

    @abstractmethod
    def __init__(self, sensors: Sequence[str] | None = None) -> None:
        """Every method is made from the sensors it may use (None: all the data's)."""

    def fit(self, inputs: ModelInputs, error_um: np.ndarray) -> Self:
        y = np.asarray(error_um, dtype=float)
        if y.shape != (inputs.n_samples,):
            raise ValueError(f"error_um must be ({inputs.n_samples},), got {y.shape}")
        if not np.all(np.isfinite(y)) or not np.all(np.isfinite(inputs.rise_C)):
            raise ValueError("fit needs finite temperatures and errors (found NaN or inf)")
        self._fit(inputs, y)
        return self

    def fit_rows(self, inputs: ModelInputs, error_um: np.ndarray, rows: np.ndarray) -> Self:
        """The same as ``fit(inputs.take(rows), error_um[rows])``.

        A method may override it to read the rows straight from ``inputs``
        (validation fits on all runs but one, and on a million-row file a copy
        of the inputs first is hundreds of megabytes).
        """
        return self.fit(inputs.take(rows), np.asarray(error_um)[rows])

    def predict_rows(self, inputs: ModelInputs, rows: np.ndarray) -> np.ndarray:
        """The same as ``predict(inputs.take(rows))``.

        A method whose terms remember the history (lags) overrides it to build
        its terms over all of ``inputs`` first: the rows of a held-out run still
        follow the heat of the runs before it.
        """
        return self.predict(inputs.take(rows))

    def predict(self, inputs: ModelInputs) -> np.ndarray:
        if not self.is_fitted:
            raise NotFittedError(
                f"this {type(self).__name__} is not fitted yet: "
                "call fit() or load it from the store"
            )
        return np.asarray(self._predict(inputs), dtype=float)

    @property
    def is_fitted(self) -> bool:
        return hasattr(self, "sensors_used_")

    @abstractmethod
    def hyperparams(self) -> dict[str, Any]:
        """Constructor arguments, JSON-able, so ``type(self)(**hyperparams())`` rebuilds it."""

    @abstractmethod
    def fitted_params(self) -> dict[str, Any]:
        """The learned numbers as plain JSON (lists and floats, named with units)."""

    @classmethod
    def from_params(cls, hyperparams: dict[str, Any], params: dict[str, Any]) -> Self:
        """Rebuild a fitted model from ``hyperparams()`` and ``fitted_params()``."""
        model = cls(**hyperparams)
        model._load_params(params)
        return model

    @abstractmethod
    def _fit(self, inputs: ModelInputs, error_um: np.ndarray) -> None: ...

    @abstractmethod
    def _predict(self, inputs: ModelInputs) -> np.ndarray: ...

    @abstractmethod
    def _load_params(self, params: dict[str, Any]) -> None: ...

    def design_matrix(self, inputs: ModelInputs) -> np.ndarray:
        """(n, k) regression terms of the fitted model, without the intercept.

        Every method here is linear in its coefficients once its structure
        (chosen sensors, principal components) is fitted; residual analysis
        refits those coefficients jointly with the terms of a candidate effect.
        """
        raise NotImplementedError(f"{type(self).__name__} has no linear design matrix")

    def input_units(self) -> dict[str, str]:
        """Unit of every input the fitted model reads (sensor rises and speed)."""
        units = {name: "°C rise" for name in self.sensors_used_}
        if self.uses_speed:
            units["speed_rpm"] = "r/min"
        return units

    @property
    def uses_speed(self) -> bool:
        return False
