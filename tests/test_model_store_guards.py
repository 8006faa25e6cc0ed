"""The model store's guards on what a store holds, through real ``check-config`` and ``run``.

- A model file whose id is not its file name (two files' contents swapped: each
  checksum and signature still whole) is refused, naming the file and both ids.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

from models.online.proposals import PROMOTED, PROPOSED, SUPERSEDED, ModelVersions, ProposalStore
from tests import served_bench as bench
from tests.cli import gateway
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
            repaired = wait_until(lambda: file_status(store, "P0003") == PROMOTED, 30)
            assert repaired, log_path.read_text()[-3000:]
            assert file_status(store, "P0002") == SUPERSEDED
            assert "model store recovered: P0003: proposed → promoted" in log_path.read_text()
            assert gateway.poll() is None
    finally:
        commands.close()
