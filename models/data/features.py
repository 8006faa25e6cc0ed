"""From a loaded file to what a model sees: rises of the sensors and of the error."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from models.base import ModelInputs
from models.data.dataset import MeasuredRuns
from models.data.references import ReferencePlan, error_origins, plan_references


@dataclass(frozen=True)
class Prepared:
    """Row-aligned model inputs and target (µm), with the reference plan used."""

    data: MeasuredRuns
    inputs: ModelInputs
    error_um: np.ndarray
    plan: ReferencePlan

    def without_sensor_readings(self) -> Prepared:
        """The same, without the raw readings of the input sensors (their rises are in
        ``inputs``): what ``fit`` and ``analyze`` keep of a big file once it is prepared."""
        return Prepared(
            data=self.data.without_readings(self.inputs.sensors),
            inputs=self.inputs,
            error_um=self.error_um,
            plan=self.plan,
        )

    def take(self, rows: np.ndarray) -> Prepared:
        return Prepared(
            data=self.data.take(rows),
            inputs=self.inputs.take(rows),
            error_um=self.error_um[rows],
            plan=self.plan,
        )


def prepare(
    data: MeasuredRuns, sensors: Sequence[str] | None = None, reference: str = "auto"
) -> Prepared:
    """Rises of the declared sensors (°C) from their references, and the target (µm) as
    measured unless a recording reads from an origin of its own (``models/data/references.py``)."""
    names = tuple(sensors) if sensors is not None else data.sensors
    plan = plan_references(data, reference)
    rise_C = np.empty((data.n_samples, len(names)))
    for j, name in enumerate(names):  # one column at a time: no (n, k) temporaries
        rise_C[:, j] = plan.rises(data.column(name))
    inputs = ModelInputs(
        rise_C=rise_C,
        sensors=names,
        speed_rpm=data.speed_rpm,
        run_index=data.run_index,
        time_s=data.time_s,
        recording=plan.recording,
    )
    return Prepared(
        data=data,
        inputs=inputs,
        error_um=plan.error(data.error_um),
        plan=plan,
    )


def retarget(shared: Prepared, data: MeasuredRuns) -> Prepared:
    """``shared`` (another target's preparation of the same rows and sensors) for ``data``'s
    target: the rises, recordings and reference rows do not depend on the target, only the
    error and its origins do; the same figures as ``prepare`` of ``data``, without taking
    the rises again."""
    if data.n_samples != shared.data.n_samples:
        raise ValueError("retarget: the target's rows differ from the prepared rows")
    old = shared.plan
    origins = error_origins(data.error_um, old.recording, old.reference_rows, data.speed_rpm)
    plan = replace(old, error_origin_um=origins)
    return Prepared(data=data, inputs=shared.inputs, error_um=plan.error(data.error_um), plan=plan)
