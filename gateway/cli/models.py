"""``python -m gateway models …``: list proposals, promote one, roll back, reject.

The store is named by ``--store DIR`` or found through the configuration
(``--config``, default ``config.yaml``: each machine's ``models.store``). With
the configuration, ``promote`` first checks the model the way the machine will
(sensors, target, bias sensitivity; :func:`gateway.live.bank.promotion.check_promoted`),
so a model the machine would refuse is refused here, with the reason. A running
gateway takes every change within a cycle (it watches ``versions/current.json``).

Every command first cleans up after a change killed mid-write (temporary files,
a version file never put in force, proposal statuses behind the versions:
:meth:`models.online.proposals.ModelVersions.recover`) and says what it did on stderr.
Models are signed (:mod:`models.signing`: the key of ``models.signing_key_file``,
``SPINDLE_MODEL_KEY_FILE`` or the default place); ``promote`` refuses a model that
is not signed with it, and ``sign`` signs a store written before that.

The commands never wait on ``versions/.lock`` without end: ``proposals`` and
``versions`` only read (through the atomic ``versions/current.json``) and skip the
clean-up while another process holds the lock; ``promote``, ``rollback`` and
``reject`` wait up to :data:`LOCK_WAIT_S` for it, then exit 2 naming the lock and
the process holding it.

Like every command, heavy modules load inside the command (tests/test_cli_start.py).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import click

from gateway.cli.options import config_option, input_errors_exit, store_option

STORE_OPTION = store_option("The model store folder.")
CONFIG_OPTION = config_option(
    default=None,
    help="Gateway configuration naming the stores (default config.yaml, unless --store).",
)
MACHINE_OPTION = click.option("--machine", "machine_id", help="Machine id (with --config).")
#: how long a command that changes the store waits for a lock another process holds, s
LOCK_WAIT_S = 10.0


@click.group("models")
def models_group() -> None:
    """Proposals of the residual monitor, promotion, rollback (versioned, nothing deleted)."""


@models_group.command("proposals")
@STORE_OPTION
@CONFIG_OPTION
@MACHINE_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print the list as JSON.")
@input_errors_exit
def list_proposals(
    store_dir: Path | None, config_path: Path | None, machine_id: str | None, as_json: bool
) -> None:
    """List every proposal with its status, and the version in force."""
    from models.online.proposals import ProposalStore

    listed: list[dict[str, Any]] = []
    lines = []
    for store_path, machine in _stores(store_dir, config_path, machine_id, reading=True):
        store = ProposalStore(store_path)
        current = store.versions.current()
        proposals = store.list(machine_id=machine)
        listed += [p.summary() | {"store": str(store_path)} for p in proposals]
        lines.append(f"{store_path}: {current.describe()}")
        lines += [f"  {p.describe()}" for p in proposals] or ["  no proposals"]
    if as_json:
        click.echo(json.dumps(listed, indent=2, ensure_ascii=False))
    else:
        click.echo("\n".join(lines))


@models_group.command("promote")
@click.argument("proposal_id")
@STORE_OPTION
@CONFIG_OPTION
@input_errors_exit
def promote(proposal_id: str, store_dir: Path | None, config_path: Path | None) -> None:
    """Put a proposal's model in force: a new version; a running gateway swaps it in."""
    from models.online.proposals import ProposalStore

    store_path, machine = _store_holding(proposal_id, store_dir, config_path)
    store = ProposalStore(store_path)
    proposal = store.get(proposal_id)
    if machine is not None:
        from gateway.live.bank.promotion import Promotions
        from gateway.wiring import load_bank

        promotions = Promotions(machine)
        promotions.check(proposal, load_bank(machine))
    version = store.versions.promote(proposal_id, by=f"command line, {_who()}", wait_s=LOCK_WAIT_S)
    click.echo(f"promoted {store.get(proposal_id).describe()}")
    click.echo(f"{version.describe()}; a running gateway takes it within a cycle")
    if machine is None:
        click.echo("note: not checked against a machine (no --config): the gateway checks it")


@models_group.command("rollback")
@STORE_OPTION
@CONFIG_OPTION
@MACHINE_OPTION
@click.option(
    "--target",
    help="Undo only the latest change of this target's promoted models (one axis of a "
    "machine that compensates several, e.g. ch5_um); the other targets' stay as they are.",
)
@input_errors_exit
def rollback(
    store_dir: Path | None, config_path: Path | None, machine_id: str | None, target: str | None
) -> None:
    """Restore the promoted set in force before the current version (as a new version)."""
    from models.online.proposals import ProposalStore

    (store_path, _), *others = _stores(store_dir, config_path, machine_id)
    if others:
        raise ValueError("the configuration names several model stores: say which with --machine")
    version = ProposalStore(store_path).versions.rollback(
        by=f"command line, {_who()}", wait_s=LOCK_WAIT_S, target=target
    )
    click.echo(f"{version.describe()}; a running gateway takes it within a cycle")


@models_group.command("reject")
@click.argument("proposal_id")
@STORE_OPTION
@CONFIG_OPTION
@click.option("--note", default="", help="Why (kept in the proposal's history).")
@input_errors_exit
def reject(proposal_id: str, store_dir: Path | None, config_path: Path | None, note: str) -> None:
    """Mark an open proposal rejected (nothing is deleted)."""
    from models.online.proposals import ProposalStore

    store_path, _ = _store_holding(proposal_id, store_dir, config_path)
    proposal = ProposalStore(store_path).reject(
        proposal_id, note=note or f"rejected, {_who()}", wait_s=LOCK_WAIT_S
    )
    click.echo(f"rejected {proposal.describe()}")


