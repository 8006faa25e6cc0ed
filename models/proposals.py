"""Proposed model changes and the versioned set of promoted models, under a model store.

The residual monitor finds an effect the running model lacks, fits the
augmented model on the logged history and *publishes* it here as a
:class:`Proposal`: the effect and its parameters, the held-out RMSE before and
after on the logged data, how many probe rows it rests on, and the augmented
model document itself (the document ``analyze --store`` writes,
:mod:`models.augmented`). Nothing runs from a proposal until it is *promoted*.

Layout (explicit JSON only, every file written to a temporary file and renamed,
so a reader never sees half a file)::

    <store>/proposals/<id>.json     one proposal, its status and status history
    <store>/versions/<n>.json       version n of the promoted set (never rewritten)
    <store>/versions/current.json   which version is in force

Every change of the promoted set writes a new version: a promotion adds (or
replaces) one entry, a rollback writes a version whose set is the one in force
before the version it leaves, and which rolls back further, to that version's
own predecessor, when rolled back again. Nothing is deleted, so the version
files are the audit trail. Version 0 is implicit: the store's own models, none
promoted.

A promoted entry names the model it takes the place of (``replaces``, a model
id of the store, or None: every regime). Promoting a proposal for the same
machine and the same ``replaces`` supersedes the entry there.

The running gateway watches ``versions/current.json`` (a ``stat`` per cycle,
:meth:`ModelVersions.pointer_key`) and swaps the set in between cycles after its
own checks (:mod:`gateway.promotion`). Writers take ``versions/.lock`` (an
advisory ``flock``), so the command line and the gateway's SCADA method can
change the set at the same time without losing a version.
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

from models import augmented
from models.json_files import write_json_atomic
from models.store import StoreError

PROPOSALS_FOLDER = "proposals"
VERSIONS_FOLDER = "versions"
CURRENT_FILE = "current.json"
LOCK_FILE = ".lock"

PROPOSAL_FORMAT = "thermal-gateway-model-proposal"
VERSION_FORMAT = "thermal-gateway-model-version"
FORMAT_VERSION = 1

PROPOSED = "proposed"
PROMOTED = "promoted"
REJECTED = "rejected"
SUPERSEDED = "superseded"
#: Promoted, but the machine would not run it (its checks, gateway/promotion.py).
REFUSED = "refused"
STATUSES = (PROPOSED, PROMOTED, REJECTED, SUPERSEDED, REFUSED)
#: Statuses of a proposal an operator may still promote.
OPEN = (PROPOSED,)

_ID_PATTERN = re.compile(r"^P(\d{4,})$")


class ProposalError(StoreError):
    """A proposal or version file that cannot be used, or a change that is not allowed."""


# -- records --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Proposal:
    """One proposed augmented model for one machine (units in the names).

    ``document`` is the augmented-model document (:mod:`models.augmented`),
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

    def for_machine(self, machine_id: str) -> list[ActiveEntry]:
        return [e for e in self.active if e.machine_id == machine_id]

    def describe(self) -> str:
        models = ", ".join(f"{e.model_id} ({e.proposal_id})" for e in self.active) or "none"
        what = {
            "start": "the store's own models",
            "promote": f"promoted {self.proposal_id}",
            "rollback": f"rolled back to the set of version {self.restores}",
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
            "active": [e.to_json() for e in self.active],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], where: str) -> Version:
        if data.get("format") != VERSION_FORMAT:
            raise ProposalError(f"{where}: not a model version (format {data.get('format')!r})")
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
        :func:`models.augmented.load` checks them; one without a checksum is
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
        sealed = checked_document(document, "proposal document")
        created = time.time() if created_s is None else float(created_s)
        params_json = json.loads(json.dumps(dict(params)))
        self.folder.mkdir(parents=True, exist_ok=True)
        figures = {name: float(value) for name, value in figures.items()}
        published = {"status": PROPOSED, "time_s": created, "note": "published"}
        while True:
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
                **figures,
            )
            if _write_new(self._path(proposal.id), proposal.to_json()):
                return proposal

    def list(self, machine_id: str | None = None, status: str | None = None) -> list[Proposal]:
        """Every proposal (of ``machine_id``, with ``status``), oldest first."""
        if not self.folder.is_dir():
            return []
        found = []
        for path in sorted(self.folder.glob("P*.json"), key=lambda p: _id_number(p.stem)):
            proposal = self._read(path)
            if machine_id is not None and proposal.machine_id != machine_id:
                continue
            if status is not None and proposal.status != status:
                continue
            found.append(proposal)
        return found

    def get(self, proposal_id: str) -> Proposal:
        path = self._path(proposal_id) if _ID_PATTERN.match(proposal_id) else None
        if path is None or not path.exists():
            have = [p.id for p in self.list()]
            raise KeyError(
                f"proposal '{proposal_id}' is not in {self.folder} "
                f"(have: {', '.join(have) if have else 'none'})"
            )
        return self._read(path)

    def reject(self, proposal_id: str, note: str = "", time_s: float | None = None) -> Proposal:
        """Mark an open proposal rejected (a promoted one is rolled back instead)."""
        with self.versions.locked():
            proposal = self.get(proposal_id)
            if not proposal.open:
                raise ProposalError(
                    f"proposal {proposal_id} is {proposal.status}; only a proposed one can be "
                    "rejected (roll back a promoted one)"
                )
            return self.set_status(proposal, REJECTED, note or "rejected", time_s)

    def set_status(
        self, proposal: Proposal, status: str, note: str, time_s: float | None
    ) -> Proposal:
        """Record a status change in the proposal's file and history (the caller holds
        :meth:`ModelVersions.locked`; promote, rollback and reject change statuses)."""
        if proposal.status == status:
            return proposal
        stamp = time.time() if time_s is None else float(time_s)
        changed = replace(
            proposal,
            status=status,
            history=(*proposal.history, {"status": status, "time_s": stamp, "note": note}),
        )
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
        """The version in force (version 0 before any promotion)."""
        if not self.pointer.exists():
            return START
        pointer = read_json(self.pointer)
        try:
            number = int(pointer["version"])
        except (KeyError, TypeError, ValueError):
            raise ProposalError(
                f"{self.pointer}: field 'version' is missing or malformed"
            ) from None
        return self.get(number)

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
        """Every version written, oldest first (version 0 included)."""
        numbers = sorted(int(p.stem) for p in self.folder.glob("*.json") if p.stem.isdigit())
        return [START, *(self.get(n) for n in numbers)]

    def promote(self, proposal_id: str, by: str = "", time_s: float | None = None) -> Version:
        """Put the proposal's model in force: a new version, the proposal ``promoted``.

        A promoted entry of the same machine in the same place (``replaces``) is
        superseded. Refused for a proposal that is not open (already promoted,
        rejected or superseded: publish it again to reconsider it).
        """
        with self.locked():
            proposal = self.proposals.get(proposal_id)
            if not proposal.open:
                raise ProposalError(
                    f"proposal {proposal_id} is {proposal.status}; only a proposed one can be "
                    "promoted"
                )
            checked_document(proposal.document, f"proposal {proposal_id}")
            current = self.current()
            entry = ActiveEntry(
                proposal.id, proposal.machine_id, proposal.replaces, proposal.document
            )
            kept = [
                e
                for e in current.active
                if (e.machine_id, e.replaces) != (entry.machine_id, entry.replaces)
            ]
            version = self._write(
                action="promote",
                previous=current.number,
                active=(*kept, entry),
                by=by,
                time_s=time_s,
                proposal_id=proposal.id,
            )
            self._update_statuses(current, version, SUPERSEDED, f"superseded by {proposal.id}")
            return version

    def rollback(self, by: str = "", time_s: float | None = None) -> Version:
        """Restore the set in force before the current version, as a new version."""
        with self.locked():
            current = self.current()
            if current.previous is None:
                raise ProposalError(
                    f"nothing to roll back in {self.folder.parent}: version {current.number} is "
                    "the store's own models"
                )
            restored = self.get(current.previous)
            version = self._write(
                action="rollback",
                previous=restored.previous,
                active=restored.active,
                by=by,
                time_s=time_s,
                restores=restored.number,
            )
            self._update_statuses(
                current, version, REJECTED, f"rolled back in version {version.number}"
            )
            return version

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
        store then says what the machine runs, not only what was asked of it.
        """
        with self.locked():
            refused = self.proposals.get(proposal_id)
            note = f"machine {machine_id} refused it: {reason}"
            self.proposals.set_status(refused, REFUSED, note, time_s)
            if kept_proposal_id is not None:
                kept = self.proposals.get(kept_proposal_id)
                note = f"machine {machine_id} still runs it: it refused {proposal_id}"
                self.proposals.set_status(kept, PROMOTED, note, time_s)

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the store's change lock (one writer of versions and statuses at a time)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        with open(self.folder / LOCK_FILE, "a", encoding="utf-8") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    def _write(
        self,
        *,
        action: str,
        previous: int | None,
        active: tuple[ActiveEntry, ...] | list[ActiveEntry],
        by: str,
        time_s: float | None,
        proposal_id: str | None = None,
        restores: int | None = None,
    ) -> Version:
        numbers = [int(p.stem) for p in self.folder.glob("*.json") if p.stem.isdigit()]
        version = Version(
            number=max(numbers, default=0) + 1,
            previous=previous,
            action=action,
            created_s=time.time() if time_s is None else float(time_s),
            by=by,
            active=tuple(active),
            proposal_id=proposal_id,
            restores=restores,
        )
        if not _write_new(self.folder / f"{version.number}.json", version.to_json()):
            raise ProposalError(f"{self.folder}: version {version.number} was written meanwhile")
        write_json_atomic(self.pointer, {"version": version.number, "changed_s": version.created_s})
        return version

    def _update_statuses(self, old: Version, new: Version, left_as: str, note: str) -> None:
        """Proposals in the new set are ``promoted``; those that left it become ``left_as``."""
        now_in = {e.proposal_id for e in new.active}
        was_in = {e.proposal_id for e in old.active}
        for proposal_id in sorted(now_in | was_in):
            try:
                proposal = self.proposals.get(proposal_id)
            except KeyError:
                continue  # a version may outlive a proposal file moved away by hand
            if proposal_id in now_in:
                self.proposals.set_status(
                    proposal, PROMOTED, f"in force in version {new.number}", new.created_s
                )
            else:
                self.proposals.set_status(proposal, left_as, note, new.created_s)


# -- helpers --------------------------------------------------------------------------------


def checked_document(document: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The augmented-model document as plain JSON with a valid checksum, or ProposalError."""
    plain = json.loads(json.dumps(dict(document), ensure_ascii=False))
    if plain.get("format") != augmented.FORMAT:
        raise ProposalError(f"{where}: not an augmented model (format {plain.get('format')!r})")
    if not plain.get("model_id"):
        raise ProposalError(f"{where}: the augmented model has no model_id")
    stored = plain.get("sha256")
    sealed = augmented.sealed(plain)
    if stored is not None and stored != sealed["sha256"]:
        raise ProposalError(f"{where}: checksum mismatch: the model was changed after it was made")
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
    """Write a complete file at ``path`` only if none is there yet (False if one was)."""
    handle, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            json.dump(payload, out, indent=2, ensure_ascii=False)
            out.write("\n")
        try:
            os.link(tmp, path)  # atomic and exclusive: fails if the name is taken
        except FileExistsError:
            return False
        return True
    finally:
        Path(tmp).unlink(missing_ok=True)


def _id_number(stem: str) -> int:
    match = _ID_PATTERN.match(stem)
    return int(match.group(1)) if match else 0


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
