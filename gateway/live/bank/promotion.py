"""Promoted models, taken into a running machine's bank between cycles, without a restart.

An operator promotes a proposal (``python -m gateway models promote ID`` or the
SCADA method ``PromoteProposal``), which writes a new version of the store's
promoted set (:mod:`models.online.proposals`). Each machine loop looks at the store's
``versions/current.json`` once per cycle, one ``stat`` (inode, mtime, size);
when it changed, the loop reads the version in force and, before the next
cycle's inputs are read, swaps its promoted models (:meth:`Promotions.poll`).

A promoted model must pass the checks a model passes at start:

- it loads and runs sample by sample (:class:`gateway.live.bank.model_bank.BankedAugmented`);
- every sensor it needs is a channel of this machine (the ambient one included);
- it predicts the bank's target in the bank's unit (several axes: the target of the
  model it replaces, or one of the bank's);
- one sensor off by ``models.sensor_accuracy_C`` moves it by at most
  ``models.max_bias_error_um`` (its steady-state slope: a held bias shifts a
  lag of that sensor by the same amount, so every term of the sensor counts);
- its id is not that of one of the store's own models, and the model it
  replaces (if it names one) is in the store.

A model that fails is refused with a logged reason and counted; whatever served
in its place before keeps serving. A swap is logged and counted. The new model's
lag states are taken warm (:mod:`gateway.live.bank.lag_state`), and its prediction goes
through the same online correction, clamp and slew limit as any other, so the
compensation moves to it no faster than the slew allows.

With ``models.auto_promote: true`` the loop itself promotes a new proposal for
its machine as soon as it sees it (one ``stat`` of the proposals folder per
cycle); by default nothing is promoted without an operator.

The loop never waits for the store's lock (``versions/.lock``): the recovery at start
and an automatic promotion only *try* it (:meth:`models.online.proposals.ModelVersions.locked`);
while another process holds it (a ``models promote`` under way, or stopped) they are
tried again on each later cycle, and the cycles go on. Reading the version in force
needs no lock: its commit is the atomic rename of ``versions/current.json``. The running
loop also runs that recovery whenever it sees a new version (once the lock is free): a
writer killed between its commit and the proposal files' update leaves them behind the
version in force, and nothing else would bring them in line until the next command.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.config import MachineSection
from gateway.live.bank.model_bank import BankedAugmented, ModelBank
from models.data.dataset import AMBIENT_COLUMN, ambient_sensor_of
from models.online.proposals import (
    ActiveEntry,
    Proposal,
    ProposalStore,
    StoreBusyError,
    Version,
)

log = logging.getLogger(__name__)

#: Size of the bias used for the slope of a promoted model, °C (exact for linear models).
BIAS_STEP_C = 1.0


def check_promoted(
    document: Mapping[str, Any],
    machine: MachineSection,
    bank: ModelBank,
    replaces: str | None = None,
    store_ids: frozenset[str] | None = None,
) -> BankedAugmented:
    """The model ready for ``machine``'s bank, or ValueError saying why it is refused.

    ``store_ids``: the ids of the store's own models (default: the bank's models
    that are not promoted ones).
    """
    model_id = str(document.get("model_id", "?"))
    own = store_ids if store_ids is not None else _store_ids(bank)
    if model_id in own:
        raise ValueError(f"its id {model_id} is that of a model of the store")
    if replaces is not None and replaces not in own:
        raise ValueError(f"it replaces model {replaces}, which is not in the store")
    try:
        banked = BankedAugmented.from_document(
            dict(document), ambient_sensor_of(machine.sensor_names) or AMBIENT_COLUMN
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"it cannot run: {exc}") from None
    missing = sorted(banked.sensors - set(machine.sensor_names))
    if missing:
        raise ValueError(
            f"it needs sensor(s) {missing} that no transmitter channel of machine "
            f"{machine.id} provides (channels: {sorted(machine.sensor_names)})"
        )
    targets = bank.targets_of(replaces)
    if targets and banked.target not in targets:
        compensated = ", ".join(sorted(map(str, targets)))
        raise ValueError(f"it predicts {banked.target}, the machine compensates {compensated}")
    limits = machine.models
    slopes = bias_slopes_um_per_C(banked)
    if slopes:
        worst = max(slopes, key=lambda s: abs(slopes[s]))
        error_um = limits.sensor_accuracy_C * abs(slopes[worst])
        if error_um > limits.max_bias_error_um:
            raise ValueError(
                f"a bias of ±{limits.sensor_accuracy_C:g} °C on {worst} moves it by "
                f"{error_um:.1f} µm (limit models.max_bias_error_um "
                f"{limits.max_bias_error_um:g} µm)"
            )
    return banked


def bias_slopes_um_per_C(banked: BankedAugmented) -> dict[str, float]:
    """µm per °C of a bias held on each sensor the model reads, once its lags have settled.

    A fresh stream's first sample sets every lag to its input, which is where a
    held bias takes the lags; so the slope is a central difference of first
    samples around the cold reference (exact when the model is linear in the rises).
    """
    sensors = sorted(banked.sensors)
    slopes = {}
    for sensor in sensors:
        values = []
        for sign in (1.0, -1.0):
            rises = {s: 0.0 for s in sensors}
            rises[sensor] = sign * BIAS_STEP_C
            ambient = rises.get(banked.ambient_sensor) if banked.ambient_sensor else None
            values.append(banked.stream().step(0.0, rises, 0.0, ambient))
        if all(v is not None and math.isfinite(v) for v in values):
            slopes[sensor] = (float(values[0]) - float(values[1])) / (2 * BIAS_STEP_C)  # type: ignore[arg-type]
    return slopes


def _store_ids(bank: ModelBank) -> frozenset[str]:
    promoted = set(bank.promoted.values())
    return frozenset(m for m in bank.models if m not in promoted)


@dataclass
class SwapOutcome:
    """What one version change did to a machine's bank."""

    version: int
    swapped: list[str] = field(default_factory=list)  # model ids now promoted
    refused: dict[str, str] = field(default_factory=dict)  # proposal id → why
    changed: bool = False  # the promoted set of the bank changed


