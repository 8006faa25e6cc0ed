"""The live residual monitor: from the cycles the gateway logs to a proposal.

A sink of the machine loop (:class:`MonitorSink`), so it sees every cycle record
the loop logs, after the cycle has done its work. Per cycle it

1. appends the cycle to its history (time, speed, the good temperature readings,
   and at a probe cycle the measured error: probe + compensation applied then,
   contracts §7), one cycle per 15 s and every probe cycle, capped at
   ``history_days`` (the oldest quarter dropped when full);
2. at a new probe, computes the model's residual (probe + applied − predicted,
   both of the cycle before, as the runtime's online correction does) and runs
   it through a shadow online filter with the machine's correction parameters:
   its innovation, standardised, goes to the sequential tests of
   :mod:`models.online.residual_monitor`, per regime;
3. on an alarm, saves the history and starts the residual analysis of
   :mod:`models.analysis.history` in a separate process (never in the cycle:
   the sink only submits the job and, at later cycles, looks whether it is
   done);
4. when the analysis names an effect, hands the proposal (effect, parameters,
   held-out RMSE before/after on the logged probes, the augmented model) to
   the ``publish`` callable and logs it. Nothing is promoted here: an operator
   promotes a proposal.

One analysis runs at a time; alarms while one runs are logged and counted but
start nothing, and after an analysis the tests start from fresh evidence, as
they do when a model never seen before comes into use (a promotion). An effect
already proposed is not proposed again (the analysis refits the declared model
from scratch, so after a promotion it would name the same effect).

For a machine with several axes it watches the first axis only: it reads the record's
own per-axis fields (``model_id``, ``predicted_um``, ``applied_um``), which repeat the
first axis's (:attr:`gateway.live.record.CycleRecord.axes`), the axis the probe
measures; the other axes are never mixed into its residuals.
"""

from __future__ import annotations

import logging
import math
import tempfile
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from models.analysis.history import GRID_STEP_S, History, analyse_history
from models.online.correction import CorrectionParams, OnlineCorrection
from models.online.residual_monitor import Alarm, MonitorParams, ProbeInnovation, ResidualMonitor

log = logging.getLogger(__name__)

SPEED_STEP_MIN_RPM = 50.0  # a smaller change of the speed reading is not a speed change
CHUNK_ROWS = 65536

Publisher = Callable[[dict[str, Any]], None]


class HistoryBuffer:
    """Growing cycle-aligned arrays, the oldest rows dropped past ``max_rows``."""

    def __init__(self, sensors: tuple[str, ...], max_rows: int) -> None:
        self.sensors = sensors
        self.max_rows = max_rows
        self.n = 0
        self._time = np.empty(CHUNK_ROWS)
        self._speed = np.empty(CHUNK_ROWS)
        self._temps = np.empty((CHUNK_ROWS, len(sensors)), dtype=np.float32)
        self._error = np.empty(CHUNK_ROWS)

    def append(
        self, time_s: float, speed_rpm: float, temps_C: list[float], error_um: float
    ) -> None:
        if self.n == self._time.size:
            self._grow()
        i = self.n
        self._time[i], self._speed[i], self._error[i] = time_s, speed_rpm, error_um
        self._temps[i] = temps_C
        self.n += 1

    def _grow(self) -> None:
        if self.n >= self.max_rows:  # drop the oldest quarter: amortised O(1) per cycle
            keep = self.n - self.max_rows // 4
            for name in ("_time", "_speed", "_temps", "_error"):
                array = getattr(self, name)
                array[:keep] = array[self.n - keep : self.n]
            self.n = keep
            return
        size = min(self._time.size * 2, self.max_rows + CHUNK_ROWS)
        for name in ("_time", "_speed", "_temps", "_error"):
            array = getattr(self, name)
            grown = np.empty((size, *array.shape[1:]), dtype=array.dtype)
            grown[: self.n] = array[: self.n]
            setattr(self, name, grown)

    def snapshot(self) -> History:
        n = self.n
        return History(
            time_s=self._time[:n].copy(),
            speed_rpm=self._speed[:n].copy(),
            sensors=self.sensors,
            temperatures_C=self._temps[:n].astype(float),
            error_um=self._error[:n].copy(),
        )


def run_analysis_job(path: str, method: str, sensors: tuple[str, ...] | None, version: str):
    """The background job (a separate process): load the saved history, analyse it."""
    return analyse_history(History.load(path), method, sensors, version)


@dataclass
class MonitorState:
    """What the monitor has done so far (for logs, SCADA, tests)."""

    probes: int = 0
    alarms: list[Alarm] = field(default_factory=list)
    analyses: int = 0
    alarms_ignored: int = 0  # alarms while an analysis was running
    results: list[dict[str, Any]] = field(default_factory=list)  # every analysis summary
    proposals: list[dict[str, Any]] = field(default_factory=list)


