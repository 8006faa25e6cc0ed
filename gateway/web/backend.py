"""What the console needs from the running gateway, in one place.

The console reads the machines' live state and changes models only through the
gateway's own methods (:meth:`gateway.wiring.Gateway.promote` and ``rollback``, the
SCADA methods' path, and the proposal store's ``reject``, the one ``models
reject`` calls), so a promotion from the browser is checked exactly like one
from SCADA or the command line.
"""

from __future__ import annotations

from typing import Any, Protocol

from gateway.outputs.axes import axis_cnc_um_per_unit, cnc_um_per_unit
from gateway.outputs.health import integer_counters
from gateway.web.series import SourceSpec


class GatewayLike(Protocol):
    config: Any
    loops: list[Any]
    supervisors: dict[str, Any]

    def health(self, machine_id: str) -> dict[str, Any]: ...
    def promote(self, machine_id: str, proposal_id: str, by: str = ...) -> str: ...
    def rollback(self, machine_id: str, by: str = ...) -> str: ...


class Backend:
    def __init__(self, gateway: GatewayLike) -> None:
        self._gateway = gateway
        self._loops = {loop.config.id: loop for loop in gateway.loops}

    @property
    def machines(self) -> list[str]:
        return list(self._loops)

    def loop(self, machine: str) -> Any:
        try:
            return self._loops[machine]
        except KeyError:
            raise KeyError(f"no machine {machine!r}") from None

    def facts(self, machine: str) -> dict[str, Any]:
        """Loop state and health counters for the overview row."""
        loop = self.loop(machine)
        supervisor = self._gateway.supervisors.get(machine)
        health = self._gateway.health(machine)
        if supervisor is not None and supervisor.last_error and getattr(loop, "cycles", 0) == 0:
            state = "restarting"
        elif not loop.compensation_enabled:
            state = "compensation off"
        else:
            state = "compensating"
        return {
            "state": state,
            "health": integer_counters(health),
            "models_version": loop.promotions.version,
            "cnc_unit": loop.config.compensation.unit,
        }

    def cnc_um_per_unit(self, machine: str) -> float:
        comp = self.loop(machine).config.compensation
        return cnc_um_per_unit(comp.unit, comp.sign)

    def axes(self, machine: str) -> dict[str, float]:
        """A multi-axis machine's axes in configured order, each with its CNC value's µm
        per unit (empty for a single-axis machine)."""
        return axis_cnc_um_per_unit(self.loop(machine).config)

    def proposals(self, machine: str) -> list[Any]:
        return list(self.loop(machine).promotions.store.list(machine_id=machine))

    def promote(self, machine: str, proposal_id: str, by: str) -> str:
        self._own(machine, proposal_id)
        return self._gateway.promote(machine, proposal_id, by=by)

    def reject(self, machine: str, proposal_id: str, by: str) -> str:
        self._own(machine, proposal_id)
        proposal = self.loop(machine).promotions.store.reject(proposal_id, note=f"rejected, {by}")
        return f"rejected {proposal.describe()}"

    def rollback(self, machine: str, by: str) -> str:
        return self._gateway.rollback(machine, by=by)

    def _own(self, machine: str, proposal_id: str) -> None:
        proposal = self.loop(machine).promotions.store.get(proposal_id)
        if proposal.machine_id != machine:
            raise ValueError(f"{proposal_id} is a proposal for {proposal.machine_id}")

    def source(self) -> SourceSpec:
        """Where the logged data is read back from (as ``export`` reads it)."""
        logging = self._gateway.config.logging
        influx = logging.influxdb
        if influx is None:
            return ("local", str(logging.local_store))
        return (
            "influx",
            influx.url_value(),
            influx.token(),
            influx.org_value(),
            influx.bucket_value(),
            influx.timeout_s,
        )
