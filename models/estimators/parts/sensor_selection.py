"""Temperature-sensitive point selection of paper 002 (Miao et al. 2015, §3).

1. Cluster the sensors with fuzzy c-means (:mod:`models.estimators.parts.fcm`): each sensor is one
   point, its z-scored temperature-rise series (:func:`models.estimators.parts.fcm.sensor_points`),
   so sensors group by the shape of their thermal response.
2. Grade every sensor by its grey absolute degree of incidence to the thermal
   error (:mod:`models.estimators.parts.grey_incidence`).
3. In each cluster keep the sensor with the highest grade; on an exact tie the
   sensor earlier in input order wins.

The paper has 10 sensors in 2 classes, {T1..T5} and {T6..T10}, and keeps T1 and
T7. Its printed grade values cannot come from the textbook formula (see
:mod:`models.estimators.parts.grey_incidence`); this module reproduces the selection structure.

Number of clusters: if not given, c runs over 2 … min(max_clusters, p − 1) and
the c with the lowest Xie–Beni index (compactness over separation, Xie & Beni
1991) wins, the smaller c on a tie. c = p is left out because every sensor
alone is trivially compact and says nothing. With p ≤ 2 sensors no clustering is
done: each sensor is its own cluster.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.estimators.parts.fcm import fuzzy_c_means, sensor_points, span_coordinates, xie_beni
from models.estimators.parts.grey_incidence import absolute_degrees


@dataclass(frozen=True)
class SensorSelection:
    """Outcome of :func:`select_sensors`.

    Attributes:
        sensors: all candidate sensors, in input order.
        clusters: sensor names per cluster (input order inside a cluster);
            cluster 0 holds the first sensor.
        grades: grey absolute degree of each sensor to the thermal error.
        selected: the highest-graded sensor of each cluster, in cluster order.
        n_clusters: number of clusters (non-empty ones).
        partition_coefficient: Bezdek's PC of the fuzzy partition (1 if crisp).
        xie_beni: Xie–Beni index of the partition; NaN when no clustering was
            done (p ≤ 2 sensors).
    """

    sensors: tuple[str, ...]
    clusters: tuple[tuple[str, ...], ...]
    grades: dict[str, float]
    selected: tuple[str, ...]
    n_clusters: int
    partition_coefficient: float
    xie_beni: float

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (a NaN Xie–Beni index becomes ``None``)."""
        return {
            "sensors": list(self.sensors),
            "clusters": [list(cluster) for cluster in self.clusters],
            "grades": dict(self.grades),
            "selected": list(self.selected),
            "n_clusters": self.n_clusters,
            "partition_coefficient": self.partition_coefficient,
            "xie_beni": None if math.isnan(self.xie_beni) else self.xie_beni,
        }


def _check_inputs(
    rise_C: np.ndarray, sensors: Sequence[str], error_um: np.ndarray
) -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    rise = np.asarray(rise_C, dtype=float)
    names = tuple(sensors)
    if rise.ndim != 2 or rise.shape[1] != len(names):
        raise ValueError(
            f"rise_C must be (n_samples, {len(names)}) for sensors {list(names)}, "
            f"got shape {rise.shape}"
        )
    if len(names) == 0:
        raise ValueError("no sensors to select from")
    if len(set(names)) != len(names):
        raise ValueError(f"sensor names must be unique, got {list(names)}")
    if rise.shape[0] < 2:
        raise ValueError(f"need at least 2 samples, got {rise.shape[0]}")
    error = np.asarray(error_um, dtype=float)
    if error.shape != (rise.shape[0],):
        raise ValueError(f"error_um must be ({rise.shape[0]},), got shape {error.shape}")
    if not (np.all(np.isfinite(rise)) and np.all(np.isfinite(error))):
        raise ValueError("rise_C and error_um must be finite (found NaN or inf)")
    return rise, names, error


def select_sensors(
    rise_C: np.ndarray,
    sensors: Sequence[str],
    error_um: np.ndarray,
    n_clusters: int | None = None,
    segments: np.ndarray | None = None,
    max_clusters: int = 6,
    seed: int = 0,
) -> SensorSelection:
    """Pick one temperature-sensitive sensor per FCM cluster (paper 002, §3).

    Args:
        rise_C: (n_samples, p) temperature rises, °C.
        sensors: the p sensor names, in column order.
        error_um: (n_samples,) thermal error, µm (the grey reference sequence).
        n_clusters: number of clusters, 2 ≤ c ≤ p; ``None`` picks c by the lowest
            Xie–Beni index over 2 … min(max_clusters, p − 1).
        segments: optional (n_samples,) integer run numbers; grades are then
            computed per run and averaged weighted by run length.
        max_clusters: upper bound of the automatic search (≥ 2).
        seed: seed of the FCM starts.

    Raises:
        ValueError: on mismatched shapes, fewer than 2 samples, non-finite data,
            duplicate names or an impossible cluster count.
    """
    rise, names, error = _check_inputs(rise_C, sensors, error_um)
    p = len(names)
    grade_values = absolute_degrees(error, rise, segments)
    grades = {name: float(g) for name, g in zip(names, grade_values, strict=True)}

    if p <= 2:
        if n_clusters is not None and n_clusters != p:
            raise ValueError(
                f"with {p} sensor(s) each is its own cluster; got n_clusters={n_clusters}"
            )
        labels = np.arange(p)
        pc, xb = 1.0, float("nan")
    else:
        # One coordinate per sample is wasteful: the p sensors span at most p
        # dimensions, and memberships and the Xie–Beni index are the same there.
        points, _ = span_coordinates(sensor_points(rise))
        if n_clusters is not None:
            if not 2 <= n_clusters <= p:
                raise ValueError(f"n_clusters must be in 2..{p} for {p} sensors, got {n_clusters}")
            candidates = [n_clusters]
        else:
            if max_clusters < 2:
                raise ValueError(f"max_clusters must be ≥ 2, got {max_clusters}")
            candidates = list(range(2, min(max_clusters, p - 1) + 1))
        best = None
        for c in candidates:
            result = fuzzy_c_means(points, c, seed=seed)
            index = xie_beni(points, result)
            if best is None or index < best[0]:
                best = (index, result)
        assert best is not None, "no cluster count to try"
        xb, result = best
        labels = result.labels
        pc = result.partition_coefficient()

    clusters: list[tuple[str, ...]] = []
    selected: list[str] = []
    for label in range(int(labels.max()) + 1):
        members = [i for i in range(p) if labels[i] == label]
        if not members:
            continue
        clusters.append(tuple(names[i] for i in members))
        # argmax returns the first maximum: ties go to the earlier sensor.
        selected.append(names[members[int(np.argmax(grade_values[members]))]])

    return SensorSelection(
        sensors=names,
        clusters=tuple(clusters),
        grades=grades,
        selected=tuple(selected),
        n_clusters=len(clusters),
        partition_coefficient=float(pc),
        xie_beni=float(xb),
    )
