"""The declared model's base predictions for a replay, each training set fitted once.

A leave-one-run-out replay with the declared base fits the model on every run but
one (the held-out runs, and ``offline_accuracy``), and, inside each, on the inner
folds of the training runs (the residuals the filter is chosen on); every probe
interval needs the same fits again. Those training sets are known before any replay
starts, so :func:`prefill` fits each distinct one once, in worker processes (one per
core, one BLAS thread each) with a progress bar, and :func:`prediction` serves them.
A fit is the same wherever it runs, so the figures do not change.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from tqdm import tqdm

from models.data.features import Prepared
from models.estimators.registry import make_model
from models.estimators.ridge_pls import grouped_runs

#: From this many distinct fits on, they run in worker processes.
PARALLEL_FROM_FITS = 8

_Key = tuple[int, str, tuple[str, ...] | None, bytes]
#: Predictions fitted on demand (a few, as before any prefill): by (data, method, sensors,
#: training rows).
_cache: dict[_Key, np.ndarray] = {}
_CACHE_SIZE = 32
#: Every training set of the replay last prefilled (one data set at a time).
_prefilled: dict[_Key, np.ndarray] = {}


def _key(prepared: Prepared, method: str, sensors: Sequence[str] | None, train: np.ndarray) -> _Key:
    names = None if sensors is None else tuple(sensors)
    return (id(prepared), method, names, np.packbits(train).tobytes())


def prediction(
    prepared: Prepared, method: str, sensors: Sequence[str] | None, train: np.ndarray
) -> np.ndarray:
    """The declared model fitted on ``train`` (its lags built over the whole history),
    predicting every row."""
    key = _key(prepared, method, sensors, train)
    for store in (_prefilled, _cache):
        cached = store.get(key)
        if cached is not None and cached.size == prepared.data.n_samples:
            return cached
    predicted = _fit_predict(prepared, method, sensors, train)
    if len(_cache) >= _CACHE_SIZE:
        _cache.pop(next(iter(_cache)))
    _cache[key] = predicted
    return predicted


def _fit_predict(
    prepared: Prepared, method: str, sensors: Sequence[str] | None, train: np.ndarray
) -> np.ndarray:
    model = make_model(method, sensors).fit_rows(prepared.inputs, prepared.error_um, train)
    return model.predict(prepared.inputs)


def _fit_predict_one_thread(
    prepared: Prepared, method: str, sensors: Sequence[str] | None, train: np.ndarray
) -> np.ndarray:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        return _fit_predict(prepared, method, sensors, train)


def clear() -> None:
    """Forget every fit kept (a test comparing the prefilled replay with fits on demand)."""
    _cache.clear()
    _prefilled.clear()


def kept_on_demand() -> int:
    """How many fits were made on demand and are kept (none when a prefill served all)."""
    return len(_cache)


def training_sets(prepared: Prepared) -> list[np.ndarray]:
    """Every distinct training mask a leave-one-run-out replay fits: each run left out,
    and within each, the inner folds of the others (as ``_ReplayBase.inner_residual``)."""
    data = prepared.data
    runs = list(data.run_ids)
    masks = {r: data.run == r for r in runs}
    found: dict[bytes, np.ndarray] = {}
    for held in runs:
        train_runs = [r for r in runs if r != held]
        sets = [train_runs]
        folds = grouped_runs(np.arange(len(train_runs)))
        for fold in np.unique(folds):
            sets.append([r for r, f in zip(train_runs, folds, strict=True) if f != fold])
        for chosen in sets:
            mask = np.any([masks[r] for r in chosen], axis=0)
            found.setdefault(np.packbits(mask).tobytes(), mask)
    return list(found.values())


def prefill(
    prepared: Prepared, method: str, sensors: Sequence[str] | None, progress: bool = False
) -> int:
    """Fit every training set of the replay (:func:`training_sets`) once; the count."""
    _prefilled.clear()
    todo = [m for m in training_sets(prepared) if _key(prepared, method, sensors, m) not in _cache]
    bar = tqdm(
        total=len(todo), desc="base fits", unit="fit", disable=not progress, leave=False,
        mininterval=0,  # every fit shown as it ends
    )  # fmt: skip
    workers = min(os.cpu_count() or 1, len(todo))
    with bar:
        if len(todo) < PARALLEL_FROM_FITS or workers < 2:
            results = (_fit_predict(prepared, method, sensors, m) for m in todo)
        else:
            from joblib import Parallel, delayed

            jobs = (delayed(_fit_predict_one_thread)(prepared, method, sensors, m) for m in todo)
            results = Parallel(n_jobs=workers, return_as="generator")(jobs)
        for mask, predicted in zip(todo, results, strict=True):
            _prefilled[_key(prepared, method, sensors, mask)] = predicted
            bar.update(1)
    return len(todo)
