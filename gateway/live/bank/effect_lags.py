"""The lag states of a machine's augmented models: advanced every cycle, kept across restarts.

An augmented model's lag terms remember every sample since the cold reference
(:mod:`models.online.streaming`), so they cannot be computed from one cycle's
rises. The loop advances every augmented model in the bank each cycle, the
selected one and the others alike, so a model the regime rules switch in
mid-shift starts warm instead of from the present rises.

The states are kept in ``<state_dir>/<machine>-effect-state.json``, next to the
temperature reference, each with the checksum of the model it belongs to. The
file is written atomically on the first cycle, then at most every
``SAVE_EVERY_S`` of machine time and when the loop closes; a restarted gateway
carries on from it, the first cycle's Δt spanning the downtime. A state saved
for a model that has changed since, or one the model cannot take, is dropped
(with a warning) and that model's lags start again from the present rises.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterable, Mapping
from pathlib import Path

from gateway.live.bank.model_bank import BankedAugmented
from gateway.live.bank.warm_lags import WarmLags
from models.json_files import write_json_atomic
from models.online.streaming import StreamingAugmented

log = logging.getLogger(__name__)

SAVE_EVERY_S = 60.0

#: Lag-state files whose last save failed, with its errno, in this process. A full
#: disk fails every machine's save every minute: the first failure of an episode is
#: logged, the rest only once a save succeeds again.
_failing: dict[Path, int | None] = {}


class EffectStates:
    """One :class:`~models.online.streaming.StreamingAugmented` per augmented model of the bank."""

    def __init__(
        self,
        models: Iterable[BankedAugmented],
        state_file: Path | None,
        save_every_s: float = SAVE_EVERY_S,
        warm: WarmLags | None = None,
    ) -> None:
        """``warm``: lags of every input kept for models added later (:meth:`set_models`)."""
        self.models = list(models)
        self.streams = {m.model_id: m.stream() for m in self.models}
        self.state_file = state_file
        self.save_every_s = save_every_s
        self.warm = warm
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
        try:
            write_json_atomic(self.state_file, payload)
        except OSError as exc:  # compensation goes on; a restart would start the lags again
            self._failed(self.state_file, exc)
            return
        if _failing.pop(self.state_file, False) is not False and not _failing:
            log.info("%s: lag states are saved again", self.state_file)

    @staticmethod
    def _failed(state_file: Path, exc: OSError) -> None:
        """Log a failed save only if it starts an episode: no other file (of any machine)
        is failing the same way already, and this one was not."""
        episode = exc.errno not in _failing.values() and state_file not in _failing
        _failing[state_file] = exc.errno
        if episode:
            log.warning(
                "%s: cannot save the lag states: %s (compensation goes on; saves that fail "
                "the same way are not logged again until one succeeds)",
                state_file,
                exc,
            )

    def _restore(self) -> None:
        if self.state_file is None or not self.state_file.exists():
            return
        try:
            document = json.loads(self.state_file.read_text(encoding="utf-8"))
            saved = document["models"]
            if not isinstance(saved, dict):
                raise TypeError("'models' is not an object")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("%s: unreadable (%s); every lag starts again", self.state_file, exc)
            return
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
