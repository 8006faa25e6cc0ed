"""A connected pair of pseudo-terminals from socat: a serial cable without hardware.

Use the ``serial_pty`` fixture (import ``serial_pty_fixture`` into a test module) or
the ``socat_pty_pair`` context manager. The server opens ``pair.server_port``
(ttyA), the client ``pair.client_port`` (ttyB). A pty ignores baud rate, parity and
inter-frame timing, so those must be tested separately. With ``hexdump`` socat logs
every chunk it passes (direction, time stamp, bytes) to ``pair.log_path``: a wire
tap for tests that check the frames themselves (``tests/rtu_wire.py`` reads it).
"""

from __future__ import annotations

import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

START_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class PtyPair:
    server_port: str
    client_port: str
    log_path: Path | None = None


@contextmanager
def socat_pty_pair(
    directory: Path, timeout_s: float = START_TIMEOUT_S, *, hexdump: bool = False
) -> Iterator[PtyPair]:
    """Run socat with two linked ptys in ``directory``; stop it on exit.

    Waits until both symlinks exist, since socat creates them after it has started
    and a server opening the path earlier would fail.
    """
    socat = shutil.which("socat")
    if socat is None:
        raise RuntimeError("socat is not installed (scripts/setup-system.sh installs it)")
    tty_a, tty_b = directory / "ttyA", directory / "ttyB"
    log_path = directory / "socat.log"
    # The log goes to a file, not a pipe, so socat never blocks on a full pipe.
    with log_path.open("wb") as log_file:
        process = subprocess.Popen(
            [
                socat,
                "-d",
                "-d",
                *(["-x"] if hexdump else []),
                f"pty,raw,echo=0,link={tty_a}",
                f"pty,raw,echo=0,link={tty_b}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=log_file,
        )
        try:
            deadline = time.monotonic() + timeout_s
            while not (tty_a.exists() and tty_b.exists()):
                if process.poll() is not None:
                    log = log_path.read_text(errors="replace")
                    raise RuntimeError(f"socat exited early: {log}")
                if time.monotonic() > deadline:
                    raise RuntimeError(f"socat made no pty pair within {timeout_s} s")
                time.sleep(0.01)
            yield PtyPair(server_port=str(tty_a), client_port=str(tty_b), log_path=log_path)
        finally:
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=2)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()


@pytest.fixture(name="serial_pty")
def serial_pty_fixture(tmp_path: Path) -> Iterator[PtyPair]:
    """A socat pty pair in the test's tmp_path, killed at teardown."""
    with socat_pty_pair(tmp_path) as pair:
        yield pair
