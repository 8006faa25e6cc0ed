"""Hidden effects: physics the sensors do not show directly, switched on by name.

They are how residual analysis is tested. Each one changes either the boundary
temperatures the network sees (ambient, cooler) or the Z growth (thermal_lag,
speed_direct, drift), and each leaves a signature in recorded data:

- ``thermal_lag``: ``share`` of the shaft's growth follows the shaft temperature
  only through a first-order lag of ``tau_s`` (a tool holder / spindle nose no
  sensor touches), so the error keeps growing after the sensors settle.
- ``speed_direct``: an instantaneous Z change a·n + b·n² (n in 1000 r/min) from
  centrifugal and gyroscopic forces: the error jumps at a speed step while the
  temperatures have not moved.
- ``ambient``: the hall temperature follows a sine of ``amplitude_C`` and
  ``period_s``. It reaches the big column (no sensor on it) while the enclosed
  spindle head keeps the enclosure air, so only the ambient sensor sees it.
- ``drift``: probe or fixture creep, ``um_per_h`` from the start of the run.
- ``cooler``: an oil cooler whose jacket around the bearing cartridge has a coolant that
  saw-tooths (``period_s``, ``amplitude_C`` around ambient + ``offset_C``),
  imposing the saw-tooth on the bearing sensors and the error.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from simulator.params import EFFECTS, MachineParams

NONE = "none"


def parse_effects(names: Iterable[str]) -> tuple[str, ...]:
    """Validated effect names; ``none`` (alone) means no hidden effect."""
    chosen = tuple(dict.fromkeys(n.strip() for n in names if n.strip()))
    if chosen == (NONE,) or not chosen:
        return ()
    unknown = [n for n in chosen if n not in EFFECTS]
    if unknown or NONE in chosen:
        choices = ", ".join((*EFFECTS, NONE))
        raise ValueError(
            f"unknown hidden effect(s) {unknown or [NONE]}: choose from {choices} (none alone)"
        )
    return chosen


class HiddenEffects:
    """The active effects of one machine, with the state they carry."""

    def __init__(self, params: MachineParams, active: Iterable[str]) -> None:
        self.active = parse_effects(active)
        self.p = params.effects
        self.ambient_C = params.ambient_C
        self.lag_state_C: float | None = None

    def __contains__(self, name: str) -> bool:
        return name in self.active

    @property
    def coolant_conductance_W_per_K(self) -> float:
        return self.p.cooler.conductance_W_per_K if "cooler" in self else 0.0

    def room_C(self, time_s: float) -> float:
        if "ambient" not in self:
            return self.ambient_C
        cycle = self.p.ambient
        return self.ambient_C + cycle.amplitude_C * math.sin(2 * math.pi * time_s / cycle.period_s)

    def coolant_C(self, time_s: float, room_C: float) -> float:
        if "cooler" not in self:
            return room_C
        c = self.p.cooler
        phase = (time_s / c.period_s) % 1.0
        return room_C + c.offset_C + c.amplitude_C * (2.0 * phase - 1.0)

    def advance_lag(self, shaft_C: float, dt_s: float) -> None:
        if "thermal_lag" not in self:
            return
        if self.lag_state_C is None:
            self.lag_state_C = shaft_C
        a = math.exp(-dt_s / self.p.thermal_lag.tau_s)
        self.lag_state_C = a * self.lag_state_C + (1 - a) * shaft_C

    def shaft_growth_um(self, shaft_C: float, reference_C: float, um_per_K: float) -> float:
        """Growth of the shaft, part of it through the hidden lag when that effect is on."""
        if "thermal_lag" not in self or self.lag_state_C is None:
            return um_per_K * (shaft_C - reference_C)
        share = self.p.thermal_lag.share
        return um_per_K * (
            (1 - share) * (shaft_C - reference_C) + share * (self.lag_state_C - reference_C)
        )

    def direct_um(self, speed_rpm: float, run_time_s: float) -> float:
        """Growth terms that are not temperatures: speed_direct and drift."""
        total = 0.0
        if "speed_direct" in self:
            krpm = speed_rpm / 1000.0
            total += (
                self.p.speed_direct.um_per_krpm * krpm + self.p.speed_direct.um_per_krpm2 * krpm**2
            )
        if "drift" in self:
            # creep starts with the run
            total += self.p.drift.um_per_h * max(0.0, run_time_s) / 3600.0
        return total
