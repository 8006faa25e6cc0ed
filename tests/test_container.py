"""The edge image, built from the repository's Dockerfile and run as an edge box runs it.

podman (Debian's 4.3, runc) builds the image on a local Debian base
(``scripts/build-image.sh``; base and layers cached machine-wide, see scripts/podman.sh)
and runs it the way deploy/docker-compose.yml does: uid 10001, read-only root, only
``/data`` and ``/tmp`` writable, every capability dropped, no new privileges. The
container's network is the host's, so it reaches the simulated machine
(``python -m gateway simulate``) and a real InfluxDB on 127.0.0.1. Its configuration
is deploy/config.docker.yaml as shipped, with only the machine's addresses (and the
SCADA port, to stay clear of other tests) pointed at this bench, and its settings come
from the environment variables compose passes. Every command is the one
deploy/README.md gives an edge box.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.demo.compensate import write_training_data
from gateway.outputs.influx import InfluxReader
from tests.influx_server import InfluxServer
from tests.ports import free_tcp_port, wait_for_port
from tests.served_bench import gateway_process

ROOT = Path(__file__).resolve().parent.parent
PODMAN = [str(ROOT / "scripts/podman.sh")]
CONFIG = ROOT / "deploy/config.docker.yaml"
NODE_DIR = ROOT / "tests/node"
UID = 10001
GRACE_S = 30  # compose's stop_grace_period
HEALTHY_WITHIN_S = 60


def podman(*args: str, timeout_s: float = 120, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [*PODMAN, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout_s
    )
    if check:
        assert result.returncode == 0, f"podman {' '.join(args)}: {result.stderr[-3000:]}"
    return result


def version() -> str:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"][
        "version"
    ]


@pytest.fixture(scope="module")
def image() -> str:
    """The image, built (or found up to date in the layer cache) by scripts/build-image.sh."""
    tag = f"spindle-thermal-gateway:{version()}"
    started = time.monotonic()
    build = subprocess.run(
        ["bash", "scripts/build-image.sh", tag],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-4000:]
    print(f"image build: {time.monotonic() - started:.1f} s", file=sys.stderr)
    return tag


def hardening(data: Path) -> list[str]:
    """The run options of deploy/docker-compose.yml's gateway service, for podman."""
    return [
        "--user",
        f"{UID}:{UID}",
        "--read-only",
        "--read-only-tmpfs=false",  # podman would add /run, /var/tmp: only /tmp here
        "--tmpfs",
        "/tmp",
        "--cap-drop",
        "ALL",
        "--security-opt",
        "no-new-privileges",
        "--network",
        "host",
        "-v",
        f"{data}:/data",
    ]


def bench_config(bus_port: int, cnc_port: int, scada_port: int) -> dict[str, Any]:
    """config.docker.yaml as shipped, its machine pointed at the simulated one."""
    config = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    (machine,) = config["machines"]
    (bus,) = machine["transmitters"]
    bus["tcp"] = {"host": "127.0.0.1", "port": bus_port}
    machine["cnc"] = {"modbus": {"host": "127.0.0.1", "port": cnc_port}}
    # The simulator runs ×20: its temperatures change faster than a real machine's.
    machine["sensors"] = {f"T{i}": {"max_rate_C_per_s": 50.0} for i in range(1, 10)}
    # … and its error grows 20 times faster too: the prediction's rate bound follows.
    machine["quality"] = {"max_prediction_rate_um_per_s": 20 * 0.1}
    config["scada"]["port"] = scada_port
    return config


