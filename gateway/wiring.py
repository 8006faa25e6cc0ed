"""Building and running the gateway from its configuration: one loop per machine.

Each machine loop runs under its own :class:`gateway.process.supervision.Supervised`: a
loop that raises is logged, restarted after a back-off and counted
(``loop_restarts``), while the other machines keep cycling. A sink that raises
is counted by the loop and never stops a cycle. :meth:`Gateway.health` gathers
every counter of a machine (and the forwarder's) once, with
:mod:`gateway.outputs.health`, for SCADA, the heartbeat, the console and Sparkplug.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from drivers.bus_hub import BusHub, rtu_silence_s
from drivers.clock import Clock, WallClock
from drivers.cnc import CncClient, CncError
from drivers.cnc_modbus import ModbusCnc
from drivers.cnc_opcua import OpcUaCnc
from drivers.register_map import DeviceRegisters
from drivers.transmitters import DeviceMap, ModbusConnection, TransmitterBus
from drivers.yaml_loader import KeyPathError
from gateway.config import (
    SINGLE_AXIS,
    GatewayConfig,
    MachineSection,
    login_limits,
    rtu_buses,
)
from gateway.live.axis import axis_targets
from gateway.live.bank.model_bank import ModelBank
from gateway.live.bank.promotion import Promotions, proposals_view
from gateway.live.loop import MachineLoop
from gateway.live.proposal_monitor import MonitorSink, build_monitor
from gateway.live.record import CycleRecord, Sink
from gateway.live.scheduler import CycleScheduler
from gateway.outputs.health import Health, gateway_counters, machine_health, scalar_counters
from gateway.outputs.sinks import Outputs
from gateway.process.gc_tuning import frozen_startup_heap
from gateway.process.supervision import Supervised
from gateway.scada.server import ScadaServer, ScadaSettings, ScadaUser
from gateway.web.server import WebConsole, build_web
from models.data.dataset import ambient_sensor_of

if TYPE_CHECKING:
    from gateway.sparkplug.node import EdgeNode

log = logging.getLogger(__name__)


def build_buses(
    machine: MachineSection, hubs: dict[str, BusHub] | None = None
) -> list[TransmitterBus]:
    """The machine's buses; an RTU bus reads through ``hubs[port]`` when given (a line
    shared with other machines, :func:`shared_hubs`)."""
    hubs = shared_hubs([machine]) if hubs is None else hubs
    buses = []
    for bus in machine.transmitters:
        devices = [
            DeviceMap(
                d.device_id, tuple(d.channels), DeviceRegisters(d.map, d.effective_workarounds)
            )
            for d in bus.devices
        ]
        if bus.tcp is not None:
            buses.append(
                TransmitterBus(
                    devices,
                    tcp=(bus.tcp.host, bus.tcp.port),
                    timeout_s=bus.timeout_s,
                    name=bus.name,
                )
            )
        else:
            assert bus.rtu is not None
            buses.append(
                TransmitterBus(
                    devices,
                    serial_port=bus.rtu.port,
                    baudrate=bus.rtu.baudrate,
                    parity=bus.rtu.parity,
                    timeout_s=bus.timeout_s,
                    name=bus.name,
                    hub=hubs[bus.rtu.port],
                )
            )
    return buses


def build_cnc(machine: MachineSection, clock: Clock | None = None) -> CncClient:
    """The CNC client; its reconnect back-off runs on the gateway's clock."""
    cnc = machine.cnc
    now = (clock or WallClock()).now
    if cnc.opcua is not None:
        o = cnc.opcua
        return OpcUaCnc(
            o.endpoint,
            namespace=o.namespace,
            speed_node=o.speed_node,
            commanded_node=o.commanded_node,
            run_mode_node=o.run_mode_node,
            macro_node=o.macro_node,
            timeout_s=o.timeout_s,
            username=o.username,
            password=o.password(),
            security=None if o.security is None else o.security.settings(),
            clock=now,
        )
    assert cnc.modbus is not None
    m = cnc.modbus
    return ModbusCnc(
        m.host,
        m.port,
        device_id=m.device_id,
        speed_register=m.speed_register,
        commanded_register=m.commanded_register,
        run_mode_register=m.run_mode_register,
        macro_base_register=m.macro_base_register,
        timeout_s=m.timeout_s,
        register_map=m.register_map(),
        workarounds=m.workarounds,
        clock=now,
    )


