"""Edge deployment: Dockerfile, compose file, Grafana provisioning, container config, health.

There is no Docker engine here, so the files are checked for what Docker, compose and
Grafana would need, and the commands the image runs (its ENTRYPOINT + CMD and its
HEALTHCHECK) are run in this environment instead.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import time
import tomllib
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.config import load_config
from gateway.outputs.heartbeat import check, heartbeat_path, write_heartbeat
from tests.cli import gateway, gateway_in_process

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
COMPOSE = DEPLOY / "docker-compose.yml"
ENV_EXAMPLE = DEPLOY / ".env.example"
DATASOURCE = DEPLOY / "grafana/provisioning/datasources/influxdb.yml"
PROVIDERS = DEPLOY / "grafana/provisioning/dashboards/dashboards.yml"
DASHBOARD = DEPLOY / "grafana/dashboards/spindle-gateway.json"
CONFIG = DEPLOY / "config.docker.yaml"

# ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?err}, ${VAR?err}; "$$" is a literal "$".
VAR_REF = re.compile(r"(?<!\$)\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])[^}]*)?\}")
SECRET_KEY = re.compile(r"PASSWORD|TOKEN|SECRET|_KEY$", re.IGNORECASE)
GRAFANA_FLUX_MACROS = {"timeRangeStart", "timeRangeStop", "windowPeriod", "defaultBucket"}
GRAFANA_FLUX_MACROS |= {"organization"}


# --- helpers ----------------------------------------------------------------------------
def compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text(encoding="utf-8"))


def services() -> dict[str, Any]:
    return compose()["services"]


def environment(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


def references(path: Path) -> set[str]:
    """Variables the values of a YAML file refer to (comments do not count)."""

    def strings(node: Any) -> list[str]:
        if isinstance(node, dict):
            return [s for item in node.items() for part in item for s in strings(part)]
        if isinstance(node, list):
            return [s for item in node for s in strings(item)]
        return [node] if isinstance(node, str) else []

    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    return {m.group(1) for s in strings(doc) for m in VAR_REF.finditer(s)}


def env_example() -> dict[str, str]:
    values: dict[str, str] = {}
    for number, line in enumerate(ENV_EXAMPLE.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition("=")
        assert sep, f".env.example:{number}: not KEY=VALUE: {line!r}"
        assert key not in values, f".env.example:{number}: {key} listed twice"
        values[key] = value
    return values


def dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    instructions, pending = [], ""
    for line in (ROOT / "Dockerfile").read_text(encoding="utf-8").splitlines():
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        full = (pending + line).strip()
        pending = ""
        keyword, _, args = full.partition(" ")
        instructions.append((keyword.upper(), args.strip()))
    assert not pending, "Dockerfile ends inside a continued line"
    return instructions


def instruction(name: str) -> list[str]:
    return [args for keyword, args in dockerfile_instructions() if keyword == name]


def exec_form(args: str) -> list[str]:
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), args
    return value


def healthcheck_command() -> list[str]:
    (args,) = instruction("HEALTHCHECK")
    _, _, command = args.partition(" CMD ")
    return exec_form(command.strip())


def dashboard() -> dict[str, Any]:
    return json.loads(DASHBOARD.read_text(encoding="utf-8"))


def panel_queries(panel: dict[str, Any]) -> str:
    return "\n".join(t.get("query", "") for t in panel.get("targets", []))


# --- compose ------------------------------------------------------------------------------
def test_compose_has_the_three_services_built_and_wired() -> None:
    svc = services()
    assert set(svc) == {"gateway", "influxdb", "grafana"}
    gw = svc["gateway"]
    assert gw["build"]["context"] == ".."
    assert (DEPLOY / gw["build"]["context"] / gw["build"].get("dockerfile", "Dockerfile")).is_file()
    assert gw["restart"] == "unless-stopped"
    assert "influxdb" in gw["depends_on"]
    assert gw["command"] == ["run", "--config", "/config/config.yaml"]
    for name in ("influxdb", "grafana"):
        assert svc[name]["restart"] == "unless-stopped"


def test_compose_images_are_pinned() -> None:
    svc = services()
    version = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"][
        "version"
    ]
    assert svc["gateway"]["image"] == f"spindle-thermal-gateway:{version}"
    assert svc["influxdb"]["image"].startswith("influxdb:2.7")
    assert svc["grafana"]["image"].startswith("grafana/grafana-oss:")
    for name, service in svc.items():
        image = service["image"]
        repository, _, tag = image.rpartition(":")
        assert repository and "/" not in tag, f"{name}: image {image} has no tag"
        assert tag != "latest" and "${" not in image, f"{name}: image {image} is not pinned"
        if name != "gateway":
            assert re.fullmatch(r"\d+\.\d+(\.\d+)?", tag), f"{name}: {image}: not a version tag"


def test_compose_volumes_and_ports() -> None:
    doc = compose()
    svc = doc["services"]
    mounts = {v.split(":")[1]: v.split(":")[0] for v in svc["gateway"]["volumes"]}
    assert mounts["/data"] in doc["volumes"], "gateway /data must be a named volume"
    config_source = DEPLOY / mounts["/config/config.yaml"]
    assert config_source.resolve() == CONFIG.resolve()
    assert any(v.endswith("/config/config.yaml:ro") for v in svc["gateway"]["volumes"])

    influx = {v.split(":")[1]: v.split(":")[0] for v in svc["influxdb"]["volumes"]}
    assert influx["/var/lib/influxdb2"] in doc["volumes"]

    grafana = {v.split(":")[1]: v.split(":")[0] for v in svc["grafana"]["volumes"]}
    provisioning = DEPLOY / grafana["/etc/grafana/provisioning"]
    assert (provisioning / "datasources/influxdb.yml").resolve() == DATASOURCE.resolve()
    assert (provisioning / "dashboards/dashboards.yml").resolve() == PROVIDERS.resolve()
    assert grafana["/var/lib/grafana"] in doc["volumes"]
    assert any(p.split(":")[-2:] == ["3000", "3000"] for p in map(str, svc["grafana"]["ports"]))
    influx_ports = [str(p) for p in svc["influxdb"].get("ports", [])]
    assert all(p.startswith("127.0.0.1:") for p in influx_ports), "InfluxDB only on loopback"


def test_compose_influxdb_is_initialised_from_the_env_file() -> None:
    env = environment(services()["influxdb"])
    assert env["DOCKER_INFLUXDB_INIT_MODE"] == "setup"
    for key in ("USERNAME", "PASSWORD", "ORG", "BUCKET", "ADMIN_TOKEN"):
        assert VAR_REF.fullmatch(env[f"DOCKER_INFLUXDB_INIT_{key}"]), key


def test_compose_holds_no_secret_values() -> None:
    for name, service in services().items():
        for key, value in environment(service).items():
            if SECRET_KEY.search(key):
                match = VAR_REF.fullmatch(value)
                assert match and match.group(2) is None, (
                    f"{name}.environment.{key} must be a plain ${{VAR}} reference, got {value!r}"
                )
    text = COMPOSE.read_text(encoding="utf-8")
    assert not re.search(r"(?i)(password|token|secret)\s*[:=]\s*['\"]?[A-Za-z0-9+/]{8,}", text)
    assert "env_file" not in text, "pass each container only its own variables"


def test_every_compose_variable_is_in_env_example_without_a_value_for_secrets() -> None:
    listed = env_example()
    referenced = references(COMPOSE)
    assert referenced, "the compose file takes its settings from .env"
    assert sorted(referenced - set(listed)) == [], "referenced in compose, missing in .env.example"
    assert sorted(set(listed) - referenced) == [], "listed in .env.example, unused by compose"
    for key, value in listed.items():
        if SECRET_KEY.search(key):
            assert value == "", f".env.example must not ship a value for {key}"


def test_config_passwords_reach_the_gateway_container() -> None:
    config = load_config(CONFIG)
    env = environment(services()["gateway"])
    for machine in config.machines:
        opcua = machine.cnc.opcua
        if opcua is not None and opcua.password_env:
            assert opcua.password_env in env, f"{opcua.password_env} is not passed to gateway"


# --- Grafana -----------------------------------------------------------------------------
def test_datasource_is_influxdb_flux_with_the_token_from_the_environment() -> None:
    doc = yaml.safe_load(DATASOURCE.read_text(encoding="utf-8"))
    assert doc["apiVersion"] == 1
    (source,) = doc["datasources"]
    assert source["type"] == "influxdb"
    assert source["url"] == "http://influxdb:8086"
    assert source["jsonData"]["version"] == "Flux"
    assert source["secureJsonData"]["token"] == "${INFLUXDB_TOKEN}"
    used = references(DATASOURCE)
    assert used >= {"INFLUXDB_TOKEN", "INFLUXDB_ORG", "INFLUXDB_BUCKET"}
    grafana_env = environment(services()["grafana"])
    assert sorted(used - set(grafana_env)) == [], "datasource variables Grafana is not given"
    uids = {t["datasource"]["uid"] for p in dashboard()["panels"] for t in p["targets"]}
    assert uids == {source["uid"]}


def test_dashboard_provider_points_at_the_mounted_dashboards() -> None:
    doc = yaml.safe_load(PROVIDERS.read_text(encoding="utf-8"))
    (provider,) = doc["providers"]
    assert provider["type"] == "file"
    mounts = {v.split(":")[1]: v.split(":")[0] for v in services()["grafana"]["volumes"]}
    source = DEPLOY / mounts[provider["options"]["path"]]
    assert (source / DASHBOARD.name).resolve() == DASHBOARD.resolve()


def test_dashboard_is_valid_grafana_json() -> None:
    doc = dashboard()
    assert isinstance(doc["schemaVersion"], int) and doc["schemaVersion"] >= 36
    assert doc["uid"] and doc["title"]
    panels = doc["panels"]
    ids = [p["id"] for p in panels]
    assert len(ids) == len(set(ids)), f"duplicate panel ids {ids}"
    cells: set[tuple[int, int]] = set()
    for panel in panels:
        grid = panel["gridPos"]
        assert {"h", "w", "x", "y"} <= set(grid), panel["title"]
        assert grid["x"] >= 0 and grid["w"] > 0 and grid["x"] + grid["w"] <= 24, panel["title"]
        own = {
            (x, y)
            for x in range(grid["x"], grid["x"] + grid["w"])
            for y in range(grid["y"], grid["y"] + grid["h"])
        }
        assert not own & cells, f"panel {panel['title']} overlaps another"
        cells |= own
        assert panel["targets"], panel["title"]
        refs = [t["refId"] for t in panel["targets"]]
        assert all(refs) and len(refs) == len(set(refs)), panel["title"]


def test_dashboard_queries_are_flux_on_v_bucket_for_the_selected_machine() -> None:
    doc = dashboard()
    variables = {v["name"]: v for v in doc["templating"]["list"]}
    assert {"bucket", "machine"} <= set(variables)
    assert '"machine"' in variables["machine"]["query"]
    for panel in doc["panels"]:
        for target in panel["targets"]:
            query = target["query"]
            assert "from(bucket: v.bucket)" in query, panel["title"]
            assert 'r.machine == "${machine}"' in query, panel["title"]
            assert "range(start: v.timeRangeStart, stop: v.timeRangeStop)" in query
    # Grafana supplies only its macros as v.*; v.bucket is defined by the query itself.
    for query in [panel_queries(p) for p in doc["panels"]] + [
        v["query"] for v in variables.values()
    ]:
        used = set(re.findall(r"\bv\.([A-Za-z]+)", query))
        if "bucket" in used:
            assert 'v = {bucket: "${bucket}"}' in query
        assert used <= GRAFANA_FLUX_MACROS | {"bucket"}, used


def shows(query: str, name: str) -> bool:
    """The query reads ``name`` as a field (``r._field == "name"``) or as a tag (``r.name``)."""
    return f'r._field == "{name}"' in query or re.search(rf"\br\.{name}\b", query) is not None


@pytest.mark.parametrize(
    ("measurement", "fields", "types"),
    [
        ("spindle_temperature", ["value_C"], {"timeseries"}),
        ("spindle_cycle", ["speed_rpm"], {"timeseries"}),
        ("spindle_cycle", ["regime", "model_id"], {"state-timeline", "table"}),
        ("spindle_cycle", ["predicted_um", "applied_um"], {"timeseries"}),
        ("spindle_probe", ["error_um"], {"timeseries"}),
    ],
)
def test_dashboard_has_the_panel(measurement: str, fields: list[str], types: set[str]) -> None:
    matching = [
        p
        for p in dashboard()["panels"]
        if f'r._measurement == "{measurement}"' in panel_queries(p)
        and all(shows(panel_queries(p), f) for f in fields)
    ]
    assert len(matching) == 1, f"one panel for {measurement} {fields}"
    assert matching[0]["type"] in types


def test_temperatures_are_shown_per_sensor() -> None:
    (panel,) = [p for p in dashboard()["panels"] if "spindle_temperature" in panel_queries(p)]
    assert '"sensor"' in panel_queries(panel)
    assert panel["fieldConfig"]["defaults"]["unit"] == "celsius"


# --- Dockerfile ---------------------------------------------------------------------------
def test_dockerfile_base_user_volumes_and_commands() -> None:
    keywords = [k for k, _ in dockerfile_instructions()]
    # The base is an ARG: the slim Python image for users, a local base where no registry is.
    assert instruction("ARG")[0] == "BASE=python:3.11-slim-bookworm"
    assert instruction("FROM") == ["${BASE} AS dependencies", "${BASE}"]
    (user,) = instruction("USER")
    assert user.split(":")[0] not in {"root", "0"}
    assert keywords.index("USER") < keywords.index("ENTRYPOINT")
    assert keywords.index("USER") < keywords.index("HEALTHCHECK")
    (volume,) = instruction("VOLUME")
    assert set(exec_form(volume)) == {"/config", "/data"}
    (entrypoint,) = instruction("ENTRYPOINT")
    assert exec_form(entrypoint) == ["python", "-m", "gateway"]
    (cmd,) = instruction("CMD")
    assert exec_form(cmd) == ["run", "--config", "/config/config.yaml"]
    assert healthcheck_command() == [
        "python",
        "-m",
        "gateway.outputs.heartbeat",
        "--state-dir",
        "/data/state",
        "--max-age-s",
        "30",
    ]
    assert load_config(CONFIG).state_dir == Path("/data/state"), "health check reads state_dir"


def test_dockerfile_copies_existing_sources_that_the_context_keeps() -> None:
    ignored = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.startswith("#")
    ]
    for required in (".venv", ".cache", "tests/node/node_modules", "deploy/.env"):
        assert required in ignored, required
    assert any("__pycache__" in pattern for pattern in ignored)
    packages = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"][
        "setuptools"
    ]["packages"]["find"]["include"]
    git_ignored = (ROOT / ".gitignore").read_text(encoding="utf-8").splitlines()
    copied: set[str] = set()
    for args in instruction("COPY"):
        if "--from=" in args:  # from the build's own first stage
            continue
        parts = [p for p in shlex.split(args) if not p.startswith("--")]
        for source in parts[:-1]:
            assert source not in ignored and source.split("/")[0] not in ignored, source
            if source == "wheelhouse":  # made by scripts/build-wheelhouse.sh, not in git
                assert "/wheelhouse/" in git_ignored
                continue
            assert (ROOT / source).exists(), f"COPY {source}: not in the repository"
            copied.add(source)
    assert {p.rstrip("*") for p in packages} <= copied, "every package of pyproject is copied"


def locked(path: Path) -> dict[str, tuple[str, set[str]]]:
    """name → (version, sha256 hashes) of a pip-compile lock file."""
    packages: dict[str, tuple[str, set[str]]] = {}
    name = ""
    for line in path.read_text(encoding="utf-8").splitlines():
        if line and not line.startswith((" ", "#")):
            name, _, rest = line.partition("==")
            packages[name.lower()] = (rest.split()[0], set())
        for digest in re.findall(r"--hash=sha256:([0-9a-f]{64})", line):
            packages[name.lower()][1].add(digest)
    return packages


def test_the_lock_pins_what_pyproject_pins_with_hashes() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    runtime, dev = locked(ROOT / "requirements.lock"), locked(ROOT / "requirements-dev.lock")
    for pins, lock in (
        (project["dependencies"], runtime),
        (project["optional-dependencies"]["dev"], dev),
    ):
        for pin in pins:
            name, _, version = pin.partition("==")
            assert lock[name.lower()][0] == version, pin
    assert all(hashes for _, hashes in runtime.values()), "every locked package has hashes"
    # make install (the dev lock) and the image (the runtime lock): the same versions.
    for name, (version, _) in runtime.items():
        assert dev[name][0] == version, name


def test_image_and_make_install_the_lock_with_hashes_and_no_index() -> None:
    installs = [r for r in instruction("RUN") if "pip install" in r]
    assert any(
        "--require-hashes" in r and "-r /tmp/requirements.lock" in r and "--no-index" in r
        for r in installs
    ), installs
    assert all("--no-index" in r and "--find-links /tmp/wheelhouse" in r for r in installs)
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert "--require-hashes -r requirements-dev.lock" in makefile
    assert "--no-deps -e ." in makefile


# --- the container's commands, run here ---------------------------------------------------
def test_entrypoint_runs_and_cmd_is_a_known_command() -> None:
    (entrypoint,) = instruction("ENTRYPOINT")
    (cmd,) = instruction("CMD")
    assert exec_form(entrypoint)[:2] == ["python", "-m"]
    result = gateway("--help")
    assert result.returncode == 0, result.stderr
    command = exec_form(cmd)
    assert command[0] in result.stdout
    help_run = gateway(command[0], "--help")
    assert help_run.returncode == 0, help_run.stderr
    assert "--config" in help_run.stdout


def run_healthcheck(state_dir: Path) -> subprocess.CompletedProcess[str]:
    """The image's HEALTHCHECK command, with /data/state replaced by ``state_dir``."""
    command = healthcheck_command()
    assert command[0] == "python"
    command = [sys.executable, *command[1:]]
    command[command.index("/data/state")] = str(state_dir)
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_healthcheck_passes_on_a_fresh_heartbeat(tmp_path: Path) -> None:
    write_heartbeat(tmp_path, "vmc-1", 120.0, cycles=120)
    write_heartbeat(tmp_path, "vmc-2", 118.0, cycles=118)
    result = run_healthcheck(tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("healthy:")
    assert "vmc-1" in result.stdout and "vmc-2" in result.stdout


def test_healthcheck_fails_on_a_stale_heartbeat_and_names_the_machine(tmp_path: Path) -> None:
    write_heartbeat(tmp_path, "vmc-1", 120.0, cycles=120)
    write_heartbeat(tmp_path, "lathe-3", 80.0, cycles=80, wall_time=time.time() - 95.0)
    result = run_healthcheck(tmp_path)
    assert result.returncode == 1
    assert "unhealthy" in result.stderr and "machine lathe-3" in result.stderr
    assert "vmc-1" not in result.stderr
    assert "max 30 s" in result.stderr


def test_healthcheck_fails_with_no_heartbeat_or_no_state_dir(tmp_path: Path) -> None:
    empty = run_healthcheck(tmp_path)
    assert empty.returncode == 1 and "no heartbeat" in empty.stderr
    missing = run_healthcheck(tmp_path / "absent")
    assert missing.returncode == 1 and "absent" in missing.stderr


def test_health_usage_error_is_unhealthy_not_docker_reserved_status_2(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "gateway.outputs.heartbeat", "--state-dir", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    assert "--max-age-s" in result.stderr


def test_heartbeat_file_is_small_json_written_atomically(tmp_path: Path) -> None:
    path = write_heartbeat(tmp_path / "state", "vmc-1", 42.5, cycles=7, wall_time=1000.0)
    assert path == heartbeat_path(tmp_path / "state", "vmc-1")
    assert json.loads(path.read_text(encoding="utf-8")) == {
        "machine": "vmc-1",
        "wall_time": 1000.0,
        "time_s": 42.5,
        "cycles": 7,
    }
    write_heartbeat(tmp_path / "state", "vmc-1", 43.5, cycles=8, wall_time=1001.0)
    assert [p.name for p in (tmp_path / "state").iterdir()] == ["vmc-1-heartbeat.json"]
    with pytest.raises(ValueError, match="plain name"):
        write_heartbeat(tmp_path, "../escape", 0.0)


def test_check_ages_and_unreadable_files(tmp_path: Path) -> None:
    write_heartbeat(tmp_path, "vmc-1", 0.0, wall_time=1000.0)
    (tmp_path / "vmc-1-reference.json").write_text("{}", encoding="utf-8")  # not a heartbeat
    assert check(tmp_path, 30, now=1029.0) == (True, "healthy: vmc-1 29.0 s ago")
    healthy, message = check(tmp_path, 30, now=1031.0)
    assert not healthy and "machine vmc-1: last heartbeat 31.0 s ago" in message
    (tmp_path / "vmc-2-heartbeat.json").write_text("{not json", encoding="utf-8")
    healthy, message = check(tmp_path, 30, now=1001.0)
    assert not healthy and "machine vmc-2: unreadable heartbeat" in message


# --- the container's configuration ----------------------------------------------------------
def under_data(path: Path) -> bool:
    return path.is_absolute() and path.parts[:2] == ("/", "data")


def test_docker_config_validates_and_keeps_everything_under_data() -> None:
    config = load_config(CONFIG)
    assert config.state_dir == Path("/data/state")
    logging = config.logging
    assert config.scada is not None
    writable = [config.state_dir, logging.local_store, logging.buffer_path, config.scada.pki_dir]
    for machine in config.machines:
        store = machine.models.store
        assert store.parts[:3] == ("/", "data", "models"), store
        writable.append(store)
        assert machine.cnc.opcua is None or machine.cnc.opcua.password_env
    assert [p for p in writable if not under_data(p)] == []
    assert config.simulator is None


def test_docker_config_logs_to_influxdb_with_every_setting_from_compose() -> None:
    influx = load_config(CONFIG).logging.influxdb
    assert influx is not None, "the container logs to the compose InfluxDB"
    env = environment(services()["gateway"])
    variables = {
        "url_env": influx.url_env,
        "org_env": influx.org_env,
        "bucket_env": influx.bucket_env,
        "token_env": influx.token_env,
    }
    assert all(variables.values()), variables
    assert sorted(v for v in variables.values() if v not in env) == []
    assert env[influx.url_env] == "http://influxdb:8086"
    influx_env = environment(services()["influxdb"])
    assert env[influx.bucket_env] == influx_env["DOCKER_INFLUXDB_INIT_BUCKET"]
    assert env[influx.org_env] == influx_env["DOCKER_INFLUXDB_INIT_ORG"]


def test_docker_config_serves_scada_on_the_published_port() -> None:
    scada = load_config(CONFIG).scada
    assert scada is not None
    assert (scada.host, scada.port) == ("0.0.0.0", 4840)
    published = [str(p).split(":")[-1] for p in services()["gateway"]["ports"]]
    assert str(scada.port) in published
    env = environment(services()["gateway"])
    assert {u.role for u in scada.users} == {"operator", "viewer"}
    for user in scada.users:
        assert user.password_env in env, f"{user.password_env} is not passed to gateway"


def test_influx_settings_come_from_the_environment(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "config.yaml"
    doc = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    influx = load_config(path).logging.influxdb
    assert influx is not None
    for name, value in {
        "INFLUXDB_URL": "http://127.0.0.1:8086",
        "INFLUXDB_ORG": "workshop",
        "INFLUXDB_BUCKET": "spindle",
        "INFLUXDB_TOKEN": "s3cret",
    }.items():
        monkeypatch.setenv(name, value)
    assert (influx.url_value(), influx.org_value(), influx.bucket_value(), influx.token()) == (
        "http://127.0.0.1:8086",
        "workshop",
        "spindle",
        "s3cret",
    )
    monkeypatch.delenv("INFLUXDB_BUCKET")
    with pytest.raises(ValueError, match="INFLUXDB_BUCKET \\(bucket_env\\) is not set"):
        influx.bucket_value()
    # A literal and its variable together, or neither: refused with file, line and key.
    doc["logging"]["influxdb"]["url"] = "http://127.0.0.1:8086"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    result = gateway_in_process("check-config", "--config", path)
    assert result.returncode == 2, result.stderr
    assert "logging.influxdb: give 'url' or 'url_env', not both" in result.stderr
    assert re.search(r"config\.yaml:\d+: logging\.influxdb", result.stderr), result.stderr
    del doc["logging"]["influxdb"]["url"], doc["logging"]["influxdb"]["url_env"]
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    result = gateway_in_process("check-config", "--config", path)
    assert result.returncode == 2 and "give 'url' or 'url_env'" in result.stderr


# --- the dashboard's Flux against a real InfluxDB (1.8.10, Flux and the v2 API) --------------
def grafana_interpolate(query: str, bucket: str, start: str, stop: str) -> str:
    """What Grafana sends: dashboard variables, then its v.* macros replaced as text."""
    for name, value in {
        "${bucket}": bucket,
        "${machine}": "vmc-1",
        "v.timeRangeStart": start,
        "v.timeRangeStop": stop,
        "v.windowPeriod": "10s",
    }.items():
        query = query.replace(name, value)
    return query


def test_dashboard_queries_run_on_influxdb(tmp_path: Path) -> None:
    from influxdb_client import InfluxDBClient
    from influxdb_client.client.write_api import SYNCHRONOUS

    from tests.influx_server import ORG, TOKEN, InfluxServer

    t0 = (int(time.time()) // 60 - 10) * 60  # s, ten minutes ago on a whole minute
    lines = []
    for i in range(60):  # a minute of cycles, the regime switching half-way
        ns = (t0 + i) * 1_000_000_000
        regime = "variable" if i < 30 else "constant"
        lines.append(
            f"spindle_cycle,machine=vmc-1,model_id=mlr-error_um-{regime},regime={regime} "
            f"speed_rpm={3000.0 + i},predicted_um={0.1 * i},applied_um={0.09 * i},"
            f'write_status="ok",link_errors=0i {ns}'
        )
        for sensor, base in (("T1", 20.0), ("T7", 22.0)):
            quality = "good" if i != 5 else "suspect"
            lines.append(
                f"spindle_temperature,machine=vmc-1,quality={quality},sensor={sensor} "
                f"value_C={base + 0.01 * i} {ns}"
            )
    lines.append(f"spindle_probe,machine=vmc-1 error_um=1.5 {(t0 + 45) * 1_000_000_000}")
    lines.append(f"spindle_cycle,machine=lathe-2 speed_rpm=1.0,link_errors=0i {t0 * 10**9}")

    with InfluxServer(tmp_path) as server:
        bucket = server.create_database("spindle")
        client = InfluxDBClient(url=server.url, token=TOKEN, org=ORG)
        try:
            client.write_api(write_options=SYNCHRONOUS).write(bucket=bucket, record=lines)
            start, stop = (
                datetime.fromtimestamp(t0 + offset_s, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
                for offset_s in (-600, 600)
            )
            doc = dashboard()
            results: dict[str, list[tuple[dict[str, Any], list[Any]]]] = {}
            for panel in doc["panels"]:
                for target in panel["targets"]:
                    query = grafana_interpolate(target["query"], f"{bucket}", start, stop)
                    tables = client.query_api().query(query)
                    results[panel["title"]] = [
                        (
                            {
                                k: v
                                for k, v in t.records[0].values.items()
                                if k in ("sensor", "_field")
                            },
                            [r.get_value() for r in t.records],
                        )
                        for t in tables
                    ]
            (variable,) = [v for v in doc["templating"]["list"] if v["name"] == "machine"]
            machines = client.query_api().query(
                grafana_interpolate(variable["query"], bucket, start, stop)
            )
            assert sorted(r.get_value() for t in machines for r in t.records) == [
                "lathe-2",
                "vmc-1",
            ]
        finally:
            client.close()

    temperatures = results["Temperatures"]
    assert sorted(labels["sensor"] for labels, _ in temperatures) == ["T1", "T7"]
    assert all(len(values) == 6 for _, values in temperatures), "one series per sensor"
    (speed,) = results["Spindle speed"]
    assert len(speed[1]) == 6 and speed[1][0] == pytest.approx(3004.5)
    states = {labels["_field"]: values for labels, values in results["Regime and model"]}
    assert states["regime"] == ["variable"] * 3 + ["constant"] * 3
    assert states["model"][-1] == "mlr-error_um-constant"
    compensation = {
        labels["_field"]: values
        for labels, values in results["Predicted error vs compensation applied"]
    }
    assert set(compensation) == {"predicted_um", "applied_um"}
    assert all(len(v) == 6 for v in compensation.values())
    assert results["Probe residual"] == [({"_field": "error_um"}, [1.5])]
