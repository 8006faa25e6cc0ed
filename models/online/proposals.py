"""Proposed model changes and the versioned set of promoted models, under a model store.

The residual monitor finds an effect the running model lacks, fits the
augmented model on the logged history and *publishes* it here as a
:class:`Proposal`: the effect and its parameters, the held-out RMSE before and
after on the logged data, how many probe rows it rests on, and the augmented
model document itself (the document ``analyze --store`` writes,
:mod:`models.analysis.augmented`). Nothing runs from a proposal until it is *promoted*.

Layout (explicit JSON only, every file written to a temporary file and renamed,
so a reader never sees half a file)::

    <store>/proposals/<id>.json     one proposal, its status and status history
    <store>/versions/<n>.json       version n of the promoted set (never rewritten)
    <store>/versions/current.json   which version is in force

Every change of the promoted set writes a new version: a promotion adds (or
replaces) one entry, a rollback writes a version whose set is the one in force
before the version it leaves, and which rolls back further, to that version's
own predecessor, when rolled back again. Nothing in force is deleted, so the
version files are the audit trail. Version 0 is implicit: the store's own
models, none promoted.

One commit point. A change writes ``versions/<n>.json`` (n = the version in
force + 1, fsynced), then replaces ``versions/current.json`` (fsynced): that
rename is the change. A process killed before it leaves a version file that was
never in force: it is not history, and the next writer (or :meth:`ModelVersions.recover`,
run at the start of ``run`` and of every ``models`` command) removes it with any
temporary file a killed writer left. A proposal's status is *derived* from the
versions in force (:meth:`ModelVersions.derive`): promoted while it is in the
version in force, superseded or rejected (rolled back) from the version that
took it out; only what no version says (published, rejected while open, a
machine's refusal of the version in force) comes from its own file. The status
written in the file, and its history, follow after the commit and are brought
in line by the next recovery, so a reader never sees a status that contradicts
the version in force, wherever a writer was killed.

Every file read is checked for its ``format`` and a supported ``format_version``,
naming the file; so are the augmented models inside proposals and versions
(:func:`models.analysis.augmented.check`), and their signatures (:mod:`models.signing`;
not in a store declared unsigned).

A promoted entry names the model it takes the place of (``replaces``, a model
id of the store, or None: every regime). Promoting a proposal for the same
machine and the same ``replaces`` supersedes the entry there.

The running gateway watches ``versions/current.json`` (a ``stat`` per cycle,
:meth:`ModelVersions.pointer_key`) and swaps the set in between cycles after its
own checks (:mod:`gateway.live.bank.promotion`). Writers take ``versions/.lock`` (an
advisory ``flock``), so the command line and the gateway's SCADA method can
change the set at the same time without losing a version. The lock is only ever
tried, never waited on in the kernel (:meth:`ModelVersions.locked`): a holder that
is stopped stops no one else; readers need no lock, the rename of
``versions/current.json`` being the commit; publishing a proposal takes none.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import re
import tempfile
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from models import signing
from models.analysis import augmented
from models.json_files import fsync_folder, remove_temporaries, write_json_atomic
from models.store import StoreError

PROPOSALS_FOLDER = "proposals"
VERSIONS_FOLDER = "versions"
CURRENT_FILE = "current.json"
LOCK_FILE = ".lock"
#: how often a busy ``versions/.lock`` is tried again while a writer waits for it, s
LOCK_RETRY_S = 0.05
#: a publication tries this many free ids (each taken meanwhile, or its file removed)
PUBLISH_TRIES = 100
#: temporary files of writers (models.json_files; ``tmp*.tmp``: before they were dot-named)
TEMPORARIES = (".*.tmp", "tmp*.tmp")

PROPOSAL_FORMAT = "thermal-gateway-model-proposal"
VERSION_FORMAT = "thermal-gateway-model-version"
FORMAT_VERSION = 1

PROPOSED = "proposed"
PROMOTED = "promoted"
REJECTED = "rejected"
SUPERSEDED = "superseded"
#: Promoted, but the machine would not run it (its checks, gateway/live/bank/promotion.py).
REFUSED = "refused"
STATUSES = (PROPOSED, PROMOTED, REJECTED, SUPERSEDED, REFUSED)
#: Statuses of a proposal an operator may still promote.
OPEN = (PROPOSED,)

_ID_PATTERN = re.compile(r"^P(\d{4,})$")


class ProposalError(StoreError):
    """A proposal or version file that cannot be used, or a change that is not allowed."""


class StoreBusyError(ProposalError):
    """Another process holds ``versions/.lock`` (a change under way, or a stopped writer)."""

    def __init__(self, path: Path, holder: str, waited_s: float) -> None:
        self.path = path
        who = f"process {holder}" if holder.isdigit() else "another process"
        waited = f" for {waited_s:g} s" if waited_s > 0 else ""
        super().__init__(
            f"{path} is held by {who}{waited}: another change of the promoted set is under way "
            "(or its writer is stopped); nothing was changed, try again when it is done"
        )


# -- records --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Proposal:
    """One proposed augmented model for one machine (units in the names).

    ``document`` is the augmented-model document (:mod:`models.analysis.augmented`),
    checksummed; ``history`` lists every status change as
    ``{"status", "time_s", "note"}``, the first being the publication.
    """

    id: str
    machine_id: str
    created_s: float
    effect: str
    params: dict[str, Any]
    before_rmse_um: float
    after_rmse_um: float
    probe_rows: int
    document: dict[str, Any]
    status: str = PROPOSED
    replaces: str | None = None
    note: str = ""
    history: tuple[dict[str, Any], ...] = field(default_factory=tuple)

    @property
    def model_id(self) -> str:
        return str(self.document["model_id"])

    @property
    def open(self) -> bool:
        return self.status in OPEN

    def summary(self) -> dict[str, Any]:
        """Everything but the model document: what a list or a SCADA node shows."""
        return {
            "id": self.id,
            "machine_id": self.machine_id,
            "created_s": self.created_s,
            "effect": self.effect,
            "params": dict(self.params),
            "before_rmse_um": self.before_rmse_um,
            "after_rmse_um": self.after_rmse_um,
            "probe_rows": self.probe_rows,
            "model_id": self.model_id,
            "replaces": self.replaces,
            "status": self.status,
            "note": self.note,
        }

    def describe(self) -> str:
        """One line for logs and the SCADA newest-proposal node."""
        params = ", ".join(
            f"{k} {v:g}" if _number(v) else f"{k} {v}" for k, v in self.params.items()
        )
        return (
            f"{self.id} ({self.machine_id}): {self.effect}"
            f"{f' ({params})' if params else ''}, held-out RMSE {self.before_rmse_um:.2f} → "
            f"{self.after_rmse_um:.2f} µm on {self.probe_rows} probe rows, {self.status}"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "format": PROPOSAL_FORMAT,
            "format_version": FORMAT_VERSION,
            **self.summary(),
            "history": [dict(h) for h in self.history],
            "document": self.document,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], where: str) -> Proposal:
        if data.get("format") != PROPOSAL_FORMAT:
            raise ProposalError(f"{where}: not a model proposal (format {data.get('format')!r})")
        check_format_version(data, where)
        try:
            proposal = cls(
                id=str(data["id"]),
                machine_id=str(data["machine_id"]),
                created_s=float(data["created_s"]),
                effect=str(data["effect"]),
                params=dict(data["params"]),
                before_rmse_um=float(data["before_rmse_um"]),
                after_rmse_um=float(data["after_rmse_um"]),
                probe_rows=int(data["probe_rows"]),
                document=dict(data["document"]),
                status=str(data["status"]),
                replaces=None if data.get("replaces") is None else str(data["replaces"]),
                note=str(data.get("note", "")),
                history=tuple(dict(h) for h in data.get("history", [])),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ProposalError(f"{where}: field {exc} is missing or malformed") from None
        if proposal.status not in STATUSES:
            raise ProposalError(
                f"{where}: status {proposal.status!r} is not one of {', '.join(STATUSES)}"
            )
        return proposal


@dataclass(frozen=True)
class ActiveEntry:
    """One promoted model in a version: which proposal, which machine, in place of what."""

    proposal_id: str
    machine_id: str
    replaces: str | None
    document: dict[str, Any]

    @property
    def model_id(self) -> str:
        return str(self.document["model_id"])

    @property
    def sha256(self) -> str:
        return str(self.document.get("sha256", ""))

    @property
    def target(self) -> str:
        """The error column the model predicts (one axis of a machine that compensates
        several): a promotion supersedes only an entry of the same target."""
        return target_of(self.document)

    def to_json(self) -> dict[str, Any]:
        return {
            "proposal_id": self.proposal_id,
            "machine_id": self.machine_id,
            "model_id": self.model_id,
            "replaces": self.replaces,
            "document": self.document,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], where: str) -> ActiveEntry:
        try:
            return cls(
                proposal_id=str(data["proposal_id"]),
                machine_id=str(data["machine_id"]),
                replaces=None if data.get("replaces") is None else str(data["replaces"]),
                document=dict(data["document"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ProposalError(
                f"{where}: active entry field {exc} is missing or malformed"
            ) from None


@dataclass(frozen=True)
class Version:
    """Version ``number`` of the promoted set; ``previous`` is what a rollback restores."""

    number: int
    previous: int | None
    action: str  # "start", "promote" or "rollback"
    created_s: float
    by: str
    active: tuple[ActiveEntry, ...]
    proposal_id: str | None = None  # promote: the proposal promoted
    restores: int | None = None  # rollback: the version whose set this one restores
    target: str | None = None  # rollback of one target's models only: that target

    def proposal_ids(self) -> set[str]:
        return {e.proposal_id for e in self.active}

    def for_machine(self, machine_id: str) -> list[ActiveEntry]:
        return [e for e in self.active if e.machine_id == machine_id]

    def describe(self) -> str:
        models = ", ".join(f"{e.model_id} ({e.proposal_id})" for e in self.active) or "none"
        what = {
            "start": "the store's own models",
            "promote": f"promoted {self.proposal_id}",
            "rollback": f"rolled back to the set of version {self.restores}"
            + (f" for target {self.target}" if self.target is not None else ""),
            "sign": f"the set of version {self.number - 1}, its models signed",
        }.get(self.action, self.action)
        return f"version {self.number}: {what}; promoted models: {models}"

    def to_json(self) -> dict[str, Any]:
        return {
            "format": VERSION_FORMAT,
            "format_version": FORMAT_VERSION,
            "version": self.number,
            "previous": self.previous,
            "action": self.action,
            "created_s": self.created_s,
            "by": self.by,
            "proposal_id": self.proposal_id,
            "restores": self.restores,
            **({"target": self.target} if self.target is not None else {}),
            "active": [e.to_json() for e in self.active],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], where: str) -> Version:
        if data.get("format") != VERSION_FORMAT:
            raise ProposalError(f"{where}: not a model version (format {data.get('format')!r})")
        check_format_version(data, where)
        try:
            return cls(
                number=int(data["version"]),
                previous=None if data.get("previous") is None else int(data["previous"]),
                action=str(data["action"]),
                created_s=float(data["created_s"]),
                by=str(data.get("by", "")),
                active=tuple(ActiveEntry.from_json(e, where) for e in data["active"]),
                proposal_id=None if data.get("proposal_id") is None else str(data["proposal_id"]),
                restores=None if data.get("restores") is None else int(data["restores"]),
                target=None if data.get("target") is None else str(data["target"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ProposalError(f"{where}: field {exc} is missing or malformed") from None


#: The implicit version 0: the store's own models, nothing promoted.
START = Version(number=0, previous=None, action="start", created_s=0.0, by="", active=())


# -- the store ------------------------------------------------------------------------------


class ProposalStore:
    """Proposals of one model store folder, and the versions of its promoted set."""

    def __init__(self, store_dir: str | Path) -> None:
        self.store_dir = Path(store_dir)
        self.folder = self.store_dir / PROPOSALS_FOLDER
        self.versions = ModelVersions(self.store_dir, self)

    # proposals -----------------------------------------------------------------------------
    def publish(
        self,
        *,
        machine_id: str,
        effect: str,
        params: Mapping[str, Any],
        before_rmse_um: float,
        after_rmse_um: float,
        probe_rows: int,
        document: Mapping[str, Any],
        replaces: str | None = None,
        note: str = "",
        created_s: float | None = None,
    ) -> Proposal:
        """Store a new proposal (status ``proposed``) under the next free id and return it.

        The document must be an augmented model (format and checksum as
        :func:`models.analysis.augmented.load` checks them; one without a checksum is
        sealed here). The figures must be finite, ``probe_rows`` at least 1.
        """
        if not machine_id:
            raise ProposalError("a proposal needs the machine id")
        figures = {"before_rmse_um": before_rmse_um, "after_rmse_um": after_rmse_um}
        for name, value in figures.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ProposalError(f"proposal {name} must be a finite number ≥ 0, got {value!r}")
        if int(probe_rows) < 1:
            raise ProposalError(f"proposal probe_rows must be at least 1, got {probe_rows!r}")
        key = signing.key_for_store(self.store_dir, create=True)
        sealed = checked_document(document, "proposal document", key, sign_unsigned=True)
        created = time.time() if created_s is None else float(created_s)
        params_json = json.loads(json.dumps(dict(params)))
        self.folder.mkdir(parents=True, exist_ok=True)
        published = {"status": PROPOSED, "time_s": created, "note": "published"}
        # No lock: the running loop publishes, and must never wait for a writer of versions.
        # The file is linked to a free id (exclusive); a recovery that removed its temporary
        # file mid-write (FileNotFoundError at the link) only costs another try.
        for _ in range(PUBLISH_TRIES):
            proposal = Proposal(
                self._next_id(),
                str(machine_id),
                created,
                str(effect),
                params_json,
                probe_rows=int(probe_rows),
                document=sealed,
                replaces=replaces,
                note=note,
                history=(published,),
                before_rmse_um=float(before_rmse_um),
                after_rmse_um=float(after_rmse_um),
            )
            with contextlib.suppress(FileNotFoundError):
                if _write_new(self._path(proposal.id), proposal.to_json()):
                    return proposal
        raise ProposalError(
            f"{self.folder}: no proposal file could be written in {PUBLISH_TRIES} tries"
        )

    def list(self, machine_id: str | None = None, status: str | None = None) -> list[Proposal]:
        """Every proposal (of ``machine_id``, with ``status``), oldest first."""
        if not self.folder.is_dir():
            return []
        found = []
        log = self.versions.history()
        for path in sorted(self.folder.glob("P*.json"), key=lambda p: _id_number(p.stem)):
            proposal = self.versions.with_status(self._read(path), log)
            if machine_id is not None and proposal.machine_id != machine_id:
                continue
            if status is not None and proposal.status != status:
                continue
            found.append(proposal)
        return found

    def get(self, proposal_id: str) -> Proposal:
        """The proposal, its status derived from the versions in force (module docstring)."""
        return self.versions.with_status(self.read_file(proposal_id), self.versions.history())

    def read_file(self, proposal_id: str) -> Proposal:
        """The proposal as its file says (status and history as last written)."""
        path = self._path(proposal_id) if _ID_PATTERN.match(proposal_id) else None
        if path is None or not path.exists():
            have = [p.id for p in self.list()]
            raise KeyError(
                f"proposal '{proposal_id}' is not in {self.folder} "
                f"(have: {', '.join(have) if have else 'none'})"
            )
        return self._read(path)

    def reject(
        self, proposal_id: str, note: str = "", time_s: float | None = None, wait_s: float = 0.0
    ) -> Proposal:
        """Mark an open proposal rejected (a promoted one is rolled back instead). ``wait_s``:
        how long to wait for a busy lock (:meth:`ModelVersions.locked`)."""
        with self.versions.locked(wait_s):
            proposal = self.get(proposal_id)
            if not proposal.open:
                raise ProposalError(
                    f"proposal {proposal_id} is {proposal.status}; only a proposed one can be "
                    "rejected (roll back a promoted one)"
                )
            raw = self.read_file(proposal_id)
            return self.set_status(raw, REJECTED, note or "rejected", time_s)

    def set_status(
        self,
        proposal: Proposal,
        status: str,
        note: str,
        time_s: float | None,
        extra: Mapping[str, Any] | None = None,
    ) -> Proposal:
        """Record a status change in the proposal's file and history (the caller holds
        :meth:`ModelVersions.locked`; promote, rollback and reject change statuses).
        ``proposal`` as its file says (:meth:`read_file`); ``extra``: more keys of the
        history entry (a machine's record names the version it is about)."""
        if proposal.status == status and not extra:
            return proposal
        stamp = time.time() if time_s is None else float(time_s)
        entry = {"status": status, "time_s": stamp, "note": note, **(extra or {})}
        changed = replace(proposal, status=status, history=(*proposal.history, entry))
        write_json_atomic(self._path(proposal.id), changed.to_json())
        return changed

    def _path(self, proposal_id: str) -> Path:
        return self.folder / f"{proposal_id}.json"

    def _read(self, path: Path) -> Proposal:
        return Proposal.from_json(read_json(path), str(path))

    def _next_id(self) -> str:
        numbers = [_id_number(p.stem) for p in self.folder.glob("P*.json")]
        return f"P{max(numbers, default=0) + 1:04d}"


class ModelVersions:
    """The versions of a store's promoted set (see the module docstring)."""

    def __init__(self, store_dir: str | Path, proposals: ProposalStore | None = None) -> None:
        self.folder = Path(store_dir) / VERSIONS_FOLDER
        self.proposals = proposals or ProposalStore(store_dir)
        self._pointer_path = os.fspath(self.pointer)  # stat-ed every cycle: joined once

    @property
    def pointer(self) -> Path:
        return self.folder / CURRENT_FILE

    def pointer_key(self) -> tuple[int, int, int] | None:
        """What changes whenever a new version is put in force (one ``stat``; None: none yet)."""
        try:
            status = os.stat(self._pointer_path)
        except FileNotFoundError:
            return None
        return (status.st_ino, status.st_mtime_ns, status.st_size)

    def current(self) -> Version:
        """The version in force (version 0 before any promotion), its models checked: format
        version and, with a signing key for the store, signature (naming the file)."""
        version = self.get(self.current_number())
        key = signing.key_for_store(self.folder.parent)
        for entry in version.active:
            where = f"{self.folder / f'{version.number}.json'}, model of {entry.proposal_id}"
            checked_document(entry.document, where, key)
        return version

    def current_number(self) -> int:
        """The number of the version in force, from ``current.json`` (0 before any)."""
        if not self.pointer.exists():
            return 0
        pointer = read_json(self.pointer)
        try:
            return int(pointer["version"])
        except (KeyError, TypeError, ValueError):
            raise ProposalError(
                f"{self.pointer}: field 'version' is missing or malformed"
            ) from None

    def get(self, number: int) -> Version:
        if number == 0:
            return START
        path = self.folder / f"{number}.json"
        if not path.exists():
            raise KeyError(f"model version {number} is not in {self.folder}")
        version = Version.from_json(read_json(path), str(path))
        if version.number != number:
            raise ProposalError(f"{path}: holds version {version.number}, not {number}")
        return version

    def history(self) -> list[Version]:
        """Every version that was in force, oldest first (version 0 included); a version file
        above the one in force was never in force (a writer killed before its commit)."""
        last = self.current_number()
        return [START, *(self.get(n) for n in self._numbers() if n <= last)]

    def with_status(self, proposal: Proposal, log: list[Version]) -> Proposal:
        """``proposal`` with the status :meth:`derive` gives it."""
        status, _ = self.derive(proposal, log)
        return proposal if status == proposal.status else replace(proposal, status=status)

    def derive(self, proposal: Proposal, log: list[Version]) -> tuple[str, str]:
        """The proposal's status and why, from the versions in force (``log``, oldest first).

        In the version in force: promoted (or what a machine recorded about that very
        version: refused, or promoted again as the one it kept). Out of it after being in
        one: superseded or rejected, as the version that took it out says. Never in one:
        what its own file says if that is proposed or rejected, else proposed.
        """
        current = log[-1]
        last_entry = proposal.history[-1] if proposal.history else {}
        if "machine" in last_entry and last_entry.get("version") == current.number:
            return str(last_entry["status"]), str(last_entry.get("note", ""))
        holding = [i for i, v in enumerate(log) if proposal.id in v.proposal_ids()]
        if holding and holding[-1] == len(log) - 1:
            return PROMOTED, f"in force in version {current.number}"
        if holding:
            leaving = log[holding[-1] + 1]
            if leaving.action == "rollback":
                return REJECTED, f"rolled back in version {leaving.number}"
            return SUPERSEDED, f"superseded by {leaving.proposal_id}"
        if proposal.status in (PROPOSED, REJECTED):
            return proposal.status, ""
        return PROPOSED, "never in force"

    def promote(
        self, proposal_id: str, by: str = "", time_s: float | None = None, wait_s: float = 0.0
    ) -> Version:
        """Put the proposal's model in force: a new version, the proposal ``promoted``.

        A promoted entry of the same machine in the same place (``replaces``) is
        superseded. Refused for a proposal that is not open (already promoted,
        rejected or superseded: publish it again to reconsider it), and for a model of
        an unsupported format version or, with a signing key, not signed with it.
        StoreBusyError if another process holds the lock after ``wait_s`` (:meth:`locked`).
        """
        with self.locked(wait_s):
            proposal = self.proposals.get(proposal_id)
            if not proposal.open:
                raise ProposalError(
                    f"proposal {proposal_id} is {proposal.status}; only a proposed one can be "
                    "promoted"
                )
            where = f"{self.proposals.folder / f'{proposal_id}.json'}, its model"
            key = signing.key_for_store(self.folder.parent)
            checked_document(proposal.document, where, key)
            current = self.current()
            entry = ActiveEntry(
                proposal.id, proposal.machine_id, proposal.replaces, proposal.document
            )
            place = (entry.machine_id, entry.replaces, entry.target)
            kept = [e for e in current.active if (e.machine_id, e.replaces, e.target) != place]
            version = self._write(
                action="promote",
                current=current,
                previous=current.number,
                active=(*kept, entry),
                by=by,
                time_s=time_s,
                proposal_id=proposal.id,
            )
            self.reconcile(version.created_s)
            return version

    def rollback(
        self,
        by: str = "",
        time_s: float | None = None,
        wait_s: float = 0.0,
        target: str | None = None,
    ) -> Version:
        """Restore the set in force before the current version, as a new version (StoreBusyError:
        as :meth:`promote`). ``target``: undo only the latest change of that target's promoted
        models (one axis of a machine that compensates several), every other entry kept."""
        with self.locked(wait_s):
            current = self.current()
            if target is not None:
                version = self._rollback_target(current, target, by, time_s)
            elif current.previous is None:
                raise ProposalError(
                    f"nothing to roll back in {self.folder.parent}: version {current.number} is "
                    "the store's own models"
                )
            else:
                restored = self.get(current.previous)
                version = self._write(
                    action="rollback",
                    current=current,
                    previous=restored.previous,
                    active=restored.active,
                    by=by,
                    time_s=time_s,
                    restores=restored.number,
                )
            self.reconcile(version.created_s)
            return version

    def _rollback_target(
        self, current: Version, target: str, by: str, time_s: float | None
    ) -> Version:
        """A version whose ``target`` entries are those before that target's latest change
        still in force (a rollback of this target undone before is passed over), the other
        entries as they are; a plain rollback of it restores the set in force now."""
        restored = self._before_target_change(current, target)
        if restored is None:
            raise ProposalError(
                f"nothing to roll back for target {target} in {self.folder.parent}: no promoted "
                "model of that target has been put in force"
            )
        others = [e for e in current.active if e.target != target]
        return self._write(
            action="rollback",
            current=current,
            previous=current.number,
            active=(*others, *(e for e in restored.active if e.target == target)),
            by=by,
            time_s=time_s,
            restores=restored.number,
            target=target,
        )

    def _before_target_change(self, version: Version, target: str) -> Version | None:
        """The version in force just before the latest change of ``target``'s entries that
        led to ``version`` (None: they never changed)."""

        def entries(of: Version) -> set[tuple[str, str]]:
            return {(e.proposal_id, e.sha256) for e in of.active if e.target == target}

        previous = version.previous
        while previous is not None:
            if version.action == "rollback" and version.target == target:
                version = self.get(int(version.restores or 0))  # that change was undone
            else:
                before = self.get(previous)
                if entries(before) != entries(version):
                    return before
                version = before
            previous = version.previous
        return None

    def refused_by_machine(
        self,
        proposal_id: str,
        machine_id: str,
        reason: str,
        kept_proposal_id: str | None = None,
        time_s: float | None = None,
    ) -> None:
        """Record that ``machine_id`` refused the promoted ``proposal_id`` (``refused``), and
        that the proposal it kept serving in its place, if any, is in force there again.

        The version stays as written (a rollback or a new promotion replaces it): the
        store then says what the machine runs, not only what was asked of it. Both
        records name the version in force; the next version overrides them.
        """
        with self.locked():
            about = {"machine": machine_id, "version": self.current_number()}
            refused = self.proposals.read_file(proposal_id)
            note = f"machine {machine_id} refused it: {reason}"
            self.proposals.set_status(refused, REFUSED, note, time_s, about)
            if kept_proposal_id is not None:
                kept = self.proposals.read_file(kept_proposal_id)
                note = f"machine {machine_id} still runs it: it refused {proposal_id}"
                self.proposals.set_status(kept, PROMOTED, note, time_s, about)

    def sign_unsigned(self, key: bytes, by: str = "", wait_s: float = 0.0) -> list[str]:
        """Sign the unsigned models of the open proposals and of the version in force
        (``models sign``, for a store written before models were signed by default).

        A proposal file is rewritten with its model signed; the version in force, never
        rewritten, is followed by a new version (action ``sign``) holding the same models,
        signed. A model with a wrong signature is refused (ProposalError). Returns what
        was done, one line each."""
        done: list[str] = []
        with self.locked(wait_s):
            for proposal in self.proposals.list(status=PROPOSED):
                if signing.FIELD in proposal.document:
                    continue
                where = f"{self.proposals.folder / f'{proposal.id}.json'}, its model"
                raw = self.proposals.read_file(proposal.id)
                signed = checked_document(raw.document, where, key, sign_unsigned=True)
                write_json_atomic(
                    self.proposals._path(raw.id), replace(raw, document=signed).to_json()
                )
                done.append(f"signed the model of proposal {proposal.id}")
            current = self.get(self.current_number())
            if any(signing.FIELD not in e.document for e in current.active):
                where = f"{self.folder / f'{current.number}.json'}"
                active = tuple(
                    replace(
                        e, document=checked_document(e.document, where, key, sign_unsigned=True)
                    )
                    for e in current.active
                )
                version = self._write(
                    action="sign",
                    current=current,
                    previous=current.previous,
                    active=active,
                    by=by,
                    time_s=None,
                )
                done.append(
                    f"version {version.number}: the models of version {current.number}, signed"
                )
        return done

    def recover(self, wait_s: float = 0.0) -> list[str]:
        """Clean up after a writer killed mid-change (at the start of ``run`` and of the
        ``models`` commands): remove temporary files and version files never in force, and
        bring each proposal file's status in line with the versions. Returns what was done.
        StoreBusyError while another process holds the lock (its change is under way): readers
        need no recovery (they read through ``current.json``), a writer tries again later."""
        if not self.folder.is_dir() and not self.proposals.folder.is_dir():
            return []
        with self.locked(wait_s):
            done: list[str] = []
            for folder in (self.folder, self.proposals.folder):
                done += [f"removed {p}" for p in remove_temporaries(folder, TEMPORARIES)]
            done += [f"removed {p}, never in force" for p in self._remove_orphans()]
            done += self.reconcile(time.time())
            return done

    def reconcile(self, time_s: float) -> list[str]:
        """Write into each proposal file the status the versions give it, where it differs
        (the caller holds the lock). Returns one line per proposal changed."""
        if not self.proposals.folder.is_dir():
            return []
        log = self.history()
        changed = []
        for path in sorted(self.proposals.folder.glob("P*.json")):
            raw = self.proposals._read(path)
            status, note = self.derive(raw, log)
            if status != raw.status:
                self.proposals.set_status(raw, status, note, time_s)
                changed.append(f"{raw.id}: {raw.status} → {status} ({note})")
        return changed

    @contextlib.contextmanager
    def locked(self, wait_s: float = 0.0) -> Iterator[None]:
        """Hold the store's change lock (one writer of versions and statuses at a time).

        Never a blocking ``flock``: the lock is tried (``LOCK_NB``) and tried again every
        :data:`LOCK_RETRY_S` for up to ``wait_s`` (0: once), then :class:`StoreBusyError` naming
        the lock file and the process holding it. A holder that is stopped (``SIGSTOP``) or
        hung would otherwise stop every writer after it, the running loop included. The
        holder's process id is written into the lock file for that message."""
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / LOCK_FILE
        handle = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            _acquire(handle, path, wait_s)
            try:
                os.ftruncate(handle, 0)
                os.pwrite(handle, f"{os.getpid()}\n".encode(), 0)
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)
        finally:
            os.close(handle)

    def _numbers(self) -> list[int]:
        return sorted(int(p.stem) for p in self.folder.glob("*.json") if p.stem.isdigit())

    def _remove_orphans(self) -> list[Path]:
        """Remove version files above the one in force (the caller holds the lock)."""
        last = self.current_number()
        orphans = [self.folder / f"{n}.json" for n in self._numbers() if n > last]
        for path in orphans:
            path.unlink(missing_ok=True)
        if orphans:
            fsync_folder(self.folder)
        return orphans

    def _write(
        self,
        *,
        action: str,
        current: Version,
        previous: int | None,
        active: tuple[ActiveEntry, ...] | list[ActiveEntry],
        by: str,
        time_s: float | None,
        proposal_id: str | None = None,
        restores: int | None = None,
        target: str | None = None,
    ) -> Version:
        """Write version ``current + 1`` and put it in force (replacing ``current.json`` is
        the commit); a version file left above the one in force is removed first."""
        self._remove_orphans()
        version = Version(
            number=current.number + 1,
            previous=previous,
            action=action,
            created_s=time.time() if time_s is None else float(time_s),
            by=by,
            active=tuple(active),
            proposal_id=proposal_id,
            restores=restores,
            target=target,
        )
        if not _write_new(self.folder / f"{version.number}.json", version.to_json()):
            raise ProposalError(f"{self.folder}: version {version.number} was written meanwhile")
        write_json_atomic(self.pointer, {"version": version.number, "changed_s": version.created_s})
        return version


