"""A real InfluxDB 1.8.10 server for tests, on 127.0.0.1 at free ports.

influxd 1.8.10 serves the v2 write API and Flux queries that ``influxdb-client``
uses (bucket ``"<database>/autogen"``, any token, org ``"-"``). The binary is
built into ``.cache/bin/influxd`` by ``scripts/setup-system.sh``; a missing
binary fails the test with the command that builds it (no skip: these tests are
part of the suite).

Usage::

    with InfluxServer(tmp_path) as server:
        bucket = server.create_database("gateway")
        ...
        server.stop()    # an outage: the process ends, data stays on disk
        server.start()   # the same data directory and ports
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from tests.ports import free_tcp_port

REPO = Path(__file__).resolve().parents[1]
INFLUXD = REPO / ".cache" / "bin" / "influxd"
BUILD_COMMAND = (
    'GOBIN=$PWD/.cache/bin go install -trimpath -ldflags "-s -w -X main.version=1.8.10" '
    "github.com/influxdata/influxdb/cmd/influxd@v1.8.10"
)
TOKEN = "test-token"  # influxd 1.8 with auth off accepts any token
ORG = "-"

CONFIG = """\
reporting-disabled = true
bind-address = "127.0.0.1:{rpc_port}"

[meta]
  dir = "{root}/meta"
  logging-enabled = false

[data]
  dir = "{root}/data"
  wal-dir = "{root}/wal"
  query-log-enabled = false
  trace-logging-enabled = false

[monitor]
  store-enabled = false

[subscriber]
  enabled = false

[continuous_queries]
  enabled = false

[http]
  enabled = true
  bind-address = "127.0.0.1:{http_port}"
  auth-enabled = false
  log-enabled = false
  write-tracing = false
  pprof-enabled = false
  flux-enabled = true
  flux-log-enabled = false

[logging]
  level = "warn"
  suppress-logo = true

[[graphite]]
  enabled = false
  bind-address = "127.0.0.1:{http_port}"

[[collectd]]
  enabled = false
  bind-address = "127.0.0.1:{http_port}"

[[opentsdb]]
  enabled = false
  bind-address = "127.0.0.1:{http_port}"

[[udp]]
  enabled = false
  bind-address = "127.0.0.1:{http_port}"
"""


class InfluxServer:
    """One influxd process with its own data folder; ``stop``/``start`` keep the data."""

    def __init__(self, root: Path, start_timeout_s: float = 120.0) -> None:
        if not INFLUXD.is_file():
            raise RuntimeError(
                f"the InfluxDB 1.8.10 server binary {INFLUXD} is missing; build it from the "
                f"repository root with:\n  {BUILD_COMMAND}\n(scripts/setup-system.sh does this "
                "when .cache/bin/influxd is missing)"
            )
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.http_port = free_tcp_port()
        self.rpc_port = free_tcp_port()
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.token = TOKEN
        self.org = ORG
        self.start_timeout_s = start_timeout_s
        self.config_path = self.root / "influxdb.conf"
        self.config_path.write_text(
            CONFIG.format(root=self.root, rpc_port=self.rpc_port, http_port=self.http_port),
            encoding="utf-8",
        )
        self.log_path = self.root / "influxd.log"
        self._process: subprocess.Popen[bytes] | None = None

    # --- process ------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def start(self) -> None:
        """Start influxd (again) on the same ports and data folder; return once healthy."""
        if self.running:
            return
        env = {k: v for k, v in os.environ.items() if not k.startswith("INFLUXDB_")}
        with self.log_path.open("ab") as log:
            self._process = subprocess.Popen(
                [str(INFLUXD), "run", "-config", str(self.config_path)],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
            )
        self._wait_healthy()

    def stop(self, timeout_s: float = 15.0) -> None:
        """End the process (SIGTERM, then SIGKILL); its data stays for ``start``."""
        process, self._process = self._process, None
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=timeout_s)

    def kill(self) -> None:
        """End the process at once (SIGKILL), as a power cut would."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            process.kill()
            process.wait(timeout=15)

    def __enter__(self) -> InfluxServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill()

    def _wait_healthy(self) -> None:
        deadline = time.monotonic() + self.start_timeout_s
        last = "no answer"
        while time.monotonic() < deadline:
            assert self._process is not None
            if self._process.poll() is not None:
                raise RuntimeError(
                    f"influxd exited with status {self._process.returncode}:\n{self.log_tail()}"
                )
            try:
                with urllib.request.urlopen(f"{self.url}/health", timeout=1.0) as reply:
                    body = json.loads(reply.read().decode())
                if reply.status == 200 and body.get("status") == "pass":
                    return
                last = str(body)
            except (OSError, ValueError) as exc:
                last = str(exc)
            time.sleep(0.05)
        self.kill()
        raise RuntimeError(
            f"influxd not healthy after {self.start_timeout_s:g} s ({last}):\n{self.log_tail()}"
        )

    def log_tail(self, lines: int = 30) -> str:
        try:
            text = self.log_path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return "(no log)"
        return "\n".join(text.splitlines()[-lines:])

    # --- InfluxQL administration (the v2 API of 1.8 has no bucket endpoints) ------------
    def influxql(self, statement: str) -> dict:
        data = urllib.parse.urlencode({"q": statement}).encode()
        request = urllib.request.Request(f"{self.url}/query", data=data, method="POST")
        with urllib.request.urlopen(request, timeout=10.0) as reply:
            body = json.loads(reply.read().decode())
        for result in body.get("results", []):
            if "error" in result:
                raise RuntimeError(f"{statement}: {result['error']}")
        return body

    def create_database(self, name: str) -> str:
        """Create database ``name``; return its bucket name for the v2 API."""
        self.influxql(f'CREATE DATABASE "{name}"')
        return f"{name}/autogen"
