"""A real Mosquitto 2 broker for tests: loopback, TLS with a test CA, a password file.

:func:`mosquitto` starts ``/usr/sbin/mosquitto`` on a free port and yields a
:class:`Broker`; :meth:`Broker.kill` and :meth:`Broker.restart` (same port, same
files) fault it mid-run.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from tests.ports import free_tcp_port, wait_for_port

USER = "edge"
PASSWORD = "spb-test-secret"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def make_certificates(folder: Path) -> tuple[Path, Path, Path]:
    """A test CA and a server certificate for 127.0.0.1/localhost: (ca, cert, key)."""
    folder.mkdir(parents=True, exist_ok=True)
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj",
             "/CN=test-ca", "-keyout", "ca.key", "-out", "ca.crt", cwd=folder)  # fmt: skip
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost",
             "-keyout", "server.key", "-out", "server.csr", cwd=folder)  # fmt: skip
    (folder / "san.ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    _openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
             "-CAcreateserial", "-days", "2", "-extfile", "san.ext", "-out", "server.crt",
             cwd=folder)  # fmt: skip
    return folder / "ca.crt", folder / "server.crt", folder / "server.key"


@dataclass
class Broker:
    folder: Path
    port: int
    ca_file: Path
    process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtts://127.0.0.1:{self.port}"

    def start(self) -> None:
        log = open(self.folder / "mosquitto.log", "ab")  # noqa: SIM115 - kept by the process
        self.process = subprocess.Popen(
            ["/usr/sbin/mosquitto", "-c", str(self.folder / "mosquitto.conf")],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        log.close()
        wait_for_port(self.port, timeout_s=15)

    def kill(self) -> None:
        """SIGKILL: no clean shutdown, as a crashed or powered-off broker."""
        if self.process is not None:
            self.process.kill()
            self.process.wait(10)
            self.process = None

    def restart(self) -> None:
        self.kill()
        self.start()


@contextlib.contextmanager
def mosquitto(folder: Path) -> Iterator[Broker]:
    """A TLS-only broker that admits ``USER``/``PASSWORD`` and nobody anonymous."""
    folder.mkdir(parents=True, exist_ok=True)
    ca, cert, key = make_certificates(folder / "tls")
    passwords = folder / "passwords"
    subprocess.run(
        ["mosquitto_passwd", "-b", "-c", str(passwords), USER, PASSWORD],
        check=True,
        capture_output=True,
    )
    passwords.chmod(0o600)
    port = free_tcp_port()
    # Started as root, mosquitto would drop to user 'mosquitto', who cannot read tmp_path.
    user = "user root\n" if os.geteuid() == 0 else ""
    (folder / "mosquitto.conf").write_text(
        f"{user}per_listener_settings false\nallow_anonymous false\npassword_file {passwords}\n"
        f"persistence false\nmax_queued_messages 100000\n"
        f"listener {port} 127.0.0.1\ncafile {ca}\ncertfile {cert}\nkeyfile {key}\n"
    )
    broker = Broker(folder, port, ca)
    broker.start()
    try:
        yield broker
    finally:
        broker.kill()
