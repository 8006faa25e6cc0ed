"""The model store's guards on what a store holds, through real ``check-config`` and ``run``.

- A model file whose id is not its file name (two files' contents swapped: each
  checksum and signature still whole) is refused, naming the file and both ids.
"""

from __future__ import annotations

import json
import signal
import stat
from pathlib import Path

import pytest
import yaml

from models import signing
from models.online.proposals import PROMOTED, PROPOSED, SUPERSEDED, ModelVersions, ProposalStore
from models.store import _checksum, load_file
from tests import served_bench as bench
from tests.cli import gateway, gateway_in_process
from tests.ports import free_tcp_port
from tests.served_bench import wait_until
from tests.test_promotion_kill import KilledCommands, publish_offsets
from tests.test_run_command import bench_config

FALLBACK = "mlr-error_um-all"
VARIABLE = "mlr-error_um-variable"


def test_model_files_with_their_contents_swapped_are_refused_naming_both(tmp_path: Path) -> None:
    config = bench_config(tmp_path, free_tcp_port(), free_tcp_port())
    store = tmp_path / "models"
    fallback, variable = store / f"{FALLBACK}.json", store / f"{VARIABLE}.json"
    fallback_text, variable_text = fallback.read_bytes(), variable.read_bytes()
    fallback.write_bytes(variable_text)
    variable.write_bytes(fallback_text)
    for command in ("check-config", "run"):
        refused = gateway(command, "--config", config, timeout_s=120)
        assert refused.returncode == 2, (command, refused.stdout, refused.stderr)
        assert f"{fallback}: holds model '{VARIABLE}', not '{FALLBACK}'" in refused.stderr, (
            command,
            refused.stderr,
        )
        assert "Traceback" not in refused.stderr
    fallback.write_bytes(fallback_text)
    variable.write_bytes(variable_text)
    assert gateway("check-config", "--config", config, timeout_s=120).returncode == 0


def stale_after_commit(commands: KilledCommands, store: Path, proposal_id: str) -> None:
    """``models promote PROPOSAL`` killed (SIGKILL) as it first writes under proposals/:
    after its commit (``current.json`` replaced), before any proposal file is updated."""
    code, output = commands.run(
        1, store / "proposals", "models", "promote", proposal_id, "--store", str(store)
    )
    assert code == -signal.SIGKILL, output
    assert ProposalStore(store).get(proposal_id).status == PROMOTED  # derived: right
    assert file_status(store, proposal_id) == PROPOSED  # the file: behind


def file_status(store: Path, proposal_id: str) -> str:
    return json.loads((store / "proposals" / f"{proposal_id}.json").read_text())["status"]


def test_proposal_files_left_behind_by_a_killed_promote_are_repaired(tmp_path: Path) -> None:
    """At the start of ``run``, and by the running gateway when it sees the version."""
    bus, cnc = free_tcp_port(), free_tcp_port()
    config = bench_config(tmp_path, bus, cnc)
    store = tmp_path / "models"
    publish_offsets(store, 3)
    ModelVersions(store).promote("P0001")
    commands = KilledCommands(tmp_path)
    log_path = tmp_path / "run.log"
    try:
        stale_after_commit(commands, store, "P0002")
        assert file_status(store, "P0001") == PROMOTED
        with bench.bench_running(config, cnc, log_path) as gateway:
            assert file_status(store, "P0002") == PROMOTED, log_path.read_text()
            assert file_status(store, "P0001") == SUPERSEDED
            assert "model store recovered: P0002: proposed → promoted" in log_path.read_text()

            stale_after_commit(commands, store, "P0003")
            # the file is written before the line is logged: wait for both
            said = "model store recovered: P0003: proposed → promoted"
            repaired = wait_until(
                lambda: file_status(store, "P0003") == PROMOTED and said in log_path.read_text(),
                30,
            )
            assert repaired, log_path.read_text()[-3000:]
            assert file_status(store, "P0002") == SUPERSEDED
            assert gateway.poll() is None
    finally:
        commands.close()


