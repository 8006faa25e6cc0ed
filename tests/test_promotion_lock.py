"""A ``models promote`` stopped (SIGSTOP) while it holds ``versions/.lock``, a gateway running.

Real processes: ``simulate`` and ``run`` (``models.auto_promote: true``) on the bench
machine, and ``python -m gateway models promote`` under :mod:`tests.kill_at_write`,
which stops it with a real ``SIGSTOP`` as it writes its version file, the lock held.
While it is stopped a proposal for the running machine is published:

- the gateway's loop goes on cycling (its heartbeat file keeps changing) and tries
  the automatic promotion again on later cycles instead of waiting for the lock;
- ``models versions`` (read-only) answers, naming the process that holds the lock;
- a second ``run`` on the same store starts and writes its heartbeat.

Once the stopped command is continued (SIGCONT) it completes, and the gateway promotes
the new proposal on a later cycle.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml

from models.online.proposals import PROMOTED, PROPOSED, ProposalStore
from tests import served_bench as bench
from tests.ports import free_tcp_port
from tests.served_bench import ROOT, wait_until
from tests.test_promotion_kill import MACHINE, offset_model
from tests.test_run_command import bench_config

#: the stopped command's changes under versions/: the lock (recovery), the lock
#: (promotion), then the temporary version file, written with the lock held
STOP_AT_CHANGE = 3


def heartbeat(state: Path) -> dict:
    return json.loads((state / f"{MACHINE}-heartbeat.json").read_text())


def lock_is_held(store: Path) -> bool:
    with open(store / "versions" / ".lock", "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(handle, fcntl.LOCK_UN)
        return False


def publish(store: Path, machine_id: str, model_id: str, offset_um: float) -> str:
    proposal = ProposalStore(store).publish(
        machine_id=machine_id,
        effect="offset",
        params={"offset_um": offset_um},
        before_rmse_um=2.0,
        after_rmse_um=1.5,
        probe_rows=10,
        document=offset_model(store, model_id, offset_um),
    )
    return proposal.id


def publish_within(store: Path, timeout_s: float) -> str | None:
    """Publish a proposal for the running machine; None if it did not return in time."""
    published: list[str] = []
    worker = threading.Thread(
        target=lambda: published.append(publish(store, MACHINE, "offset-live", 0.5)),
        daemon=True,
    )
    worker.start()
    worker.join(timeout_s)
    return published[0] if published else None


def stopped_promote(store: Path, proposal_id: str, output: Path) -> subprocess.Popen[str]:
    """``models promote PROPOSAL --store STORE`` stopped by SIGSTOP with the lock held."""
    env = os.environ | {"KILL_AT_WRITE_SIGNAL": "SIGSTOP"}
    with open(output, "w") as out:
        command = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "tests.kill_at_write",
                str(STOP_AT_CHANGE),
                str(store / "versions"),
                "models",
                "promote",
                proposal_id,
                "--store",
                str(store),
            ],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            text=True,
        )
    stopped = wait_until(lambda: _state(command.pid) == "T" or command.poll() is not None, 60)
    assert stopped and command.poll() is None, output.read_text()
    return command


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return ""


def second_config(config: Path, tmp_path: Path) -> Path:
    """The same machine and store, its own state folder, compensation off (one writer)."""
    document = yaml.safe_load(config.read_text())
    document["state_dir"] = str(tmp_path / "state-2")
    document["logging"] = {"local_store": str(tmp_path / "data-2" / "points.sqlite")}
    document["machines"][0]["compensation"]["enabled"] = False
    return bench.write_config(document, tmp_path / "config-2.yaml")


def test_a_stopped_promote_holding_the_lock_stops_no_loop_and_no_reader(tmp_path: Path) -> None:
    bus, cnc = free_tcp_port(), free_tcp_port()
    config = bench_config(tmp_path, bus, cnc)
    document = yaml.safe_load(config.read_text())
    document["machines"][0]["models"]["auto_promote"] = True
    bench.write_config(document, config)
    store, state = tmp_path / "models", tmp_path / "state"
    # For a machine the gateway does not run: only the command promotes it.
    other = publish(store, "other-machine", "offset-other", 0.25)
    log_path = tmp_path / "run.log"
    command = second = None
    try:
        with bench.bench_running(config, cnc, log_path) as gateway:
            assert wait_until(lambda: (state / f"{MACHINE}-heartbeat.json").exists(), 30)
            command = stopped_promote(store, other, tmp_path / "promote.txt")
            assert lock_is_held(store)
            assert (store / "versions" / ".lock").read_text().strip() == str(command.pid)

            live = publish_within(store, 10)
            assert live is not None, "publishing a proposal waited for the lock"
            before = heartbeat(state)
            time.sleep(8)
            after = heartbeat(state)
            age_s = time.time() - after["wall_time"]
            cycles = after["cycles"] - before["cycles"]
            print(f"{cycles} cycles in 8 s with the lock held; heartbeat {age_s:.1f} s old")
            assert cycles >= 10, (before, after, log_path.read_text()[-3000:])
            assert age_s < 5, after
            assert gateway.poll() is None
            assert ProposalStore(store).get(live).status == PROPOSED  # tried, not waited for
            assert "is tried again every cycle" in log_path.read_text()

            started = time.monotonic()
            listed = subprocess.run(
                [sys.executable, "-m", "gateway", "models", "versions", "--store", str(store)],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=60,
            )
            print(f"models versions answered in {time.monotonic() - started:.1f} s")
            assert listed.returncode == 0, listed.stderr
            assert "* " in listed.stdout and "version 0" in listed.stdout
            assert f"held by process {command.pid}" in listed.stderr

            second = bench.gateway_process("run", "--config", second_config(config, tmp_path))
            bench.wait_for_file(tmp_path / "state-2" / f"{MACHINE}-heartbeat.json", second, 60)
            assert lock_is_held(store)  # all of it while the command was stopped

            command.send_signal(signal.SIGCONT)
            assert command.wait(timeout=60) == 0, (tmp_path / "promote.txt").read_text()
            assert ProposalStore(store).get(other).status == PROMOTED
            assert wait_until(lambda: ProposalStore(store).get(live).status == PROMOTED, 30), (
                log_path.read_text()[-3000:]
            )
            assert wait_until(lambda: "offset-live in place of" in log_path.read_text(), 30)
            assert gateway.poll() is None
            assert "Traceback" not in log_path.read_text()
    finally:
        if command is not None and command.poll() is None:
            command.send_signal(signal.SIGCONT)
            command.kill()
            command.wait()
        bench.kill_if_running(second)
