"""A machine's lag state: every augmented model's lags and the warm lags, kept across restarts.

An augmented model's lag terms remember every sample since the cold reference
(:mod:`models.online.streaming`), so they cannot be computed from one cycle's
rises. Two things carry that memory, both here:

* :class:`EffectStates` — the loop advances every augmented model in the bank each
  cycle, the selected one and the others alike, so a model the regime rules switch
  in mid-shift starts warm instead of from the present rises;
* :class:`WarmLags` — first-order lags of every input at every searched time
  constant. A model promoted while the gateway runs was not in the bank: started
  from the present rises, its lags would claim the machine had sat at today's
  temperatures forever. It takes its lag states from here
  (:meth:`WarmLags.state_for`) and predicts what it would have predicted had it been
  in the bank from the first cycle.

The residual analysis picks its time constants from fixed grids
(:data:`models.data.lag_terms.LAG_TAUS_S` and its neighbours), so the warm lags keep
the lag of every machine sensor's rise, of the speed terms and of the ambient rise
at each of those τ, with the very recursion a stream uses::

    x_k = a_k x_{k−1} + (1 − a_k) u_k,   a_k = exp(−Δt_k / τ),   x_0 = u_0

(across a logging gap, :func:`models.data.lag_terms.lag_coefficients`' exact
response to an input linear between samples; each input's last value is kept).
One difference: here each input steps whenever it is good, where a stream holds all
its lags in a cycle that lacks any of its inputs; the two agree whenever every
input was read, which is the normal case. A τ off the grids has no warm state; that
model's lags start from the present inputs (logged). The cost is 19 inputs × 9 τ
multiply-adds per cycle, and a few kB of state.

Both are kept in one file, ``<state_dir>/<machine>-effect-state.json``, next to the
temperature reference, each model's state with the checksum of the model it belongs to
(:func:`save_lag_file`, :func:`read_lag_file`). The file is written atomically on the
first cycle, then at most every ``SAVE_EVERY_S`` of machine time and when the loop
closes, by the state writer's thread in a running gateway
(:data:`gateway.process.file_writer.STATE`: the ``fsync`` does not hold up the event
loop, and the loop's close waits for the last save); a restarted gateway carries on
from it, the first cycle's Δt spanning the downtime. A state saved for a model that
has changed since, or one the model cannot take, is dropped (with a warning) and that
model's lags start again from the present rises. A save that fails (a full disk) never
stops the compensation; one warning names the first failure of an episode (any
machine, the same errno), one line says when saves work again.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gateway.live.bank.model_bank import BankedAugmented
from gateway.process.file_writer import FileWriter
from models.data.lag_terms import (
    AMBIENT_TAUS_S,
    HEAT_TAUS_S,
    LAG_TAUS_S,
    SPEED_SCALE_RPM,
    lag_step,
)
from models.json_files import write_json_atomic
from models.online.streaming import (
    AMBIENT_INPUT,
    RECORDING_START_KEY,
    RUN_START_KEY,
    SPEED_COLUMNS,
    TIME_KEY,
    StreamingAugmented,
)

log = logging.getLogger(__name__)

SAVE_EVERY_S = 60.0

#: Lag-state files whose last save failed, with its errno, in this process. A full
#: disk fails every machine's save every minute: the first failure of an episode is
#: logged, the rest only once a save succeeds again. An episode is one folder's (one
#: disk's): a file failing elsewhere, long ago, does not silence a new failure here.
#: Saves end in the state writer's thread or in the caller's: the lock keeps the two
#: apart.
_failing: dict[Path, int | None] = {}
_failing_lock = threading.Lock()


# --- the file ------------------------------------------------------------------------------
def save_lag_file(state_file: Path, payload: Mapping[str, object]) -> bool:
    """Write ``payload`` atomically; False (logged once per episode) when it cannot be."""
    try:
        write_json_atomic(state_file, dict(payload))
    except OSError as exc:  # compensation goes on; a restart would start the lags again
        lag_file_saved(state_file, exc)
        return False
    lag_file_saved(state_file, None)
    return True


def lag_file_saved(state_file: Path, error: OSError | None) -> None:
    """How a save ended (``error`` None: written): a failure that starts an episode is
    logged, and so is the first success after one."""
    with _failing_lock:
        if error is not None:
            _save_failed(state_file, error)
        elif _failing.pop(state_file, False) is not False and not _failing_beside(state_file):
            log.info("%s: lag states are saved again", state_file)


def _failing_beside(state_file: Path) -> dict[Path, int | None]:
    """The failing files in ``state_file``'s folder (itself included)."""
    return {path: errno for path, errno in _failing.items() if path.parent == state_file.parent}