def test_models_are_signed_by_default_with_a_key_made_on_first_use(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No key configured anywhere: a store written before signing (unsigned) is refused by
    check-config and run, naming what to run; ``models sign`` makes the key where SSH-like
    defaults put it (outside the store, mode 600) and signs the store; check-config says
    where the key is; ``fit`` signs with it; a forged model (checksum recomputed) is then
    refused for its signature, naming the file."""
    config = bench_config(tmp_path, free_tcp_port(), free_tcp_port())
    store = tmp_path / "models"
    monkeypatch.delenv(signing.KEY_ENV)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    key = tmp_path / "xdg" / "spindle-gateway" / "model-signing.key"
    for path in store.glob("*.json"):  # as an older version wrote them: unsigned
        document = json.loads(path.read_text())
        del document["signature"]
        path.write_text(json.dumps(document))

    for command in ("check-config", "run"):
        refused = gateway(command, "--config", config, timeout_s=120)
        assert refused.returncode == 2, (command, refused.stdout)
        assert f"model signing key {key} does not exist" in refused.stderr
        assert f"python -m gateway models sign --store {store}" in refused.stderr
    assert not key.exists()  # a reader never makes a key

    signed = gateway("models", "sign", "--store", store, timeout_s=120)
    assert signed.returncode == 0, signed.stderr
    assert f"made the model signing key {key} (mode 600)" in signed.stdout
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    assert stat.S_IMODE(key.parent.stat().st_mode) == 0o700
    assert all("signature" in json.loads(p.read_text()) for p in store.glob("*.json"))
    checked = gateway("check-config", "--config", config, timeout_s=120)
    assert checked.returncode == 0, checked.stderr
    assert f"models signed, signing key {key}" in checked.stdout

    refit = tmp_path / "refit"
    fitted = gateway_in_process("fit", tmp_path / "training.csv", "--store", refit)
    assert fitted.returncode == 0, fitted.stderr
    for path in refit.glob("*.json"):
        assert load_file(path)[1].signature is not None  # the same key

    path = store / f"{FALLBACK}.json"
    forged = json.loads(path.read_text())
    forged["params"]["intercept_um"] += 30.0
    forged["sha256"] = _checksum(forged)
    path.write_text(json.dumps(forged))
    for command in ("check-config", "run"):
        refused = gateway(command, "--config", config, timeout_s=120)
        assert refused.returncode == 2, (command, refused.stdout)
        assert f"{path}: the model's signature does not match the signing key" in refused.stderr
        assert "probe" not in refused.stderr
    again = gateway("models", "sign", "--store", store, timeout_s=120)
    assert again.returncode == 2 and "not signed again" in again.stderr  # never whitewashed


def test_a_store_declared_unsigned_is_neither_signed_nor_checked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = bench_config(tmp_path, free_tcp_port(), free_tcp_port())
    store = tmp_path / "models"
    monkeypatch.delenv(signing.KEY_ENV)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    for path in store.glob("*.json"):
        document = json.loads(path.read_text())
        del document["signature"]
        path.write_text(json.dumps(document))
    document = yaml.safe_load(config.read_text())
    document["machines"][0]["models"]["signing"] = False
    bench.write_config(document, config)
    checked = gateway("check-config", "--config", config, timeout_s=120)
    assert checked.returncode == 0, checked.stderr
    assert f"models of {store} unsigned (models.signing: false)" in checked.stdout
    assert not (tmp_path / "xdg").exists()


def test_models_sign_signs_open_proposals_and_the_version_in_force(tmp_path: Path) -> None:
    """A store whose promoted and proposed models were written unsigned (an older version):
    check-config refuses the version in force; ``models sign`` follows it with a version of
    the same models, signed (the version files are never rewritten), and signs the open
    proposal's model, which can then be promoted."""
    config = bench_config(tmp_path, free_tcp_port(), free_tcp_port())
    store = tmp_path / "models"
    publish_offsets(store, 2)
    ModelVersions(store).promote("P0001")
    version_file = store / "versions" / "1.json"
    written = json.loads(version_file.read_text())
    for entry in written["active"]:
        del entry["document"]["signature"]
    version_file.write_text(json.dumps(written))
    proposal_file = store / "proposals" / "P0002.json"
    proposal = json.loads(proposal_file.read_text())
    del proposal["document"]["signature"]
    proposal_file.write_text(json.dumps(proposal))

    refused = gateway("check-config", "--config", config, timeout_s=120)
    assert refused.returncode == 2
    assert f"{version_file}, model of P0001: the model is not signed" in refused.stderr

    signed = gateway("models", "sign", "--config", config, timeout_s=120)
    assert signed.returncode == 0, signed.stderr
    assert "signed the model of proposal P0002" in signed.stdout
    assert "version 2: the models of version 1, signed" in signed.stdout
    assert json.loads(version_file.read_text()) == written  # never rewritten
    assert ModelVersions(store).current().action == "sign"
    assert ProposalStore(store).get("P0001").status == PROMOTED
    checked = gateway("check-config", "--config", config, timeout_s=120)
    assert checked.returncode == 0, checked.stderr
    assert "models version 2" in checked.stdout
    promoted = gateway("models", "promote", "P0002", "--config", config, timeout_s=120)
    assert promoted.returncode == 0, promoted.stderr