@models_group.command("versions")
@STORE_OPTION
@CONFIG_OPTION
@MACHINE_OPTION
@input_errors_exit
def versions(store_dir: Path | None, config_path: Path | None, machine_id: str | None) -> None:
    """Every version of the promoted set, oldest first, and which one is in force."""
    from models.online.proposals import ProposalStore

    for store_path, _ in _stores(store_dir, config_path, machine_id, reading=True):
        history = ProposalStore(store_path).versions
        current = history.current().number
        click.echo(f"{store_path}:")
        for version in history.history():
            stamp = (
                time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(version.created_s))
                if version.created_s
                else "-"
            )
            mark = "*" if version.number == current else " "
            click.echo(
                f" {mark} {stamp} {version.describe()}{f' (by {version.by})' if version.by else ''}"
            )


@models_group.command("sign")
@STORE_OPTION
@CONFIG_OPTION
@MACHINE_OPTION
@input_errors_exit
def sign(store_dir: Path | None, config_path: Path | None, machine_id: str | None) -> None:
    """Sign a store's unsigned models with its key, made if there is none yet.

    For a store written before models were signed by default: its model files,
    augmented models, open proposals and the version in force (followed by a new
    version holding the same models, signed). Each is checked whole first; a model
    whose signature is wrong is refused, never signed again. Sign only models you
    know to be yours.
    """
    from models import signing
    from models.analysis import augmented
    from models.online.proposals import ProposalStore
    from models.store import sign_unsigned_models

    for store_path, _ in _stores(store_dir, config_path, machine_id):
        key_file = signing.key_file_for_store(store_path)
        if key_file is None:
            raise ValueError(f"{store_path}: models.signing is false (an unsigned store)")
        made = not key_file.exists()
        key = signing.key_for_store(store_path, create=True)
        assert key is not None
        if made:
            click.echo(f"made the model signing key {key_file} (mode 600)")
        files = sign_unsigned_models(store_path, key) + augmented.sign_unsigned(store_path, key)
        for path in files:
            click.echo(f"signed {path}")
        by = f"command line, {_who()}"
        for line in ProposalStore(store_path).versions.sign_unsigned(key, by, LOCK_WAIT_S):
            click.echo(f"{store_path}: {line}")
        click.echo(f"{store_path}: every model signed with the key {key_file}")


# -- finding the store --------------------------------------------------------------------


def _stores(
    store_dir: Path | None,
    config_path: Path | None,
    machine_id: str | None,
    reading: bool = False,
) -> list[tuple[Path, Any]]:
    """(store folder, machine id or None) for the store(s) the options name (``reading``:
    for a command that only reads, see :func:`_recovered`)."""
    if store_dir is not None:
        if config_path is not None:
            raise ValueError("give --store or --config, not both")
        if not store_dir.is_dir():
            what = "is a file" if store_dir.exists() else "no such folder"
            raise ValueError(f"--store {store_dir}: {what}; a model store folder was expected")
        return [(_recovered(store_dir, reading), machine_id)]
    machines = _machines(config_path, machine_id)
    seen: dict[Path, str | None] = {}
    for machine in machines:
        # Two machines sharing a store: show all of its proposals.
        seen[machine.models.store] = machine.id if machine.models.store not in seen else None
    return [(_recovered(store, reading), machine) for store, machine in seen.items()]


def _recovered(store_dir: Path, reading: bool = False) -> Path:
    """``store_dir``, cleaned up after a change killed mid-write (said on stderr).

    ``reading``: a command that only reads does not wait for a lock another process
    holds; it says so and reads what is in force (the clean-up is that writer's, or the
    next command's). A command that writes waits up to :data:`LOCK_WAIT_S`."""
    from models.online.proposals import ModelVersions, StoreBusyError

    try:
        lines = ModelVersions(store_dir).recover(wait_s=0.0 if reading else LOCK_WAIT_S)
    except StoreBusyError as exc:
        if not reading:
            raise
        click.echo(f"{store_dir}: not cleaned up: {exc}", err=True)
        return store_dir
    for line in lines:
        click.echo(f"{store_dir}: recovered: {line}", err=True)
    return store_dir


def _store_holding(
    proposal_id: str, store_dir: Path | None, config_path: Path | None
) -> tuple[Path, Any]:
    """The store holding the proposal, and the configured machine it is for (or None)."""
    from models.online.proposals import ProposalStore

    if store_dir is not None:
        store_path, _ = _stores(store_dir, config_path, None)[0]
        return store_path, None
    machines = _machines(config_path, None)
    unknown = None
    for machine in machines:
        store = ProposalStore(_recovered(machine.models.store))
        try:
            proposal = store.get(proposal_id)
        except KeyError as exc:
            unknown = exc
            continue
        owner = next((m for m in machines if m.id == proposal.machine_id), None)
        if owner is None or owner.models.store != machine.models.store:
            raise ValueError(
                f"proposal {proposal_id} is for machine {proposal.machine_id}, which the "
                f"configuration does not run on {machine.models.store}"
            )
        return machine.models.store, owner
    assert unknown is not None
    raise unknown


def _machines(config_path: Path | None, machine_id: str | None) -> list[Any]:
    from gateway.config import load_config
    from models import signing

    config = load_config(config_path or Path("config.yaml"))
    for machine in config.machines:
        signing.configure(
            machine.models.store, machine.models.signing_key_file, machine.models.signing
        )
    machines = list(config.machines)
    if machine_id is not None:
        machines = [m for m in machines if m.id == machine_id]
        if not machines:
            known = ", ".join(m.id for m in config.machines)
            raise ValueError(f"machine {machine_id} is not in {config_path} (have: {known})")
    return machines


def _who() -> str:
    import getpass

    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "unknown user"
