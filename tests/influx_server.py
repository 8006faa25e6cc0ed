"""A real InfluxDB 2.7.12 server for tests, on 127.0.0.1 at a free port.

The same version deploy/docker-compose.yml ships, so the writer, the forwarder's
outage handling, ``export`` and the Grafana dashboard's queries are tested against
the database a deployment runs: token authentication, an organisation, buckets,
the v2 write API and Flux. The binary is built into ``.cache/bin/influxd2`` by
``scripts/build-influxd2.sh`` (called by ``scripts/setup-system.sh`` when missing);
a missing binary fails the test with that command (no skip: these tests are part
of the suite).

The first start runs the server's one-time setup (``POST /api/v2/setup``) with a
known operator token, organisation and bucket; later starts reuse its data.

Usage::

    with InfluxServer(tmp_path) as server:
        bucket = server.create_database("gateway")   # a bucket in server.org
        ...
        server.stop()    # an outage: the process ends, data stays on disk
        server.start()   # the same data folder and port
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

from tests.ports import free_tcp_port

REPO = Path(__file__).resolve().parents[1]
INFLUXD = REPO / ".cache" / "bin" / "influxd2"
VERSION = "2.7.12"  # = deploy/docker-compose.yml's influxdb image
BUILD_COMMAND = "bash scripts/build-influxd2.sh"
TOKEN = "spindle-test-operator-token"  # the operator token the setup creates
ORG = "spindle"
USER = "admin"
PASSWORD = "spindle-test-password"
SETUP_BUCKET = "setup"


class InfluxServer:
    """One influxd 2 process with its own data folder; ``stop``/``start`` keep the data."""

    def __init__(self, root: Path, start_timeout_s: float = 120.0) -> None:
        if not INFLUXD.is_file():
            raise RuntimeError(
                f"the InfluxDB {VERSION} server binary {INFLUXD} is missing; build it from the "
                f"repository root with:\n  {BUILD_COMMAND}\n(scripts/setup-system.sh does this "
                "when it is missing; about 12 minutes once)"
            )
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.http_port = free_tcp_port()
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.token = TOKEN
        self.org = ORG
        self.org_id: str | None = None
        self.start_timeout_s = start_timeout_s
        self.log_path = self.root / "influxd.log"
        self._process: subprocess.Popen[bytes] | None = None

    # --- process ------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def command(self) -> list[str]:
        return [
            str(INFLUXD),
            "--http-bind-address",
            f"127.0.0.1:{self.http_port}",
            "--bolt-path",
            str(self.root / "influxd.bolt"),
            "--engine-path",
            str(self.root / "engine"),
            "--sqlite-path",
            str(self.root / "influxd.sqlite"),
            "--reporting-disabled",
            "--log-level",
            "warn",
        ]

    def start(self) -> None:
        """Start influxd (again) on the same port and data folder; return once set up."""
        if self.running:
            return
        env = {k: v for k, v in os.environ.items() if not k.startswith(("INFLUX", "INFLUXD_"))}
        with self.log_path.open("ab") as log:
            self._process = subprocess.Popen(
                self.command(),
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
            )
        self._wait_healthy()
        self._set_up()

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
                body = self.api("GET", "/health", auth=False, timeout_s=1.0)
                if body.get("status") == "pass":
                    return
                last = str(body)
            except (OSError, ValueError) as exc:
                last = str(exc)
            time.sleep(0.05)
        self.kill()
        raise RuntimeError(
            f"influxd not healthy after {self.start_timeout_s:g} s ({last}):\n{self.log_tail()}"
        )

    def _set_up(self) -> None:
        """The one-time setup on a new data folder: user, org, bucket, operator token."""
        if self.api("GET", "/api/v2/setup", auth=False).get("allowed"):
            answer = self.api(
                "POST",
                "/api/v2/setup",
                {
                    "username": USER,
                    "password": PASSWORD,
                    "org": ORG,
                    "bucket": SETUP_BUCKET,
                    "token": TOKEN,
                },
                auth=False,
            )
            self.org_id = answer["org"]["id"]
        else:
            (org,) = self.api("GET", f"/api/v2/orgs?org={ORG}")["orgs"]
            self.org_id = org["id"]

    def log_tail(self, lines: int = 30) -> str:
        try:
            text = self.log_path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return "(no log)"
        return "\n".join(text.splitlines()[-lines:])

    # --- the HTTP API -------------------------------------------------------------------
    def api(
        self,
        method: str,
        path: str,
        body: dict | None = None,
        auth: bool = True,
        timeout_s: float = 10.0,
    ) -> dict:
        """One JSON call of the server's API; raises RuntimeError with its message."""
        headers = {"Content-Type": "application/json"}
        if auth:
            headers["Authorization"] = f"Token {self.token}"
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data, headers, method=method)
        try:
            with urllib.request.urlopen(request, timeout=timeout_s) as reply:
                text = reply.read().decode()
        except urllib.error.HTTPError as exc:
            raise RuntimeError(f"{method} {path}: HTTP {exc.code} {exc.read().decode()}") from None
        return json.loads(text) if text.strip() else {}

    def create_database(self, name: str) -> str:
        """Create bucket ``name`` (infinite retention) in ``org``; return its name."""
        self.api(
            "POST", "/api/v2/buckets", {"orgID": self.org_id, "name": name, "retentionRules": []}
        )
        return name

    create_bucket = create_database

    def create_token(self, description: str, bucket: str, write: bool = True) -> str:
        """A token that may read (and write) one bucket only, as a deployment gives out."""
        resource = {"type": "buckets", "orgID": self.org_id, "name": bucket}
        (found,) = self.api("GET", f"/api/v2/buckets?orgID={self.org_id}&name={bucket}")["buckets"]
        resource["id"] = found["id"]
        actions = ["read", "write"] if write else ["read"]
        answer = self.api(
            "POST",
            "/api/v2/authorizations",
            {
                "orgID": self.org_id,
                "description": description,
                "permissions": [{"action": a, "resource": resource} for a in actions],
            },
        )
        return answer["token"]