def _save_failed(state_file: Path, exc: OSError) -> None:
    """Log a failed save only if it starts an episode: no other file (of any machine)
    in its folder is failing the same way already, and this one was not."""
    beside = _failing_beside(state_file)
    episode = exc.errno not in beside.values() and state_file not in beside
    _failing[state_file] = exc.errno
    if episode:
        log.warning(
            "%s: cannot save the lag states: %s (compensation goes on; saves that fail "
            "the same way are not logged again until one succeeds)",
            state_file,
            exc,
        )


def read_lag_file(state_file: Path | None) -> dict[str, Any] | None:
    """The saved document (its ``models`` an object), or None: no file, or unreadable (logged)."""
    if state_file is None or not state_file.exists():
        return None
    try:
        document = json.loads(state_file.read_text(encoding="utf-8"))
        if not isinstance(document["models"], dict):
            raise TypeError("'models' is not an object")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("%s: unreadable (%s); every lag starts again", state_file, exc)
        return None
    return document


# --- the warm lags of every input --------------------------------------------------------
#: Every time constant the residual analysis searches (s), zero (no lag) left out.
TAUS_S = tuple(sorted({t for t in (*LAG_TAUS_S, *HEAT_TAUS_S, *AMBIENT_TAUS_S) if t > 0}))


