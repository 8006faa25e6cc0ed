"""Sensor selection on synthetic data shaped like paper 002's experiment."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.estimators.parts.sensor_selection import select_sensors

NAMES = [f"T{i}" for i in range(1, 11)]
T_MIN = np.arange(0.0, 300.0, 5.0)  # 60 samples, every 5 min


def _area(x: np.ndarray) -> float:
    """Liu & Lin's s = Σ_{k=2}^{n−1} x⁰(k) + ½ x⁰(n) of a zero-starting series."""
    z = x - x[0]
    return float(z[1:-1].sum() + 0.5 * z[-1])


def paper_like_data(seed: int = 42, t_min: np.ndarray = T_MIN) -> tuple[np.ndarray, np.ndarray]:
    """10 sensors in two families and an error built from T1 and T7.

    T1–T5: fast bearing-like rise, time constants 8–12 min, different gains.
    T6–T10: slow motor/housing-like rise, 20 min delay, time constants 50–70 min.
    The absolute degree ranks a sensor by how close the area s of its rise (°C)
    is to the area of the error (µm). The error is ½·T1 + ½·T7, and T7's gain is
    set so that s(T7) = s(T1); so s(error) ≈ s(T1) ≈ s(T7), while every other
    sensor's gain is at least 25 % off its family's winner.
    """
    rng = np.random.default_rng(seed)
    fast = [1 - np.exp(-t_min / tau) for tau in (8, 9, 10, 11, 12)]
    slow = [1 - np.exp(-np.maximum(t_min - 20, 0) / tau) for tau in (50, 55, 60, 65, 70)]
    fast_gain_C = np.array([12.0, 8.0, 6.0, 16.0, 20.0])
    t7_gain_C = fast_gain_C[0] * _area(fast[0]) / _area(slow[1])
    slow_gain_C = t7_gain_C * np.array([0.6, 1.0, 0.75, 1.4, 1.8])
    clean = np.column_stack(
        [g * s for g, s in zip(fast_gain_C, fast, strict=True)]
        + [g * s for g, s in zip(slow_gain_C, slow, strict=True)]
    )
    rise_C = clean + rng.normal(0, 0.05, clean.shape)
    error_um = 0.5 * clean[:, 0] + 0.5 * clean[:, 6] + rng.normal(0, 0.3, t_min.size)
    return rise_C, error_um


def test_two_families_two_clusters_and_paper_winners() -> None:
    rise, error = paper_like_data()
    sel = select_sensors(rise, NAMES, error, n_clusters=2)
    assert sel.sensors == tuple(NAMES)
    assert sel.clusters == (tuple(NAMES[:5]), tuple(NAMES[5:]))
    assert sel.n_clusters == 2
    assert len(sel.selected) == 2
    for cluster, chosen in zip(sel.clusters, sel.selected, strict=True):
        assert chosen in cluster
        assert all(sel.grades[chosen] >= sel.grades[name] for name in cluster)
        assert sum(sel.grades[chosen] == sel.grades[name] for name in cluster) == 1
    assert sel.selected == ("T1", "T7")
    assert all(0.5 < g <= 1.0 for g in sel.grades.values())
    assert 0.9 < sel.partition_coefficient <= 1.0
    assert sel.xie_beni > 0


def test_automatic_cluster_count_picks_two() -> None:
    rise, error = paper_like_data(seed=7)
    sel = select_sensors(rise, NAMES, error)
    assert sel.n_clusters == 2
    assert sel.clusters == (tuple(NAMES[:5]), tuple(NAMES[5:]))
    assert sel.selected == ("T1", "T7")


def test_clusters_follow_shape_not_input_order() -> None:
    rise, error = paper_like_data()
    order = [5, 0, 6, 1, 7, 2, 8, 3, 9, 4]  # interleave the families
    names = [NAMES[i] for i in order]
    sel = select_sensors(rise[:, order], names, error, n_clusters=2)
    assert sel.clusters == (
        ("T6", "T7", "T8", "T9", "T10"),
        ("T1", "T2", "T3", "T4", "T5"),
    )
    assert sel.selected == ("T7", "T1")


def test_segments_use_per_run_grades() -> None:
    # Two runs back to back; grading per run still picks T1 and T7.
    rise_a, error_a = paper_like_data(seed=1)
    rise_b, error_b = paper_like_data(seed=2)
    rise = np.vstack([rise_a, rise_b])
    error = np.concatenate([error_a, error_b])
    segments = np.repeat([0, 1], len(T_MIN))
    sel = select_sensors(rise, NAMES, error, n_clusters=2, segments=segments)
    assert sel.selected == ("T1", "T7")
    joined = select_sensors(rise, NAMES, error, n_clusters=2)
    assert sel.grades != joined.grades


def test_tie_goes_to_the_earlier_sensor() -> None:
    rise, error = paper_like_data()
    rise[:, 2] = rise[:, 0]  # T3 becomes an exact copy of T1: equal grades
    sel = select_sensors(rise, NAMES, error, n_clusters=2)
    assert sel.grades["T1"] == sel.grades["T3"]
    assert sel.selected[0] == "T1"
    swapped = [NAMES[2], NAMES[1], NAMES[0], *NAMES[3:]]  # T3 first in input order
    sel = select_sensors(rise, swapped, error, n_clusters=2)
    assert sel.selected[0] == "T3"


def test_two_sensors_are_their_own_clusters() -> None:
    rise, error = paper_like_data()
    sel = select_sensors(rise[:, [0, 6]], ["T1", "T7"], error)
    assert sel.clusters == (("T1",), ("T7",))
    assert sel.selected == ("T1", "T7")
    assert sel.as_dict()["xie_beni"] is None


def test_as_dict_is_json() -> None:
    rise, error = paper_like_data()
    d = select_sensors(rise, NAMES, error, n_clusters=2).as_dict()
    back = json.loads(json.dumps(d))
    assert back["selected"] == ["T1", "T7"]
    assert back["clusters"][0] == NAMES[:5]
    assert set(back["grades"]) == set(NAMES)


def test_validation() -> None:
    rise, error = paper_like_data()
    with pytest.raises(ValueError, match="rise_C must be"):
        select_sensors(rise, NAMES[:9], error)
    with pytest.raises(ValueError, match="error_um must be"):
        select_sensors(rise, NAMES, error[:-1])
    with pytest.raises(ValueError, match="at least 2 samples"):
        select_sensors(rise[:1], NAMES, error[:1])
    with pytest.raises(ValueError, match="unique"):
        select_sensors(rise, ["T1"] * 10, error)
    with pytest.raises(ValueError, match="n_clusters"):
        select_sensors(rise, NAMES, error, n_clusters=11)
    with pytest.raises(ValueError, match="finite"):
        bad = rise.copy()
        bad[3, 3] = np.nan
        select_sensors(bad, NAMES, error)