class MonitorSink:
    """The monitor as a loop sink; see the module docstring."""

    def __init__(
        self,
        machine: str,
        sensors: tuple[str, ...],
        params: MonitorParams,
        correction: CorrectionParams | None = None,
        *,
        method: str = "mlr",
        history_days: float = 30.0,
        cycle_s: float = 1.0,
        min_history_probes: int = 24,
        publish: Publisher | None = None,
        workdir: Path | None = None,
        in_process: bool = False,
        version: str = "unknown",
    ) -> None:
        self.machine = machine
        self.sensors = sensors
        self.params = params
        self.filter = OnlineCorrection(correction or CorrectionParams())
        self.monitor = ResidualMonitor(params)
        self.method = method
        # The analysis runs on a 15 s grid (models.analysis.history.GRID_STEP_S): a faster
        # cycle is kept once per step (and at every probe), so 30 days take ~11 MB, not 150.
        self.history_step_s = max(cycle_s, GRID_STEP_S)
        rows = history_days * 86400 / self.history_step_s * (1 + self.history_step_s / 300.0)
        self.history = HistoryBuffer(sensors, max(int(rows), 1024))
        self._kept_s: float | None = None
        self.min_history_probes = min_history_probes
        self.publish = publish
        self.workdir = workdir
        self.in_process = in_process
        self.version = version
        self.state = MonitorState()
        self._basis: tuple[float, float] | None = None  # (predicted, applied) of the last cycle
        self._speed: float | None = None
        self._step_rpm = 0.0
        self._step_s: float | None = None
        self._pending: Future | None = None
        self._pending_alarm: Alarm | None = None
        self._executor: ProcessPoolExecutor | None = None
        self._models_seen: set[str] = set()
        self._proposed_effects: set[str] = set()  # effects published: never proposed twice

    # --- per cycle ----------------------------------------------------------------------
    def __call__(self, record: Any) -> None:
        self._collect()
        self._note_model(record.model_id)
        speed = record.speed_rpm
        temps = [
            value if value is not None and record.quality.get(name) == "good" else math.nan
            for name, value in ((n, record.temperatures_C.get(n)) for n in self.sensors)
        ]
        basis, self._basis = (
            self._basis,
            (
                None
                if record.predicted_um is None or record.applied_um is None
                else (record.predicted_um, record.applied_um)
            ),
        )
        error_um = math.nan
        if record.probe_error_um is not None and basis is not None:
            error_um = record.probe_error_um + basis[1]  # the machine's error when probed
            self._probe(record, record.probe_error_um + basis[1] - basis[0])
        self._track_speed(record.time_s, speed)
        due = self._kept_s is None or record.time_s - self._kept_s >= 0.999 * self.history_step_s
        if due or math.isfinite(error_um):  # one cycle per history step, and every probe
            self._kept_s = record.time_s
            self.history.append(
                record.time_s, math.nan if speed is None else speed, temps, error_um
            )

    def _note_model(self, model_id: str | None) -> None:
        """A model never seen before (a promotion, a rollback to another) restarts the
        evidence: the residual it leaves is a new one. The history stays: it is the
        machine's measured error, whatever the model."""
        if model_id is None or model_id in self._models_seen:
            return
        if self._models_seen:
            log.info(
                "%s: residual monitor: model %s in use; the tests start afresh",
                self.machine,
                model_id,
            )
            self.monitor.reset()
            self.filter.reset()
        self._models_seen.add(model_id)

    def _track_speed(self, time_s: float, speed: float | None) -> None:
        if speed is None:
            return
        if self._speed is None:
            self._speed, self._step_s = speed, time_s
        elif abs(speed - self._speed) >= SPEED_STEP_MIN_RPM:
            self._step_rpm, self._step_s, self._speed = speed - self._speed, time_s, speed

    def _probe(self, record: Any, residual_um: float) -> None:
        outcome = self.filter.update(record.time_s, residual_um)
        if not outcome.accepted or not math.isfinite(outcome.innovation_sigma_um):
            return  # an outlier is the correction's business, not evidence of structure
        if outcome.predicted_um is None or not math.isfinite(outcome.predicted_um):
            return
        self.state.probes += 1
        probe = ProbeInnovation(
            time_s=record.time_s,
            innovation_um=outcome.residual_um - outcome.predicted_um,
            sigma_um=outcome.innovation_sigma_um,
            speed_rpm=self._speed or 0.0,
            speed_step_rpm=self._step_rpm,
            since_step_s=record.time_s - (self._step_s if self._step_s is not None else 0.0),
            regime=record.regime or "all",
        )
        alarm = self.monitor.observe(probe)
        if alarm is not None:
            self._alarm(alarm)

    def _alarm(self, alarm: Alarm) -> None:
        self.state.alarms.append(alarm)
        if self._pending is not None:
            self.state.alarms_ignored += 1
            log.info(
                "%s: residual monitor: %s (an analysis is running)", self.machine, alarm.describe()
            )
            return
        probes = int(np.isfinite(self.history._error[: self.history.n]).sum())
        if probes < self.min_history_probes:
            log.info(
                "%s: residual monitor: %s; %d probes logged, the analysis waits for %d",
                self.machine,
                alarm.describe(),
                probes,
                self.min_history_probes,
            )
            self.state.alarms_ignored += 1
            return
        log.warning(
            "%s: residual monitor: %s; residual analysis of %d logged cycles (%d probes) "
            "started in the background",
            self.machine,
            alarm.describe(),
            self.history.n,
            probes,
        )
        self._start(alarm)

    # --- the background analysis -----------------------------------------------------------
    def _start(self, alarm: Alarm) -> None:
        history = self.history.snapshot()
        self.state.analyses += 1
        self._pending_alarm = alarm
        if self.in_process:  # tests on a manual clock: the same job, inline
            future: Future = Future()
            future.set_result(analyse_history(history, self.method, None, self.version))
            self._pending = future
            self._collect()
            return
        folder = self.workdir or Path(tempfile.gettempdir())
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{self.machine}-monitor-history-{self.state.analyses}.npz"
        history.save(str(path))
        if self._executor is None:
            self._executor = ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"))
        self._pending = self._executor.submit(
            run_analysis_job, str(path), self.method, None, self.version
        )
        self._pending.add_done_callback(lambda _: path.unlink(missing_ok=True))

    def _collect(self) -> None:
        """A finished analysis becomes a proposal (or a logged 'none'); never waits."""
        future = self._pending
        if future is None or not future.done():
            return
        self._pending = None
        alarm, self._pending_alarm = self._pending_alarm, None
        self.monitor.reset()
        try:
            summary = future.result()
        except Exception:
            log.exception("%s: residual monitor: the residual analysis failed", self.machine)
            return
        summary = summary | {"alarm": alarm.as_dict() if alarm else None}
        self.state.results.append(summary)
        if summary["effect"] == "none":
            log.info(
                "%s: residual monitor: the analysis of %d probes finds no missing effect "
                "(held-out RMSE %.2f µm)",
                self.machine,
                summary["probes"],
                summary["before"]["rmse_um"],
            )
            return
        named = {e["effect"] for e in summary["effects"]}
        if named <= self._proposed_effects:
            log.info(
                "%s: residual monitor: the analysis names %s again, already proposed; "
                "not published again",
                self.machine,
                ", ".join(sorted(named)),
            )
            return
        self._proposed_effects |= named
        self.state.proposals.append(summary)
        effects = ", ".join(f"{e['effect']} {e['params']}" for e in summary["effects"])
        log.warning(
            "%s: residual monitor proposes %s: held-out RMSE on %d logged probes %.2f → %.2f µm "
            "(model %s; promote it to use it)",
            self.machine,
            effects,
            summary["probes"],
            summary["before"]["rmse_um"],
            summary["after"]["rmse_um"],
            summary["document"]["model_id"],
        )
        if self.publish is not None:
            self.publish(summary)

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the running analysis (if any) is done and collected (tests, stop)."""
        if self._pending is not None:
            self._pending.exception(timeout=timeout_s)
            self._collect()

    @property
    def analysing(self) -> bool:
        return self._pending is not None

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None


def store_publisher(store_dir: Path, machine_id: str) -> Publisher:
    """Publish a monitor proposal in the store's proposals (:mod:`models.online.proposals`)."""

    def publish(summary: dict[str, Any]) -> None:
        from models.online.proposals import ProposalStore

        first = summary["effects"][0]
        alarm = summary.get("alarm") or {}
        proposal = ProposalStore(store_dir).publish(
            machine_id=machine_id,
            effect=" + ".join(e["effect"] for e in summary["effects"]),
            params=first["params"]
            if len(summary["effects"]) == 1
            else {f"{i + 1}.{e['effect']}": e["params"] for i, e in enumerate(summary["effects"])},
            before_rmse_um=summary["before"]["rmse_um"],
            after_rmse_um=summary["after"]["rmse_um"],
            probe_rows=summary["probes"],
            document=summary["document"],
            note=(
                f"residual monitor: {alarm.get('test', '?')} alarm on regime "
                f"{alarm.get('regime', '?')}; {summary['validation']}, "
                f"{summary['rows']} logged cycles"
            ),
        )
        summary["proposal_id"] = proposal.id
        log.warning("%s: published proposal %s", machine_id, proposal.describe())

    return publish


def build_monitor(
    machine: Any, workdir: Path | None, version: str = "unknown"
) -> MonitorSink | None:
    """The monitor sink of one machine's config (``machines[].monitor``), or None when off."""
    section = machine.monitor
    if not section.enabled:
        return None
    correction = machine.online_correction.params().with_limits(
        process_um2_per_h=section.process_um2_per_h, kind="bias", reversion_tau_s=None
    )
    return MonitorSink(
        machine.id,
        tuple(machine.sensor_names),
        section.params(),
        correction,
        method=section.method,
        history_days=section.history_days,
        cycle_s=machine.cycle_s,
        min_history_probes=section.min_history_probes,
        publish=store_publisher(Path(machine.models.store), machine.id),
        workdir=workdir,
        version=version,
    )