def simulator_config(bus_port: int, cnc_port: int) -> dict[str, Any]:
    devices = [
        {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
        {"device_id": 2, "channels": ["T9", "ambient"]},
    ]
    return {
        "simulator": {
            "program": "const8000",
            "speedup": 20,
            "transmitters": {"tcp": {"port": bus_port, "devices": devices}},
            "cnc": {"modbus": {"port": cnc_port}},
        }
    }


def node_read(endpoint: str, pki: Path, operations: list[dict], password: str) -> tuple[int, dict]:
    """node-opcua (tests/node/scada_client.mjs) as the viewer, SignAndEncrypt."""
    if shutil.which("node") is None or not (NODE_DIR / "node_modules").is_dir():
        raise RuntimeError("node and tests/node/node_modules are needed (npm ci in tests/node)")
    command = ["node", "scada_client.mjs", endpoint, json.dumps(operations)]
    result = subprocess.run(
        [*command, "--pki", str(pki), "--user", "viewer"],
        cwd=NODE_DIR,
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "SCADA_PASSWORD": password},
    )
    lines = result.stdout.strip().splitlines()
    assert lines, f"no output (exit {result.returncode}): {result.stderr[-2000:]}"
    return result.returncode, json.loads(lines[-1])


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The simulated machine and a real InfluxDB on loopback, for the container to reach."""
    bus_port, cnc_port = free_tcp_port(), free_tcp_port()
    sim_path = tmp_path / "simulator.yaml"
    sim_path.write_text(yaml.safe_dump(simulator_config(bus_port, cnc_port)), encoding="utf-8")
    simulator = gateway_process("simulate", "--config", sim_path)
    try:
        with InfluxServer(tmp_path / "influxdb") as influx:
            wait_for_port(cnc_port)
            yield {
                "bus_port": bus_port,
                "cnc_port": cnc_port,
                "influx": influx,
                "bucket": influx.create_database("spindle"),
            }
    finally:
        simulator.send_signal(signal.SIGINT)
        simulator.communicate(timeout=30)


@pytest.mark.timeout(1800)  # the image build (its module fixture) counts: minutes on a busy machine
def test_image_runs_hardened_against_the_simulator_and_influxdb(
    image: str, bench: dict[str, Any], tmp_path: Path
) -> None:
    data, runs, config_dir = tmp_path / "data", tmp_path / "runs", tmp_path / "config"
    for folder in (data, runs, config_dir):
        folder.mkdir()
    os.chown(data, UID, UID)  # README: chown -R 10001:10001 a bind-mounted /data
    scada_port = free_tcp_port()
    config_path = config_dir / "config.yaml"
    config_path.write_text(
        yaml.safe_dump(bench_config(bench["bus_port"], bench["cnc_port"], scada_port)),
        encoding="utf-8",
    )
    influx: InfluxServer = bench["influx"]
    secrets = {
        "CNC_OPCUA_PASSWORD": "unused-with-a-modbus-cnc",
        "SCADA_OPCUA_OPERATOR_PASSWORD": uuid.uuid4().hex,
        "SCADA_OPCUA_VIEWER_PASSWORD": uuid.uuid4().hex,
        "INFLUXDB_URL": influx.url,
        "INFLUXDB_ORG": influx.org,
        "INFLUXDB_BUCKET": bench["bucket"],
        "INFLUXDB_TOKEN": influx.token,
        "TZ": "",
    }
    env_file = tmp_path / "gateway.env"
    env_file.write_text("".join(f"{k}={v}\n" for k, v in secrets.items()), encoding="utf-8")
    env_file.chmod(0o600)
    common = [*hardening(data), "-v", f"{config_path}:/config/config.yaml:ro"]
    common += ["--env-file", str(env_file)]

    # Step 4 of deploy/README.md: fit the models into the data volume, inside the image.
    write_training_data(runs / "vmc-1.csv", seed=1)
    for extra in (["--regime-column", "regime"], []):
        fit = podman(
            "run", "--rm", *common, "-v", f"{runs}:/runs:ro", image,
            "fit", "/runs/vmc-1.csv", "--method", "mlr", *extra,
            "--store", "/data/models/vmc-1",
            timeout_s=600,
        )  # fmt: skip
        assert "mlr-error_um" in fit.stdout, fit.stdout
    check = podman("run", "--rm", *common, image, "check-config", "--config", "/config/config.yaml")
    assert "ok" in check.stdout, check.stdout + check.stderr

    name = f"spindle-gateway-test-{uuid.uuid4().hex[:8]}"
    podman("create", "--name", name, *common, image)
    try:
        # What podman itself puts in the container's layer before the gateway starts
        # (mount points for /etc/hosts, /etc/resolv.conf, …): the baseline of the diff.
        podman("init", name)
        baseline = set(podman("diff", name).stdout.splitlines())
        started = time.monotonic()
        podman("start", name)
        # Healthy by the image's own HEALTHCHECK command, within 60 s of the start.
        healthy = None
        while time.monotonic() - started < HEALTHY_WITHIN_S:
            probe = podman("healthcheck", "run", name, check=False, timeout_s=30)
            if probe.returncode == 0:
                healthy = time.monotonic() - started
                break
            time.sleep(1.0)
        logs = podman("logs", name, check=False).stderr
        assert healthy is not None, f"not healthy within {HEALTHY_WITHIN_S} s: {logs[-3000:]}"
        print(f"healthy {healthy:.1f} s after the start", file=sys.stderr)

        # Points reach InfluxDB with their tags and wall-clock timestamps.
        reader = InfluxReader(influx.url, influx.token, influx.org, bench["bucket"])
        try:
            deadline = time.monotonic() + 30
            cycles: list = []
            while time.monotonic() < deadline and len(cycles) < 5:
                time.sleep(1.0)
                cycles = reader.query("spindle_cycle", "vmc-1")
            temperatures = reader.query("spindle_temperature", "vmc-1")
        finally:
            reader.close()
        assert len(cycles) >= 5, podman("logs", name, check=False).stderr[-3000:]
        # Less than window_s of speed history: "variable", whose model serves once the
        # sensors are trusted (the first cycles carry no model).
        assert {p.tags.get("regime") for p in cycles} == {"variable"}
        assert cycles[-1].tags["model_id"] == "mlr-error_um-variable", cycles[-1]
        assert all(p.fields["speed_rpm"] > 0 for p in cycles[-3:])
        assert {p.tags["sensor"] for p in temperatures} == {f"T{i}" for i in range(1, 10)}
        assert abs(cycles[-1].time_ns - time.time_ns()) < 60e9, "stamped with the wall clock"

        # The SCADA server answers node-opcua: refused until its certificate is trusted
        # (the README's mv), then it reads the live values over SignAndEncrypt.
        endpoint = f"opc.tcp://127.0.0.1:{scada_port}/scada"
        pki = tmp_path / "node-pki"
        password = secrets["SCADA_OPCUA_VIEWER_PASSWORD"]
        reads = [{"read": "vmc-1.Health.Cycles"}, {"read": "vmc-1.ModelId"}]
        code, reply = node_read(endpoint, pki, reads, password)
        assert code == 1 and reply["status"] == "BadCertificateUntrusted", reply
        rejected = podman("exec", name, "ls", "/data/pki/rejected").stdout.split()
        assert len(rejected) == 1, rejected
        podman("exec", name, "mv", f"/data/pki/rejected/{rejected[0]}", "/data/pki/trusted/")
        code, reply = node_read(endpoint, pki, reads, password)
        assert code == 0, reply
        cycles_read, model_read = reply["results"]
        assert cycles_read["status"] == "Good" and cycles_read["value"] >= 5, reply
        assert model_read["value"] == "mlr-error_um-variable", reply

        # Nothing was written outside the volumes: the container's own layer is unchanged.
        changed = set(podman("diff", name).stdout.splitlines()) - baseline
        outside = [c for c in changed if not c.split()[-1].startswith(("/data", "/tmp"))]
        assert outside == [], outside

        # SIGTERM (podman stop, as docker compose stop): ends within the grace period,
        # exit status 0, with its state saved and the buffer forwarded.
        stop_started = time.monotonic()
        podman("stop", "-t", str(GRACE_S), name, timeout_s=GRACE_S + 30)
        stop_s = time.monotonic() - stop_started
        inspect = json.loads(podman("inspect", name).stdout)[0]["State"]
        logs = podman("logs", name).stdout
        assert stop_s < GRACE_S, f"stop took {stop_s:.1f} s"
        assert inspect["ExitCode"] == 0, inspect
        assert "stopped" in logs, logs[-2000:]
        print(f"stopped {stop_s:.1f} s after SIGTERM", file=sys.stderr)
    finally:
        podman("rm", "-f", name, check=False)

    # Every path written is under /data (the volume) and owned by the gateway's uid.
    written = sorted(str(p.relative_to(data)) for p in data.rglob("*"))
    assert {"state/vmc-1-reference.json", "state/vmc-1-heartbeat.json"} <= set(written)
    assert "log/buffer.sqlite" in written and "pki/server_cert.der" in written
    assert any(p.startswith("models/vmc-1/mlr-error_um-variable") for p in written)
    assert all((data / p).stat().st_uid == UID for p in written), "written as uid 10001"
    reference = json.loads((data / "state/vmc-1-reference.json").read_text(encoding="utf-8"))
    assert reference, "the cold reference is saved"
    with contextlib.closing(sqlite3.connect(data / "log/buffer.sqlite")) as buffer:
        (left,) = buffer.execute("SELECT COUNT(*) FROM points").fetchone()
    assert left == 0, "every buffered point was forwarded before the stop"