def load_located_bank(config: GatewayConfig, index: int) -> ModelBank:
    """:func:`load_bank` for ``config.machines[index]``; a refusal (no such store, no models,
    a bad signature, a regime naming a missing model) names the file and the line of that
    machine's ``models.store`` (an axis's refusal: the line of that axis's key)."""
    loc = ("machines", index, "models", "store")
    store = config.machines[index].models.store
    if store.exists() and not store.is_dir():
        raise config.error_at(loc, f"{store} is a file; the model store folder was expected")
    try:
        return load_bank(config.machines[index])
    except KeyPathError as exc:
        raise config.error_at(("machines", index, *exc.key), str(exc)) from None
    except (ValueError, OSError) as exc:
        raise config.error_at(loc, str(exc)) from None


def load_bank(machine: MachineSection) -> ModelBank:
    """The machine's models, checked against its sensors, its regime rules and its axes
    (and their signatures: ``models.signing``, ``models.signing_key_file``)."""
    from models import signing

    signing.configure(machine.models.store, machine.models.signing_key_file, machine.models.signing)
    bank = ModelBank.from_store(
        machine.models.store,
        ambient_sensor=ambient_sensor_of(machine.sensor_names),
        several_targets=machine.compensation.axes is not None,
    )
    bank.check_sensors(machine.sensor_names)
    limits = machine.models
    refused = bank.refuse_sensitive(limits.sensor_accuracy_C, limits.max_bias_error_um)
    for refused_id, reason in refused.items():
        log.warning("machine %s: model %s refused: %s", machine.id, refused_id, reason)
    named = named_models(machine)
    for (label, _), model_id in named.items():
        if model_id in refused:
            raise ValueError(
                f"machine {machine.id}: {label} names model '{model_id}', which is "
                f"refused: {refused[model_id]}; refit it (fit --method ridge or pls) or raise "
                "the limit knowingly"
            )
    if not bank.models:
        raise ValueError(f"machine {machine.id}: every model in {machine.models.store} is refused")
    Promotions(machine).load(bank)  # the promoted set in force, checked like the rest
    for (label, _), model_id in named.items():
        if model_id is not None and model_id not in bank:
            raise ValueError(
                f"machine {machine.id}: {label} names model '{model_id}', "
                f"which is not in {machine.models.store} (have: {sorted(bank.models)})"
            )
    axis_targets(machine, bank)
    return bank


def named_models(machine: MachineSection) -> dict[tuple[str, str], str | None]:
    """The model ids the regime rules name, by (what names it, axis): ``regime 'x'`` for
    the single-axis form, ``axis X regime 'x'`` / ``axis X fallback`` for ``axes``."""
    if machine.compensation.axes is None:
        rules = machine.models.regimes
        single = {**rules.models, "fallback": rules.fallback_model}
        return {(f"regime '{regime}'", SINGLE_AXIS): i for regime, i in single.items()}
    named: dict[tuple[str, str], str | None] = {}
    for name, axis in machine.compensation.axes.items():
        for regime, model_id in axis.models.items():
            named[(f"axis {name} regime '{regime}'", name)] = model_id
        named[(f"axis {name} fallback", name)] = axis.fallback_model
    return named


