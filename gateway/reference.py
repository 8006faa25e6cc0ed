"""The running machine's temperature reference: the cold state the models start from.

The models predict the error *rise* from temperature *rises* above a cold
reference (see ``models/references.py``). In production that reference is taken
once, with the machine cold: each sensor's first good reading after the gateway
first starts (``first-reading``), or values set in the configuration (``fixed``).
It is kept in a small JSON file under the state folder, so a gateway restarted
mid-shift, with a warm machine, keeps the cold reference instead of taking a
warm one.

The error has no reference here: a gateway never rebases its error. Models are
fitted on the error as measured, whose reference is the model's own intercept
(the stored ``error_reference``), and the loop compensates the prediction as it
is, from the start of the recording to its end, whatever the spindle did first.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from models.json_files import write_json_atomic


class TemperatureReference:
    def __init__(self, mode: str, fixed_C: Mapping[str, float], state_file: Path | None) -> None:
        self.mode = mode
        self.state_file = state_file
        self.values_C: dict[str, float] = dict(fixed_C)
        if mode == "first-reading" and state_file is not None and state_file.exists():
            saved = json.loads(state_file.read_text(encoding="utf-8"))
            self.values_C.update({k: float(v) for k, v in saved.get("reference_C", {}).items()})

    def observe(self, good_readings_C: Mapping[str, float]) -> None:
        """Take the first good reading of each sensor that has no reference yet."""
        if self.mode != "first-reading":
            return
        new = {k: v for k, v in good_readings_C.items() if k not in self.values_C}
        if new:
            self.values_C.update(new)
            self._save()

    def rises_C(
        self, readings_C: Mapping[str, float], sensors: tuple[str, ...]
    ) -> list[float] | None:
        """Rises of ``sensors`` above the reference; None if one lacks a value or a reference."""
        if any(s not in readings_C or s not in self.values_C for s in sensors):
            return None
        return [readings_C[s] - self.values_C[s] for s in sensors]

    def available_rises_C(self, readings_C: Mapping[str, float]) -> dict[str, float]:
        """Rises of every reading that has a reference, by sensor."""
        return {s: v - self.values_C[s] for s, v in readings_C.items() if s in self.values_C}

    def _save(self) -> None:
        if self.state_file is not None:
            write_json_atomic(self.state_file, {"reference_C": self.values_C}, sort_keys=True)
