"""Accuracy figures of a prediction, named with their units.

- RMSE = sqrt(mean(e²)), e = measured − predicted (µm).
- σ = sample standard deviation of the residuals (ddof = 1): paper 002's
  "predictive accuracy", the standard-deviation estimate of the residuals
  (Miao et al. 2015, §5). It ignores a constant offset; RMSE does not.
- max |e| (µm).
- relative error = |measured − predicted| / |measured| per sample (paper 000,
  Table 5); the share of samples under 0.05 is the figure that paper quotes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Accuracy:
    rmse_um: float
    sigma_um: float
    max_abs_um: float
    n_samples: int

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def residuals(measured_um: np.ndarray, predicted_um: np.ndarray) -> np.ndarray:
    measured = np.asarray(measured_um, dtype=float)
    predicted = np.asarray(predicted_um, dtype=float)
    if measured.shape != predicted.shape:
        raise ValueError(f"shapes differ: measured {measured.shape}, predicted {predicted.shape}")
    return measured - predicted


def accuracy(measured_um: np.ndarray, predicted_um: np.ndarray) -> Accuracy:
    e = residuals(measured_um, predicted_um)
    if e.size == 0:
        raise ValueError("no samples to score")
    sigma = float(np.std(e, ddof=1)) if e.size > 1 else 0.0
    return Accuracy(
        rmse_um=float(np.sqrt(np.mean(e**2))),
        sigma_um=sigma,
        max_abs_um=float(np.max(np.abs(e))),
        n_samples=int(e.size),
    )


def relative_error(measured_um: np.ndarray, predicted_um: np.ndarray) -> np.ndarray:
    """|measured − predicted| / |measured| per sample; inf where measured is 0."""
    measured = np.asarray(measured_um, dtype=float)
    e = np.abs(residuals(measured, predicted_um))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(measured == 0, np.where(e == 0, 0.0, np.inf), e / np.abs(measured))