class WarmLags:
    """The lag of each input at each τ of :data:`TAUS_S`, since the first cycle.

    Its clock (``start_s``, where ``drift`` counts from, and ``time_s``) starts
    with the first cycle that has a good input, as a stream's starts with its
    first complete sample.
    """

    def __init__(self, sensors: Iterable[str], ambient_sensor: str | None) -> None:
        self.sensors = tuple(sensors)
        self.ambient_sensor = ambient_sensor
        self.taus_s = np.array(TAUS_S)
        self.reset()

    def reset(self) -> None:
        """Forget every lag: the next cycle starts them from its inputs."""
        self.start_s: float | None = None  # first cycle stepped: where drift counts from
        self.time_s: float | None = None  # last cycle stepped
        self._values: dict[str, np.ndarray] = {}
        self._times: dict[str, float] = {}
        self._last: dict[str, float] = {}  # each input's last good value

    def step(self, time_s: float, rises_C: Mapping[str, float], speed_rpm: float | None) -> None:
        """Advance the lag of every input that is good this cycle."""
        if self.time_s is not None and time_s < self.time_s:
            self.reset()  # the clock went back: start again
        good = self._good_inputs(rises_C, speed_rpm)
        if not good:
            return  # as a stream, whose clock starts with its first complete sample
        if self.start_s is None:
            self.start_s = float(time_s)
        self.time_s = float(time_s)
        # The inputs last stepped at the same time share one Δt: they step as one
        # (inputs × τ) array, the same multiply-adds as one row at a time, far fewer
        # numpy calls (all of them, normally: every input good every cycle).
        by_dt: dict[float, list[str]] = {}
        for name in good:
            if name in self._values:
                by_dt.setdefault(time_s - self._times[name], []).append(name)
            else:
                self._values[name] = np.full(self.taus_s.size, good[name])
        for dt_s, names in by_dt.items():
            previous = np.array([self._values[name] for name in names])
            inputs_now = np.array([[good[name]] for name in names])
            inputs_before = np.array([[self._last.get(name, good[name])] for name in names])
            stepped = lag_step(previous, inputs_before, inputs_now, dt_s, self.taus_s)
            for name, row in zip(names, stepped, strict=True):
                self._values[name] = row
        for name in good:
            self._times[name] = float(time_s)
            self._last[name] = good[name]

    def _good_inputs(
        self, rises_C: Mapping[str, float], speed_rpm: float | None
    ) -> dict[str, float]:
        """This cycle's finite inputs: sensor rises, the ambient rise, the speed terms."""
        inputs: dict[str, float | None] = {s: rises_C.get(s) for s in self.sensors}
        if self.ambient_sensor is not None:
            inputs[AMBIENT_INPUT] = rises_C.get(self.ambient_sensor)
        if speed_rpm is not None and math.isfinite(speed_rpm):
            n = float(speed_rpm) / SPEED_SCALE_RPM
            inputs[SPEED_COLUMNS[0]], inputs[SPEED_COLUMNS[1]] = n, n * n
        return {n: float(v) for n, v in inputs.items() if v is not None and math.isfinite(v)}

    def state_for(self, stream: StreamingAugmented) -> tuple[dict[str, float] | None, str]:
        """``stream``'s state as if it had been stepped since the first cycle, or (None, why)."""
        if self.time_s is None or self.start_s is None:
            return None, "no cycle has run yet"
        state = {
            TIME_KEY: self.time_s,
            RUN_START_KEY: self.start_s,
            RECORDING_START_KEY: self.start_s,
        }
        inputs: dict[str, float] = {}
        complete = True  # every input's last value known (not a state of an earlier release)
        for term in stream.terms:
            if not term.lagged:
                continue
            matches = np.flatnonzero(np.isclose(self.taus_s, term.tau_s, rtol=0, atol=1e-9))
            if matches.size == 0:
                return None, f"{term.effect} τ = {term.tau_s:g} s is not a searched time constant"
            for key, input_key, column in zip(
                term.state_keys(), term.input_keys(), term.columns, strict=True
            ):
                values = self._values.get(column)
                if values is None:
                    return None, f"no good value of {column} has been seen yet"
                state[key] = float(values[matches[0]])
                complete &= column in self._last
                inputs[input_key] = self._last.get(column, math.nan)
        if complete:
            state.update(inputs)
        return state, ""

    def export_state(self) -> dict[str, Any]:
        return {
            "taus_s": [float(t) for t in self.taus_s],
            "start_s": self.start_s,
            "time_s": self.time_s,
            "inputs": {
                name: {
                    "time_s": self._times[name],
                    "values": [float(v) for v in values],
                    "last": self._last.get(name),
                }
                for name, values in self._values.items()
            },
        }

    def import_state(self, state: Mapping[str, Any]) -> None:
        """Carry on from :meth:`export_state`; raises ValueError for a state that does not fit."""
        if [float(t) for t in state["taus_s"]] != [float(t) for t in self.taus_s]:
            raise ValueError("saved for other time constants")
        values = {str(k): np.asarray(v["values"], dtype=float) for k, v in state["inputs"].items()}
        times = {str(k): float(v["time_s"]) for k, v in state["inputs"].items()}
        if any(v.shape != self.taus_s.shape or not np.isfinite(v).all() for v in values.values()):
            raise ValueError("a saved lag is not a finite row of the right length")
        self.start_s = None if state["start_s"] is None else float(state["start_s"])
        self.time_s = None if state["time_s"] is None else float(state["time_s"])
        # "last" is absent from states saved by an earlier release: the next step holds
        saved = state["inputs"].items()
        last = {str(k): float(v["last"]) for k, v in saved if v.get("last") is not None}
        if not all(math.isfinite(v) for v in last.values()):
            raise ValueError("a saved input is not finite")
        self._values, self._times, self._last = values, times, last