# -- helpers --------------------------------------------------------------------------------


def target_of(document: Mapping[str, Any]) -> str:
    """The error column a model document predicts (``error_um`` when it names none)."""
    named = document.get("target")
    return str(named.get("name", "error_um")) if isinstance(named, Mapping) else "error_um"


def _acquire(handle: int, path: Path, wait_s: float) -> None:
    """``flock`` ``handle`` without ever blocking in the kernel; StoreBusyError after ``wait_s``."""
    deadline = time.monotonic() + max(0.0, wait_s)
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                raise StoreBusyError(path, _holder(handle), wait_s) from None
            time.sleep(LOCK_RETRY_S)


def _holder(handle: int) -> str:
    """The process id the holder wrote into the lock file ("" if none can be read)."""
    try:
        return os.pread(handle, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return ""


def check_format_version(data: Mapping[str, Any], where: str) -> None:
    """Raise ProposalError naming ``where`` unless ``data`` is of the format version read here."""
    if data.get("format_version") != FORMAT_VERSION:
        raise ProposalError(
            f"{where}: format_version {data.get('format_version')!r} is not supported (this "
            f"software reads version {FORMAT_VERSION}); a newer gateway wrote it"
        )


def checked_document(
    document: Mapping[str, Any],
    where: str,
    key: bytes | None = None,
    *,
    sign_unsigned: bool = False,
) -> dict[str, Any]:
    """The augmented-model document as plain JSON with a valid checksum, or ProposalError.

    Its format version must be one :mod:`models.analysis.augmented` reads; with ``key`` it must be
    signed with it (``sign_unsigned``: one that is not yet signed is signed here, as a
    proposal the residual monitor publishes).
    """
    plain = json.loads(json.dumps(dict(document), ensure_ascii=False))
    if plain.get("format") != augmented.FORMAT:
        raise ProposalError(f"{where}: not an augmented model (format {plain.get('format')!r})")
    if not plain.get("model_id"):
        raise ProposalError(f"{where}: the augmented model has no model_id")
    stored = plain.get("sha256")
    sealed = augmented.sealed(plain)
    if stored is not None and stored != sealed["sha256"]:
        raise ProposalError(f"{where}: checksum mismatch: the model was changed after it was made")
    if sign_unsigned and key is not None and signing.FIELD not in sealed:
        sealed = augmented.sign(sealed, key)
    try:
        augmented.check(sealed, where, key)
    except StoreError as exc:
        raise ProposalError(str(exc)) from None
    return sealed


def read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ProposalError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ProposalError(
            f"{path}: line {exc.lineno}, column {exc.colno}: not JSON ({exc.msg})"
        ) from None
    if not isinstance(data, dict):
        raise ProposalError(f"{path}: expected a JSON object")
    return data


def _write_new(path: Path, payload: Mapping[str, Any]) -> bool:
    """Write a complete file at ``path`` only if none is there yet (False if one was); its
    data and its name reach the disk before this returns."""
    handle, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            json.dump(payload, out, indent=2, ensure_ascii=False)
            out.write("\n")
            out.flush()
            os.fsync(out.fileno())
        try:
            os.link(tmp, path)  # atomic and exclusive: fails if the name is taken
        except FileExistsError:
            return False
        return True
    finally:
        Path(tmp).unlink(missing_ok=True)
        fsync_folder(path.parent)


def _id_number(stem: str) -> int:
    match = _ID_PATTERN.match(stem)
    return int(match.group(1)) if match else 0


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
