"""Stepping a streaming model through a prepared recording, row by row, as the runtime does."""

from __future__ import annotations

from typing import Any

import numpy as np

from models.data.features import Prepared


def streamed(stream: Any, prepared: Prepared, *, speed: bool = True) -> np.ndarray:
    """``stream.step`` over every row of ``prepared`` in order (the speed left out, None,
    when ``speed`` is false): what the runtime would have predicted, one cycle at a time."""
    inputs, data = prepared.inputs, prepared.data
    return np.array(
        [
            stream.step(
                float(data.time_s[k]),
                dict(zip(inputs.sensors, inputs.rise_C[k], strict=True)),
                float(data.speed_rpm[k]) if speed else None,
            )
            for k in range(data.n_samples)
        ]
    )
