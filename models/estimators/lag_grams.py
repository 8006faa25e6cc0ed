"""Gram products of lag-ridge's terms per run, taken once and shared by every fit.

Every fit inside ``lag-ridge`` (each outer fold, each inner fold, each candidate
structure) needs the products ``[1, Z, y]ᵀ[1, Z, y]`` of the terms over its
training rows. The lags are built over the whole history, so the terms of a row
do not depend on which runs a fold trains on, and the products of a set of whole
runs are the sum of each run's. Each run's products of the largest candidate's
terms are therefore taken once per data set and process; a fold sums the runs it
trains on, and a smaller candidate takes its rows and columns out of that sum.

The data set is recognised by its content (a hash of the inputs and the target),
not by the object: the folds fitted in worker processes each receive their own
copy of the inputs.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np

from models.base import ModelInputs


def fingerprint(*arrays: np.ndarray | None, names: Sequence[object] = ()) -> str:
    """A hash of the arrays' shapes, types and bytes (and of ``names``)."""
    digest = hashlib.blake2b(repr(tuple(names)).encode(), digest_size=20)
    for array in arrays:
        if array is None:
            digest.update(b"none")
            continue
        values = np.ascontiguousarray(array)
        digest.update(f"{values.dtype.str}{values.shape}".encode())
        digest.update(values.data.cast("B") if values.size else b"")
    return digest.hexdigest()


def inputs_fingerprint(inputs: ModelInputs) -> str:
    return fingerprint(
        inputs.rise_C,
        inputs.speed_rpm,
        inputs.run_index,
        inputs.time_s,
        inputs.recording,
        names=inputs.sensors,
    )


def augmented_gram(terms: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``[1, Z, y]ᵀ[1, Z, y]`` of these rows, (k + 2, k + 2)."""
    z = np.empty((terms.shape[0], terms.shape[1] + 2))
    z[:, 0] = 1.0
    z[:, 1:-1] = terms
    z[:, -1] = y
    return z.T @ z


class RunGrams:
    """Each run's ``[1, Z, y]ᵀ[1, Z, y]``, in the order of ``np.unique(run_index)``."""

    def __init__(self, terms: np.ndarray, y: np.ndarray, run_index: np.ndarray) -> None:
        self.runs, position = np.unique(run_index, return_inverse=True)
        bounds = np.r_[0, np.cumsum(np.bincount(position))]
        contiguous = bool(np.all(np.diff(position) >= 0))
        order = None if contiguous else np.argsort(position, kind="stable")
        self.grams = np.empty((self.runs.size, terms.shape[1] + 2, terms.shape[1] + 2))
        for k in range(self.runs.size):
            part = slice(bounds[k], bounds[k + 1])
            rows = part if order is None else order[part]
            self.grams[k] = augmented_gram(terms[rows], y[rows])


def whole_runs(labels: np.ndarray, run_index: np.ndarray | None) -> dict | None:
    """{group label: its runs} when every group of ``labels`` (−1: not a training row) is
    made of whole runs; None when a group takes part of a run (or there are no runs)."""
    if run_index is None:
        return None
    pairs = np.unique(np.column_stack([run_index, labels]), axis=0)
    runs, label_of_run = pairs[:, 0], pairs[:, 1]
    if np.unique(runs).size != runs.size:  # a run split between groups or left partly out
        return None
    groups: dict = {}
    for run, label in zip(runs.tolist(), label_of_run.tolist(), strict=True):
        if label >= 0:
            groups.setdefault(label, []).append(run)
    return groups


#: The last data set's run products: (key, RunGrams).
_last: list[tuple[str, RunGrams]] = []


def group_grams(
    key: str, terms: np.ndarray, y: np.ndarray, labels: np.ndarray, run_index: np.ndarray | None
) -> tuple[list, np.ndarray]:
    """(group labels in order of first row, their ``[1, Z, y]ᵀ[1, Z, y]``) of the training
    rows of ``labels`` (integers, −1: not a training row).

    When every group is made of whole runs, the sums of the run products kept for ``key``
    (the terms' data set; the target is hashed here), else taken over the rows.
    """
    order = list(dict.fromkeys(labels[labels >= 0].tolist()))
    by_group = whole_runs(labels, run_index)
    if by_group is None:
        rows = [labels == label for label in order]
        return order, np.array([augmented_gram(terms[r], y[r]) for r in rows])
    assert run_index is not None  # whole runs need runs
    full_key = key + fingerprint(y, run_index)
    if not (_last and _last[0][0] == full_key):
        _last.clear()  # drop the previous data set's products before taking the new ones
        _last.append((full_key, RunGrams(terms, y, run_index)))
    grams = _last[0][1]
    position = {run: k for k, run in enumerate(grams.runs.tolist())}
    sums = np.zeros((len(order), *grams.grams.shape[1:]))
    for total, label in zip(sums, order, strict=True):
        for run in by_group[label]:
            total += grams.grams[position[run]]
    return order, sums
