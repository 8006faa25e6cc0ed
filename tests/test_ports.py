"""Ports handed to servers under test are outside the kernel's ephemeral range and are
never handed to two xdist workers of one run (tests/ports.py)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

from tests.cli import ROOT
from tests.ports import BLOCK_PORTS, ephemeral_range, free_tcp_port

TAKE = """
import json
from tests.ports import free_tcp_port
print(json.dumps([free_tcp_port() for _ in range(60)]))
"""


def ports_of_worker(worker: str, run_id: str) -> list[int]:
    """60 ports taken by a fresh process that xdist would call ``worker`` in run ``run_id``."""
    env = {**os.environ, "PYTEST_XDIST_WORKER": worker, "PYTEST_XDIST_TESTRUNUID": run_id}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run(
        [sys.executable, "-c", TAKE], env=env, cwd=ROOT, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout)


def test_ports_are_never_ephemeral_ones() -> None:
    """An outgoing connection's source port comes from the ephemeral range: a port handed
    out from it (as bind(0) did) could be taken before the server binds it."""
    low, high = ephemeral_range()
    ports = [free_tcp_port() for _ in range(100)]
    assert not [port for port in ports if low <= port <= high]
    assert len(set(ports)) == len(ports)  # in turn: none given twice within a block


def test_two_workers_of_one_run_never_share_a_port() -> None:
    run_id = "9f1c0d2ab7e34e8c"
    first = ports_of_worker("gw0", run_id)
    second = ports_of_worker("gw1", run_id)
    assert not set(first) & set(second)
    assert max(first + second) - min(first + second) < 2 * BLOCK_PORTS  # two neighbouring blocks


def test_a_port_someone_listens_on_is_passed_over() -> None:
    taken = []
    try:
        for _ in range(3):
            port = free_tcp_port()
            server = socket.socket()
            server.bind(("127.0.0.1", port))
            server.listen()
            taken.append(server)
        listening = {s.getsockname()[1] for s in taken}
        ports = {free_tcp_port() for _ in range(2 * BLOCK_PORTS)}
        assert not ports & listening
    finally:
        for server in taken:
            server.close()
