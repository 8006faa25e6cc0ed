"""TCP ports for servers under test, that no other test process is handed at the same time.

A port the kernel picks for ``bind(port 0)`` and that is released before the server
binds it can be taken in between: by another xdist worker's server handed the same
number, or by any outgoing connection, whose source port comes from the same
ephemeral range (Linux: ``/proc/sys/net/ipv4/ip_local_port_range``, 32768–60999).
Under ``-n 2`` that showed as EADDRINUSE.

So the ports handed out here are never ephemeral ones: they come from below that
range (10000 up), each xdist worker (``PYTEST_XDIST_WORKER``) has a block of its own,
and the run (``PYTEST_XDIST_TESTRUNUID``, else the process) picks where the blocks
start, so two test sessions on one machine rarely share one. Within a block the
ports are handed out in turn, each checked free before it is given.
"""

from __future__ import annotations

import hashlib
import itertools
import os
import socket
from collections.abc import Iterator
from pathlib import Path

LOWEST_PORT = 10_000
BLOCK_PORTS = 250  # ports a worker hands out before it comes round again


def ephemeral_range() -> tuple[int, int]:
    """The kernel's range of source ports for outgoing connections (Linux default if unread)."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999


def _blocks() -> tuple[int, int]:
    """(first port of the non-ephemeral span used, how many blocks it holds)."""
    low, high = ephemeral_range()
    if low - LOWEST_PORT >= 4 * BLOCK_PORTS:
        return LOWEST_PORT, (low - LOWEST_PORT) // BLOCK_PORTS
    return high + 1, (65535 - high) // BLOCK_PORTS  # a range starting low: above it


def _worker_ports() -> Iterator[int]:
    """This process's block of ports, in turn, for ever."""
    first, count = _blocks()
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID") or f"pid {os.getpid()}"
    start = int(hashlib.sha256(run.encode()).hexdigest(), 16) % count
    block = (start + (int(worker) if worker.isdigit() else 0)) % count
    base = first + block * BLOCK_PORTS
    offset = os.getpid() % BLOCK_PORTS  # a child process of the same worker starts elsewhere
    return (base + (offset + i) % BLOCK_PORTS for i in itertools.count())


_ports = _worker_ports()


def _is_free(port: int, host: str) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that nothing listens on now, outside the ephemeral range and
    not handed to another worker of this run (see the module docstring)."""
    for _ in range(BLOCK_PORTS):
        port = next(_ports)
        if _is_free(port, host):
            return port
    raise AssertionError(f"no free port in this worker's block of {BLOCK_PORTS} ports")


def wait_for_port(port: int, host: str = "127.0.0.1", timeout_s: float = 30.0) -> None:
    """Return once something accepts TCP connections on ``port``; fail after ``timeout_s``."""
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as probe:
            if probe.connect_ex((host, port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"nothing listens on {host}:{port} after {timeout_s:g} s")