# --- the augmented models' lags ---------------------------------------------------------
class EffectStates:
    """One :class:`~models.online.streaming.StreamingAugmented` per augmented model of the bank,
    and the machine's :class:`WarmLags`; saved together in one file."""

    def __init__(
        self,
        models: Iterable[BankedAugmented],
        state_file: Path | None,
        save_every_s: float = SAVE_EVERY_S,
        warm: WarmLags | None = None,
        writer: FileWriter | None = None,
    ) -> None:
        """``warm``: lags of every input kept for models added later (:meth:`set_models`).
        ``writer``: saves are handed to its thread (the event loop does not wait for the
        disk; :meth:`flush` waits for them); without one, :meth:`save` writes itself."""
        self.models = list(models)
        self.streams = {m.model_id: m.stream() for m in self.models}
        self.state_file = state_file
        self.save_every_s = save_every_s
        self.warm = warm
        self.writer = writer
        self._saved_s: float | None = None
        self._restore()

    def set_models(self, models: Iterable[BankedAugmented]) -> None:
        """Carry these models from now on: a kept model keeps its state, a new one starts
        warm from :attr:`warm` (as if it had been stepped since the first cycle)."""
        streams = {}
        for model in models:
            kept = next((m for m in self.models if m.model_id == model.model_id), None)
            if kept is not None and kept.document.get("sha256") == model.document.get("sha256"):
                streams[model.model_id] = self.streams[model.model_id]
                continue
            stream = model.stream()
            self._start_warm(model, stream)
            streams[model.model_id] = stream
        self.models = list(models)
        self.streams = streams

    def _start_warm(self, model: BankedAugmented, stream: StreamingAugmented) -> None:
        """Give a new model's stream the lags it would have had since the first cycle."""
        if self.warm is None:
            state, why = None, "no warm lags kept"
        else:
            state, why = self.warm.state_for(stream)
        if state is None:
            log.warning("%s: its lags start from the present inputs (%s)", model.model_id, why)
            return
        stream.import_state(state)
        log.info("%s: lag states taken warm from the first cycle on", model.model_id)

    def advance(
        self, time_s: float, rises_C: Mapping[str, float], speed_rpm: float | None
    ) -> dict[str, float | None]:
        """Step every augmented model with this cycle's good rises; their predictions, µm.

        A model whose inputs are incomplete this cycle predicts None and keeps
        its state for the next complete cycle.
        """
        if self.warm is not None:
            self.warm.step(time_s, rises_C, speed_rpm)
        predicted: dict[str, float | None] = {}
        for model in self.models:
            stream = self.streams[model.model_id]
            if stream.time_s is not None and time_s < stream.time_s:
                log.warning(
                    "%s: the clock (%.0f s) is before the saved lag state (%.0f s); "
                    "its lags start again",
                    model.model_id,
                    time_s,
                    stream.time_s,
                )
                stream.reset()
            ambient_rise_C = rises_C.get(model.ambient_sensor) if model.ambient_sensor else None
            value = stream.step(time_s, rises_C, speed_rpm, ambient_rise_C)
            finite = value is not None and math.isfinite(value)
            predicted[model.model_id] = value if finite else None
        if (self.models or self.warm) and (
            self._saved_s is None or time_s - self._saved_s >= self.save_every_s
        ):
            self.save()
            self._saved_s = time_s
        return predicted

    def save(self) -> None:
        if self.state_file is None or not (self.models or self.warm):
            return
        states = {
            m.model_id: {
                "sha256": m.document.get("sha256"),
                "state": self.streams[m.model_id].export_state(),
            }
            for m in self.models
        }
        payload: dict[str, object] = {"models": states}
        if self.warm is not None:
            payload["warm_lags"] = self.warm.export_state()
        if self.writer is None:
            save_lag_file(self.state_file, payload)
            return
        # The text is taken now (the states go on changing); only the disk waits.
        text = json.dumps(payload, indent=2, ensure_ascii=False) + "\n"
        self.writer.submit(self.state_file, text, lag_file_saved)

    async def flush(self) -> None:
        """Wait until the saves handed to the writer are on disk (a stop's last save)."""
        if self.writer is not None:
            await self.writer.drain()

    def _restore(self) -> None:
        document = read_lag_file(self.state_file)
        if document is None:
            return
        saved = document["models"]
        if self.warm is not None and isinstance(document.get("warm_lags"), dict):
            try:
                self.warm.import_state(document["warm_lags"])
            except (KeyError, TypeError, ValueError) as exc:
                log.warning(
                    "%s: saved warm lags refused (%s); they start again", self.state_file, exc
                )
                self.warm.reset()
        for model in self.models:
            entry = saved.get(model.model_id)
            if not isinstance(entry, dict):  # new since the save (a promotion): warm if we can
                if self.warm is not None and self.warm.time_s is not None:
                    self._start_warm(model, self.streams[model.model_id])
                continue
            if entry.get("sha256") != model.document.get("sha256"):
                log.warning(
                    "%s: the saved lag state belongs to an earlier version of the model; "
                    "its lags start again",
                    model.model_id,
                )
                continue
            try:
                self.streams[model.model_id].import_state(entry["state"])
            except (KeyError, TypeError, ValueError) as exc:
                log.warning(
                    "%s: saved lag state refused (%s); its lags start again", model.model_id, exc
                )
