"""The running machine's temperature reference: the cold state the models start from.

The models predict the error *rise* from temperature *rises* above a cold
reference (see ``models/data/references.py``). In production that reference is taken
once, with the machine cold: each sensor's first good reading after the gateway
first starts (``first-reading``), or values set in the configuration (``fixed``).
It is kept in a small JSON file under the state folder, so a gateway restarted
mid-shift, with a warm machine, keeps the cold reference instead of taking a
warm one.

The error has no reference here: a gateway never rebases its error. Models are
fitted on the error as measured, whose reference is the model's own intercept
(the stored ``error_reference``), and the loop compensates the prediction as it
is, from the start of the recording to its end, whatever the spindle did first.

In a running gateway the file is written by the state writer's thread
(:data:`gateway.process.file_writer.STATE`, atomic with ``fsync``, as the lag states):
a thousand machines taking their first reading in the same cycle at a first start
made a thousand ``fsync`` calls on the event loop, each holding every other machine's
cycle (17 ms each on a busy disk). A save that fails is tried again next cycle.

The file also marks whether the first readings were taken with the spindle
turning (``taken_turning``): a warm reference, which the sensor plausibility
check must judge differently (:mod:`gateway.live.plausibility`) at this start and at
every later one on the same file. A file without the mark (an older gateway)
leaves it unknown.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from gateway.process.file_writer import FileWriter
from models.data.unit_ranges import TEMPERATURE_C, first_implausible
from models.json_files import write_json_atomic

log = logging.getLogger(__name__)


class TemperatureReference:
    def __init__(
        self,
        mode: str,
        fixed_C: Mapping[str, float],
        state_file: Path | None,
        writer: FileWriter | None = None,
    ) -> None:
        """``writer``: saves are handed to its thread (the event loop does not wait for
        the disk; the loop's close waits for the writer); without one, saved in place."""
        self.mode = mode
        self.state_file = state_file
        self.writer = writer
        self.values_C: dict[str, float] = dict(fixed_C)
        self._unsaved = False  # first readings taken that the file does not hold yet
        self._revision = 0  # counts the changes, so a save in flight knows if it is the last
        self._handed_over: int | None = None  # the revision with the writer now
        self._save_failing = False
        #: Whether the first readings were taken with the spindle turning (None: unknown).
        self.taken_turning: bool | None = None
        # The speed at this start's first cycle: a machine already running when the
        # gateway started is warm, whichever cycle the first good readings come at.
        self._start_speed_rpm: tuple[float | None] | None = None
        if mode == "first-reading" and state_file is not None and state_file.exists():
            self.values_C.update(read_saved_reference(state_file))
            self.taken_turning = read_taken_turning(state_file)

    def observe(self, good_readings_C: Mapping[str, float], speed_rpm: float | None = None) -> None:
        """Take the first good reading of each sensor that has no reference yet, and save
        the reference until a save succeeds; ``speed_rpm`` at the first call says whether
        the machine was running when the gateway started."""
        if self.mode != "first-reading":
            return
        if self._start_speed_rpm is None:
            self._start_speed_rpm = (speed_rpm,)
        new = {k: v for k, v in good_readings_C.items() if k not in self.values_C}
        if new:
            if not self.values_C and self._start_speed_rpm[0] is not None:
                self.taken_turning = abs(self._start_speed_rpm[0]) > 0
            self.values_C.update(new)
            self._unsaved = True
            self._revision += 1
        if self._unsaved:
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
        """Write the reference (or hand it to the writer); a full or failing disk keeps it
        in memory, named once, and the next cycle tries again (the loop goes on
        compensating meanwhile)."""
        if self.state_file is None:
            self._unsaved = False
            return
        document: dict[str, object] = {"reference_C": self.values_C}
        if self.taken_turning is not None:
            document["taken_turning"] = self.taken_turning
        revision = self._revision
        if self.writer is None:
            try:
                write_json_atomic(self.state_file, document, sort_keys=True)
            except OSError as exc:
                self._saved(revision, exc)
                return
            self._saved(revision, None)
            return
        if self._handed_over == revision:
            return  # on its way to the disk: its outcome decides
        # The text is taken now; a newer one handed over before this is written replaces it.
        self._handed_over = revision
        text = json.dumps(document, indent=2, sort_keys=True, ensure_ascii=False) + "\n"
        self.writer.submit(self.state_file, text, lambda _path, error: self._saved(revision, error))

    def _saved(self, revision: int, error: OSError | None) -> None:
        """How the save of ``revision`` ended (in the writer's thread with a writer)."""
        if self._handed_over == revision:
            self._handed_over = None
        if error is not None:
            if not self._save_failing:
                log.error(
                    "%s: cannot save the cold reference (%s); it is kept in memory and saved "
                    "once the disk allows: a restart before that takes a new one",
                    self.state_file,
                    error.strerror or error,
                )
                self._save_failing = True
            return
        if self._save_failing:
            log.info("%s: the cold reference is saved now", self.state_file)
        self._save_failing = False
        if revision == self._revision:
            self._unsaved = False


def read_saved_reference(state_file: Path) -> dict[str, float]:
    """The cold reference saved by an earlier start, °C per sensor.

    A file that cannot be read stops the gateway with its name and what to do, rather
    than being replaced: a new first reading now, with the machine possibly warm, would
    make every rise too small, and once the machine cooled below it the rises would turn
    negative and the compensation would move the tool the wrong way.
    """
    try:
        saved = json.loads(state_file.read_text(encoding="utf-8"))
        values = saved["reference_C"]
        if not isinstance(values, dict):
            raise TypeError("'reference_C' is not an object")
        reference = {str(k): float(v) for k, v in values.items()}
        sensors = list(values)
        bad = first_implausible(np.array(list(reference.values())), TEMPERATURE_C)
        if bad is not None:
            raise ValueError(
                f"sensor {sensors[bad]}: expected {TEMPERATURE_C.describe()}, "
                f"found {values[sensors[bad]]!r}"
            )
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        reason = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ValueError(
            f"{state_file}: the machine's saved cold reference is unreadable ({reason}); "
            "restore the file, or delete it to take a new reference with the machine cold"
        ) from None
    return reference


def read_taken_turning(state_file: Path) -> bool | None:
    """The saved reference's ``taken_turning`` mark (None: absent); ValueError if not a boolean.

    Called after :func:`read_saved_reference` accepted the file.
    """
    mark = json.loads(state_file.read_text(encoding="utf-8")).get("taken_turning")
    if mark is not None and not isinstance(mark, bool):
        raise ValueError(
            f"{state_file}: 'taken_turning' must be true or false, found {mark!r}; "
            "correct it, or delete the file to take a new reference with the machine cold"
        )
    return mark
