"""The optional gate on an unsure prediction (``compensation.when_uncertain``).

When the interval's half-width (:mod:`gateway.live.interval`) is above the width the
plant set, the aim handed to the compensation policy is either the value the CNC
already applies (``hold``) or the prediction scaled down (``scale``). The policy then
clamps and slew-limits it as any other aim, so entering or leaving the gate never
steps the tool. An unknown width (a model stored without a calibration) never gates.
Each episode is logged once when it starts and once when it ends.
"""

from __future__ import annotations

import logging

from gateway.config import WhenUncertainSection

log = logging.getLogger(__name__)


class UncertaintyGate:
    """The aim for one machine's policy, given this cycle's prediction and width."""

    def __init__(self, machine: str, config: WhenUncertainSection | None) -> None:
        self.machine = machine
        self.config = config
        self.active = False

    def aim(
        self, predicted_um: float | None, half_width_um: float | None, applied_um: float
    ) -> float | None:
        """The value to aim for: ``predicted_um`` unless the gate is on and the width is
        above its threshold."""
        config = self.config
        unsure = (
            config is not None
            and predicted_um is not None
            and half_width_um is not None
            and half_width_um > config.above_um
        )
        self._log_change(unsure, half_width_um)
        if not unsure or config is None or predicted_um is None:
            return predicted_um
        if config.action == "hold":
            return applied_um
        return predicted_um * config.scale

    def _log_change(self, unsure: bool, half_width_um: float | None) -> None:
        if unsure == self.active:
            return
        self.active = unsure
        config = self.config
        assert config is not None
        if unsure:
            log.warning(
                "%s: prediction unsure (interval ±%.1f µm above %.1f µm): compensation %s",
                self.machine,
                half_width_um,
                config.above_um,
                "held" if config.action == "hold" else f"scaled by {config.scale:g}",
            )
        else:
            log.info("%s: prediction sure again: compensation follows it", self.machine)
