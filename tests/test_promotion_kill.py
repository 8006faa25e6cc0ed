"""Promotion and rollback killed (SIGKILL) at every write step while ``run`` runs.

``python -m gateway models promote|rollback`` runs as its own process under
:mod:`tests.kill_at_write`, which sends it a real SIGKILL as its Nth change under
the store begins (N = 1, 2, …: the lock, each temporary file, link, rename,
removal and status write). After every kill the store must say one thing: a
proposal is ``promoted`` exactly when it is in the version in force, and the
history lists only versions that were in force. A ``models`` command then leaves
no temporary file and no version file above the one in force, and the running
gateway takes the last version in force.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from models.analysis import augmented
from models.online.proposals import PROMOTED, ModelVersions, ProposalStore
from models.store import load_file
from tests import served_bench as bench
from tests.ports import free_tcp_port
from tests.served_bench import ROOT, read_macro_mm, wait_until
from tests.test_run_command import bench_config

MACHINE = "bench-1"
STEPS = 18  # kill points per command (the changes a promote or rollback makes: 8 to 13)
#: the changes a promote or a rollback makes with nothing left to recover: each one is cut
FEWEST_CHANGES = 8


def offset_model(store: Path, model_id: str, offset_um: float) -> dict[str, Any]:
    """The store's all-regime model as an augmented model, shifted by ``offset_um``."""
    _, document = load_file(store / "mlr-error_um-all.json")
    intercept_um = document.params["intercept_um"] + offset_um
    wrapped = {
        "format": augmented.FORMAT,
        "format_version": augmented.FORMAT_VERSION,
        "model_id": model_id,
        "base": {
            "method": document.method,
            "hyperparams": document.hyperparams,
            "params": document.params,
        },
        "effects": [],
        "effect_sensors": list(document.params["sensors"]),
        "coefficients": {
            "intercept_um": intercept_um,
            "all_um_per_unit": [intercept_um, *document.params["coefficients_um_per_C"]],
        },
        "target": dict(document.target),
        "provenance": {"after": {"rmse_um": 1.0}},
    }
    return augmented.sealed(json.loads(json.dumps(wrapped)))


def publish_offsets(store: Path, count: int) -> None:
    proposals = ProposalStore(store)
    for i in range(count):
        proposals.publish(
            machine_id=MACHINE,
            effect="offset",
            params={"offset_um": 0.25 * i},
            before_rmse_um=2.0,
            after_rmse_um=1.5,
            probe_rows=10,
            document=offset_model(store, f"offset-{i:02d}", 0.25 * i),
        )


class KilledCommands:
    """``tests.kill_at_write --serve``: each command a forked process, killed at a step."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.count = 0
        self.server = subprocess.Popen(
            [sys.executable, "-m", "tests.kill_at_write", "--serve"],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def run(self, step: int, store: Path, *args: str) -> tuple[int, str]:
        """The command's exit code (-9: killed) and its output."""
        self.count += 1
        output = self.folder / f"command-{self.count}.txt"
        request = {"step": step, "folder": str(store), "args": args, "output": str(output)}
        assert self.server.stdin is not None and self.server.stdout is not None
        self.server.stdin.write(json.dumps(request) + "\n")
        self.server.stdin.flush()
        answer = self.server.stdout.readline()
        assert answer, "the kill server ended"
        return int(json.loads(answer)["returncode"]), output.read_text()

    def close(self) -> None:
        if self.server.stdin is not None:
            self.server.stdin.close()
        self.server.wait(timeout=30)


def assert_consistent(store: Path) -> int:
    """Statuses agree with the version in force; history is what was in force. Its number."""
    versions = ModelVersions(store)
    current = versions.current()
    in_force = {e.proposal_id for e in current.active}
    for proposal in ProposalStore(store).list():
        assert (proposal.status == PROMOTED) == (proposal.id in in_force), (
            proposal.id,
            proposal.status,
            current.describe(),
        )
    assert [v.number for v in versions.history()] == list(range(current.number + 1))
    return current.number


def next_command(store: Path, action: str) -> list[str]:
    if action == "rollback":
        return ["models", "rollback", "--store", str(store)]
    open_ones = [p.id for p in ProposalStore(store).list() if p.open]
    return ["models", "promote", open_ones[0], "--store", str(store)]


def test_promote_and_rollback_killed_at_every_step_leave_one_consistent_store(
    tmp_path: Path,
) -> None:
    bus, cnc = free_tcp_port(), free_tcp_port()
    config = bench_config(tmp_path, bus, cnc)
    store = tmp_path / "models"
    publish_offsets(store, 3 * STEPS + 2)
    commands = KilledCommands(tmp_path)
    # Leftovers of a writer killed before this run started: run removes them at start.
    code, output = commands.run(6, store, *next_command(store, "promote"))
    assert code == -signal.SIGKILL, output
    (store / "versions" / ".9.json.x1.tmp").write_text("{")
    (store / "proposals" / ".P0001.json.x2.tmp").write_text("{")
    log_path = tmp_path / "run.log"
    try:
        with bench.bench_running(config, cnc, log_path) as gateway:
            assert not list(store.rglob("*.tmp")), "run left a temporary file behind at start"
            assert "model store recovered" in log_path.read_text()

            kills = 0
            outcomes: list[tuple[int, str, int]] = []
            for step in range(1, STEPS + 1):
                for action in ("promote", "rollback"):
                    if action == "rollback" and ModelVersions(store).current().previous is None:
                        # the promote before was killed ahead of its commit: one to roll back
                        code, output = commands.run(10**6, store, *next_command(store, "promote"))
                        assert code == 0, output
                    code, output = commands.run(step, store, *next_command(store, action))
                    outcomes.append((step, action, code))
                    if code == -signal.SIGKILL:
                        kills += 1
                    else:  # fewer changes than the step
                        assert code == 0, output
                    assert_consistent(store)
            # How many changes a command makes depends on who cleans up after the command
            # killed before it: the command's own recovery, or the running gateway's, which
            # recovers after every new version it sees. Every step must be cut, whichever.
            for action in ("promote", "rollback"):
                killed = {s for s, a, code in outcomes if a == action and code == -signal.SIGKILL}
                assert set(range(1, FEWEST_CHANGES + 1)) <= killed, (action, repr(outcomes))
                assert (STEPS, action, 0) in outcomes, ("every change cut", action, repr(outcomes))
            print(f"{kills} of {len(outcomes)} commands killed: {outcomes}")

            promoted = subprocess.run(
                [sys.executable, "-m", "gateway", *next_command(store, "promote")],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert promoted.returncode == 0, promoted.stderr
            number = assert_consistent(store)
            assert not list(store.rglob("*.tmp"))
            numbered = [
                int(p.stem) for p in (store / "versions").glob("*.json") if p.stem.isdigit()
            ]
            assert max(numbered) == number  # no version file that was never in force
            for path in (store / "proposals").glob("P*.json"):  # the files agree too
                raw = json.loads(path.read_text())
                assert raw["status"] == ProposalStore(store).get(path.stem).status, path
            # The running gateway takes the version in force, and stays within its clamp.
            expected = f"models version {number} in force (promote)"
            assert wait_until(lambda: expected in log_path.read_text(), 60), log_path.read_text()
            assert gateway.poll() is None
            assert abs(read_macro_mm(cnc)) <= 0.050
            assert "Traceback" not in log_path.read_text()
            assert "refused" not in log_path.read_text()
    finally:
        commands.close()
