"""Spindle speed programmes: named ones from YAML, and random "production" ones.

A programme is a list of segments (duration s, speed r/min). Named programmes
(``programs.yaml``) follow paper 002's ISO 230-3 spectra and constant speeds; a
production programme is drawn at random (seeded): spindle-on periods at speeds
from a set, separated by idle gaps, as a machine in a job shop would run.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.yaml_loader import load_yaml

PROGRAMS_FILE = Path(__file__).with_name("programs.yaml")
PRODUCTION_PREFIX = "production"


@dataclass(frozen=True)
class SpeedProgram:
    name: str
    segments: tuple[tuple[float, float], ...]  # (duration_s, speed_rpm)

    def __post_init__(self) -> None:
        if not self.segments:
            raise ValueError(f"programme '{self.name}' has no segments")
        for duration, speed in self.segments:
            if duration <= 0 or speed < 0:
                raise ValueError(
                    f"programme '{self.name}': segment ({duration} s, {speed} r/min) needs "
                    "a positive duration and a speed ≥ 0"
                )

    @property
    def duration_s(self) -> float:
        return float(sum(d for d, _ in self.segments))

    def speed_at(self, time_s: float) -> float:
        """Commanded speed at ``time_s`` from the programme start (0 after the end)."""
        elapsed = 0.0
        for duration, speed in self.segments:
            elapsed += duration
            if time_s < elapsed:
                return float(speed) if time_s >= 0 else 0.0
        return 0.0


def _expand(entry: Any, parts: dict[str, list], name: str) -> list[tuple[float, float]]:
    if isinstance(entry, str):
        if entry not in parts:
            raise ValueError(f"programme '{name}' uses unknown part '{entry}'")
        entry = parts[entry]
    segments = []
    for item in entry:
        if not (isinstance(item, list | tuple) and len(item) == 2):
            raise ValueError(f"programme '{name}': expected [minutes, speed_rpm], got {item!r}")
        minutes, speed = item
        segments.append((float(minutes) * 60.0, float(speed)))
    return segments


def load_programs(path: Path = PROGRAMS_FILE) -> dict[str, SpeedProgram]:
    """The named programmes of ``path``; a bad one is refused with its line."""
    document = load_yaml(path)
    raw = document.data
    if not isinstance(raw, dict) or not isinstance(raw.get("programs"), dict):
        raise document.error((), "a mapping with a 'programs' mapping was expected")
    parts = raw.get("parts") or {}
    if not isinstance(parts, dict):
        raise document.error(("parts",), "a mapping of named parts was expected")
    programs = {}
    for name, entries in raw["programs"].items():
        try:
            if not isinstance(entries, list):
                raise ValueError(f"programme '{name}': a list of parts or segments was expected")
            segments: list[tuple[float, float]] = []
            for entry in entries:
                segments.extend(_expand(entry, parts, name))
            programs[name] = SpeedProgram(name, tuple(segments))
        except (TypeError, ValueError) as exc:
            raise document.error(("programs", name), str(exc)) from None
    return programs


def production_program(
    seed: int,
    duration_s: float = 8 * 3600.0,
    speeds_rpm: tuple[float, ...] = (1500, 2500, 3500, 4500, 6000, 7500),
    on_minutes: tuple[float, float] = (5.0, 60.0),
    idle_minutes: tuple[float, float] = (1.0, 20.0),
    idle_probability: float = 0.4,
) -> SpeedProgram:
    """A random job-shop day: spindle-on periods, sometimes an idle gap, then cool-down."""
    rng = np.random.default_rng(seed)
    segments: list[tuple[float, float]] = []
    total = 0.0
    while total < duration_s:
        if segments and rng.random() < idle_probability:
            length = rng.uniform(*idle_minutes) * 60.0
            speed = 0.0
        else:
            length = rng.uniform(*on_minutes) * 60.0
            speed = float(rng.choice(speeds_rpm))
        length = round(min(length, duration_s - total))
        if length <= 0:
            break
        segments.append((float(length), speed))
        total += length
    segments.append((7200.0, 0.0))
    return SpeedProgram(f"{PRODUCTION_PREFIX}-{seed}", tuple(segments))


def program_by_name(name: str, programs: dict[str, SpeedProgram] | None = None) -> SpeedProgram:
    """A named programme, or ``production-<seed>`` for a random one."""
    programs = load_programs() if programs is None else programs
    if name in programs:
        return programs[name]
    prefix = PRODUCTION_PREFIX + "-"
    if name.startswith(prefix) and name[len(prefix) :].isdigit():
        return production_program(int(name[len(prefix) :]))
    known = ", ".join([*programs, "production-<seed>"])
    raise ValueError(f"unknown programme '{name}' (known: {known})")