class Gateway:
    def __init__(
        self,
        config: GatewayConfig,
        clock: Clock | None = None,
        sinks: Sequence[Sink] = (),
    ) -> None:
        self.config = config
        # In the plant machine time starts at Unix time and runs on the monotonic clock
        # (the loops schedule on it); each cycle's record also carries the wall time of
        # its start (NTP and steps followed), which every output stamps it with.
        self.clock = clock or WallClock(origin_s=time.time())
        self.outputs = Outputs(config, health=self.health)
        # The heartbeat last: it carries the counts of this cycle's sink failures too.
        sinks = [self.outputs.log_points, *sinks]
        self._proposals_shown: dict[str, tuple[int, int]] = {}  # machine → what SCADA shows
        self.scada = self._build_scada()
        if self.scada is not None:
            sinks = [*sinks, self._publish_to_scada]
        self.web: WebConsole | None = None  # built once the loops exist (it reads them)
        if config.web is not None:
            sinks = [*sinks, self._to_web]
        sinks = [*sinks, self.outputs.beat]
        hubs = shared_hubs(config.machines)
        self.loops = [
            MachineLoop(
                machine,
                self.clock,
                build_buses(machine, hubs),
                build_cnc(machine, self.clock),
                load_located_bank(config, index),
                state_dir=Path(config.state_dir),
                sinks=sinks,
            )
            for index, machine in enumerate(config.machines)
        ]
        # One timer for every loop, and each loop's polls at its own phase of the cycle.
        self.scheduler = CycleScheduler(self.clock)
        self.monitors = attach_monitors(self.loops, Path(config.state_dir))
        self.supervisors = {
            loop.config.id: Supervised(
                f"machine {loop.config.id} loop",
                functools.partial(
                    loop.run,
                    scheduler=self.scheduler,
                    phase_s=self.scheduler.phase_s(loop.config.cycle_s),
                ),
                progress=_cycles_of(loop),
            )
            for loop in self.loops
        }
        self.sparkplug = self._build_sparkplug()  # after the supervisors: it reads health
        if config.web is not None:
            self.web = build_web(config, self)

    def _to_web(self, record: CycleRecord) -> None:
        if self.web is not None:
            self.web.record(record)

    def health(self, machine_id: str) -> Health:
        """Every health counter of one machine, plus the gateway-wide forwarder's: what the
        SCADA server, the heartbeat, the console and the Sparkplug node all read."""
        return machine_health(
            self._loop_of(machine_id), self.supervisors[machine_id], self.outputs.forwarder
        )

    def gateway_health(self) -> dict[str, int]:
        """The process's own counters, which belong to no one machine (the Sparkplug
        node's ``Health/…`` metrics of NBIRTH and NDATA)."""
        return gateway_counters(self.outputs.forwarder)

    def _build_scada(self) -> ScadaServer | None:
        section = self.config.scada
        if section is None:
            return None
        users = tuple(ScadaUser(u.username, u.password() or "", u.role) for u in section.users)
        settings = ScadaSettings(
            port=section.port,
            pki_dir=section.pki_dir,
            users=users,
            host=section.host,
            allow_anonymous=section.allow_anonymous,
            rejected_keep=section.rejected_keep,
            login_throttle=login_limits(section),
        )
        machines = {m.id: m.sensor_names for m in self.config.machines}
        return ScadaServer(
            settings,
            machines,
            self._set_enabled,
            on_promote=self.promote,
            on_rollback=self.rollback,
        )

    def _build_sparkplug(self) -> EdgeNode | None:
        """The Sparkplug B edge node (config ``sparkplug``), its sink before the heartbeat;
        its commands call the same functions as the SCADA methods."""
        if self.config.sparkplug is None:
            return None
        from gateway.sparkplug.build import build_node
        from gateway.sparkplug.commands import Actions

        by = "Sparkplug host"
        actions = Actions(
            set_enabled=lambda machine, on: self._set_enabled(machine, on, by=by),
            promote=lambda machine, proposal: self.promote(machine, proposal, by=by),
            rollback=lambda machine: self.rollback(machine, by=by),
            rebirth=lambda: node.rebirth(),
        )
        node = build_node(self.config, self.health, actions, self.gateway_health)
        for loop in self.loops:
            loop.sinks.insert(max(len(loop.sinks) - 1, 0), node.sink)
            self.supervisors[loop.config.id].on_failure = functools.partial(
                node.machine_stopped, loop.config.id
            )
        return node

    def _loop_of(self, machine_id: str) -> MachineLoop:
        return next(loop for loop in self.loops if loop.config.id == machine_id)

    def _set_enabled(self, machine_id: str, enabled: bool, by: str = "SCADA") -> None:
        """An authorised SCADA user (or a Sparkplug host, ``by``) switched compensation on
        or off."""
        loop = self._loop_of(machine_id)
        if loop.compensation_enabled != enabled:
            log.warning(
                "%s: compensation %s from %s", machine_id, "enabled" if enabled else "disabled", by
            )
        loop.compensation_enabled = enabled

    def promote(self, machine_id: str, proposal_id: str, by: str = "SCADA operator") -> str:
        """Promote a proposal for a machine (the SCADA method): checked here against the
        machine's bank first, then a new version that the loop takes in between cycles.

        KeyError: no such proposal; ValueError: the machine would refuse it, or it is
        not open.
        """
        loop = self._loop_of(machine_id)
        proposal = loop.promotions.store.get(proposal_id)
        loop.promotions.check(proposal, loop.bank)
        version = loop.promotions.store.versions.promote(proposal_id, by=by)
        return f"{version.describe()}; machine {machine_id} takes it within a cycle"

    def rollback(self, machine_id: str, by: str = "SCADA operator") -> str:
        """Restore the promoted set in force before the current version (the SCADA method)."""
        loop = self._loop_of(machine_id)
        version = loop.promotions.store.versions.rollback(by=by)
        return f"{version.describe()}; machine {machine_id} takes it within a cycle"

    def _publish_to_scada(self, record: CycleRecord) -> None:
        assert self.scada is not None
        health = self.health(record.machine)
        self.scada.publish_soon(record, scalar_counters(health))
        promotions = self._loop_of(record.machine).promotions
        shown = self._proposals_shown.get(record.machine)
        if shown != (promotions.proposals_revision, promotions.version):
            self._proposals_shown[record.machine] = (
                promotions.proposals_revision,
                promotions.version,
            )
            self.scada.show_proposals_soon(record.machine, proposals_view(promotions))

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Run every machine until ``stop``; on the way out save state and close links."""
        stop = stop or asyncio.Event()
        self.outputs.start()
        sparkplug_stop = asyncio.Event()
        sparkplug_task = None
        if self.sparkplug is not None:
            sparkplug_task = asyncio.create_task(self.sparkplug.run(sparkplug_stop))
        if self.scada is not None:
            await self.scada.start()
            log.info("SCADA server at %s", self.scada.endpoint)
        if self.web is not None:
            await self.web.start()
        tasks = [
            asyncio.create_task(supervisor.supervise(stop), name=supervisor.name)
            for supervisor in self.supervisors.values()
        ]
        try:
            with frozen_startup_heap():  # what is built by now lives until the stop
                await asyncio.gather(*tasks)
        finally:
            log.debug("stopping: machine loops")
            for task in tasks:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            log.debug("stopping: saving state, closing links")
            for loop in self.loops:
                try:
                    await loop.close()
                except Exception:  # one machine's failure to close must not keep the others open
                    log.exception("%s: closing the loop failed", loop.config.id)
            await self._stop_services(sparkplug_task, sparkplug_stop)

    async def _stop_services(
        self, sparkplug_task: asyncio.Task[None] | None, sparkplug_stop: asyncio.Event
    ) -> None:
        """After the loops: the Sparkplug node (its deaths), monitors, console, SCADA, logs."""
        if sparkplug_task is not None:
            log.debug("stopping: Sparkplug edge node (DDEATH, NDEATH)")
            sparkplug_stop.set()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(sparkplug_task, 3.0)
            self.sparkplug.buffer.close()  # type: ignore[union-attr]
        for monitor in self.monitors.values():
            monitor.close()
        if self.web is not None:
            log.debug("stopping: web console")
            await self.web.stop()
        if self.scada is not None:
            log.debug("stopping: SCADA server")
            await self.scada.stop()
        log.debug("stopping: logging outputs")
        await self.outputs.stop()
        log.debug("stopped")


def attach_monitors(loops: Sequence[MachineLoop], state_dir: Path) -> dict[str, MonitorSink]:
    """The residual monitor of every machine that has one on, as a sink before the heartbeat."""
    from gateway import __version__

    monitors = {}
    for loop in loops:
        monitor = build_monitor(loop.config, state_dir / "monitor", __version__)
        if monitor is not None:
            loop.sinks.insert(max(len(loop.sinks) - 1, 0), monitor)
            monitors[loop.config.id] = monitor
    return monitors


def _cycles_of(loop: MachineLoop) -> Callable[[], int]:
    return lambda: loop.cycles


async def check_connections(config: GatewayConfig) -> list[str]:
    """Try every machine's CNC and transmitters once; the problems found, in words."""
    problems = []
    hubs = shared_hubs(config.machines)
    for machine in config.machines:
        cnc = build_cnc(machine)
        try:
            await cnc.read_speed()
        except CncError as exc:
            problems.append(f"machine {machine.id}: CNC unreachable: {exc}")
        finally:
            await cnc.close()
        for bus in build_buses(machine, hubs):
            try:
                results = await bus.read_all(0.0)
                # status None: no answer at all (a sensor fault still means the device answered)
                failed = sorted({r.error for r in results.values() if r.error and r.status is None})
                problems.extend(f"machine {machine.id}: {error}" for error in failed)
            finally:
                await bus.close()
    return problems


def shared_hubs(machines: Sequence[MachineSection]) -> dict[str, BusHub]:
    """One hub per serial port of the configuration (checked by
    :func:`gateway.config.check_shared_lines`)."""
    hubs = {}
    for port, buses in rtu_buses(machines).items():
        rtus = [bus.rtu for _, bus in buses if bus.rtu is not None]
        line = rtus[0]
        if any((r.baudrate, r.parity) != (line.baudrate, line.parity) for r in rtus):
            raise ValueError(f"port {port}: buses disagree on baud rate or parity")
        link = ModbusConnection(
            serial_port=port,
            baudrate=line.baudrate,
            parity=line.parity,
            timeout_s=max(bus.timeout_s for _, bus in buses),
            name=", ".join(dict.fromkeys(bus.name for _, bus in buses)),
        )
        silence_s = max(rtu_silence_s(line.baudrate), *(r.min_silence_s for r in rtus))
        hubs[port] = BusHub(link, silence_s=silence_s)
    return hubs