class Promotions:
    """One machine's view of its store's proposals and promoted set (see the module doc)."""

    def __init__(self, machine: MachineSection, *, running: bool = False) -> None:
        """``running``: these are the running loop's promotions, whose refusals are written
        into the store (``_record_refusal``); a check (``check-config``, ``models promote
        --config``) only looks and writes nothing."""
        self.machine = machine
        self.running = running
        self.store = ProposalStore(machine.models.store)
        self.auto_promote = machine.models.auto_promote
        self.version = 0  # the version whose set the bank holds (as far as it passed)
        self.swaps = 0
        self.refused = 0
        self.proposals: list[Proposal] = []  # this machine's, refreshed when the folder changes
        self.proposals_revision = 0  # bumped whenever ``proposals`` is refreshed
        self._version_key: tuple[int, int, int] | None = None
        self._proposals_key: tuple[int, int] | None = None
        self._entries: dict[str | None, ActiveEntry] = {}  # what the bank holds, by place
        self._proposals_path = os.fspath(self.store.folder)  # stat-ed every cycle
        self._recover_pending = False  # a recovery found the lock held: tried next cycle
        self._recover_quiet = False  # ... and says so only if it is the one at start
        self._auto_pending = False  # an automatic promotion found the lock held
        self._busy_logged = False  # the held lock is logged once per episode

    # -- at start ---------------------------------------------------------------------------
    def load(self, bank: ModelBank) -> SwapOutcome:
        """Put the version in force into a freshly loaded bank (start-up, check-config).

        The running loop first cleans up after a change killed mid-write
        (:meth:`models.online.proposals.ModelVersions.recover`); a check writes nothing."""
        if self.running:
            self._recover()
        self._version_key = self.store.versions.pointer_key()
        outcome = self._apply(self.store.versions.current(), bank, at_start=True)
        self._refresh_proposals()
        return outcome

    def _recover(self, quiet: bool = False) -> None:
        """Clean up after a writer killed mid-change; tried again next cycle while another
        process holds the lock (``quiet``: without saying so, as after every new version,
        whose writer is still bringing the proposal files in line)."""
        self._recover_pending = False
        try:
            for line in self.store.versions.recover():
                log.warning("%s: model store recovered: %s", self.machine.id, line)
        except StoreBusyError as exc:  # tried again next cycle: never wait on the loop
            self._recover_pending, self._recover_quiet = True, quiet
            if not quiet:
                self._lock_busy("the recovery of the model store", exc)
            return
        except OSError as exc:  # a read-only store: nothing can have been left half-written
            log.warning("%s: model store not checked for leftovers: %s", self.machine.id, exc)
        self._busy_logged = False

    def _lock_busy(self, what: str, exc: StoreBusyError) -> None:
        """Log once per episode that ``what`` waits for a lock another process holds."""
        if not self._busy_logged:
            self._busy_logged = True
            log.warning("%s: %s is tried again every cycle: %s", self.machine.id, what, exc)

    # -- every cycle ------------------------------------------------------------------------
    def poll(self, bank: ModelBank) -> SwapOutcome | None:
        """Between cycles: new proposals (auto-promoted if configured), then a new version."""
        if self._recover_pending:
            self._recover(quiet=self._recover_quiet)
        if self._proposals_changed():
            self._refresh_proposals()
            self._auto_pending = self.auto_promote
        if self._auto_pending:
            self._auto_promote()
        key = self.store.versions.pointer_key()
        if key == self._version_key:
            return None
        self._version_key = key
        try:
            version = self.store.versions.current()
        except (KeyError, ValueError) as exc:
            self.refused += 1
            log.error(
                "%s: the promoted set cannot be read (%s); the models in use stay",
                self.machine.id,
                exc,
            )
            return None
        outcome = self._apply(version, bank)
        if self.running:
            # A writer killed after its commit leaves the proposal files behind this version.
            self._recover(quiet=True)
        self._refresh_proposals()  # promotion changes statuses
        return outcome

    def check(self, proposal: Proposal, bank: ModelBank) -> None:
        """Raise ValueError if this machine would refuse the proposal's model."""
        if proposal.machine_id != self.machine.id:
            raise ValueError(
                f"proposal {proposal.id} is for machine {proposal.machine_id}, "
                f"not {self.machine.id}"
            )
        check_promoted(proposal.document, self.machine, bank, proposal.replaces)

    # -- internals --------------------------------------------------------------------------
    def _apply(self, version: Version, bank: ModelBank, at_start: bool = False) -> SwapOutcome:
        outcome = SwapOutcome(version.number)
        own = _store_ids(bank)
        entries: dict[str | None, ActiveEntry] = {}
        models: dict[str | None, BankedAugmented] = {}
        for entry in version.for_machine(self.machine.id):
            try:
                models[entry.replaces] = check_promoted(
                    entry.document, self.machine, bank, entry.replaces, own
                )
                entries[entry.replaces] = entry
            except ValueError as exc:
                outcome.refused[entry.proposal_id] = str(exc)
                self.refused += 1
                log.error(
                    "%s: model %s of proposal %s (version %d) refused: %s; what served in its "
                    "place stays (refused promotions: %d)",
                    self.machine.id,
                    entry.model_id,
                    entry.proposal_id,
                    version.number,
                    exc,
                    self.refused,
                )
                old = self._entries.get(entry.replaces)
                if old is not None:  # keep the one that served there
                    entries[entry.replaces] = old
                    models[entry.replaces] = _banked(bank, old)
                if self.running:
                    self._record_refusal(entry, str(exc), old)
        before = {place: e.sha256 for place, e in self._entries.items()}
        after = {place: e.sha256 for place, e in entries.items()}
        self.version = version.number
        if before != after:
            bank.set_promoted((model, place) for place, model in models.items())
            self._entries = entries
            outcome.changed = True
            outcome.swapped = [m.model_id for m in models.values()]
            self.swaps += 0 if at_start else 1
            (log.info if at_start else log.warning)(
                "%s: models version %d in force%s (%s): promoted model(s) %s (model swaps: %d)",
                self.machine.id,
                version.number,
                " at start" if at_start else "",
                version.action,
                ", ".join(
                    f"{m.model_id} in place of {place or 'every regime'}"
                    for place, m in models.items()
                )
                or "none, the store's own models serve",
                self.swaps,
            )
        return outcome

    def _record_refusal(self, entry: ActiveEntry, reason: str, kept: ActiveEntry | None) -> None:
        """Say in the store what this machine runs: the refused proposal ``refused``, the
        one kept in its place ``promoted``. A store it cannot write only costs the note."""
        try:
            self.store.versions.refused_by_machine(
                entry.proposal_id,
                self.machine.id,
                reason,
                kept.proposal_id if kept is not None else None,
            )
        except (KeyError, OSError, ValueError) as exc:
            log.error(
                "%s: the refusal of proposal %s cannot be recorded in the store: %s",
                self.machine.id,
                entry.proposal_id,
                exc,
            )

    def _proposals_changed(self) -> bool:
        try:
            status = os.stat(self._proposals_path)
        except FileNotFoundError:
            key = None
        else:
            key = (status.st_ino, status.st_mtime_ns)
        if key == self._proposals_key:
            return False
        self._proposals_key = key
        return True

    def _refresh_proposals(self) -> None:
        try:
            self.proposals = self.store.list(machine_id=self.machine.id)
        except ValueError as exc:
            log.error("%s: the proposals cannot be read: %s", self.machine.id, exc)
            return
        self.proposals_revision += 1

    def _auto_promote(self) -> None:
        self._auto_pending = False
        newest = next((p for p in reversed(self.proposals) if p.open), None)
        if newest is None:
            return
        try:
            self.store.versions.promote(newest.id, by="auto_promote")
        except StoreBusyError as exc:
            self._auto_pending = True
            self._lock_busy(f"the automatic promotion of {newest.id}", exc)
            return
        except (KeyError, ValueError) as exc:
            log.error("%s: auto-promotion of %s failed: %s", self.machine.id, newest.id, exc)
            return
        log.warning(
            "%s: %s promoted automatically (models.auto_promote is true)",
            self.machine.id,
            newest.describe(),
        )
        self._busy_logged = False
        self._refresh_proposals()


def _banked(bank: ModelBank, entry: ActiveEntry) -> BankedAugmented:
    banked = bank.models[entry.model_id]
    assert isinstance(banked, BankedAugmented)
    return banked


def proposals_view(promotions: Promotions) -> dict[str, Any]:
    """What SCADA shows of a machine's proposals (``ScadaServer.show_proposals``)."""
    proposals = promotions.proposals
    return {
        "open": [p.summary() for p in proposals if p.open],
        "newest": proposals[-1].summary() if proposals else None,
        "models_version": promotions.version,
    }
