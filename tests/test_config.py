"""Configuration: a good file loads; each bad one is refused with file, line and key path."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from gateway.config import ConfigError, load_config
from tests.cli import gateway, gateway_in_process
from tests.ports import free_tcp_port
from tests.synthetic import write_runs_csv

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A store with an MLR model on T1–T7 (the synthetic sensors)."""
    folder = tmp_path_factory.mktemp("store")
    data = write_runs_csv(folder / "runs.csv")
    result = gateway_in_process("fit", data, "--method", "mlr", "--store", folder / "models")
    assert result.returncode == 0, result.stderr
    return folder / "models"


GOOD = """\
machines:
  - id: vmc-1
    cycle_s: 1.0
    transmitters:
      - name: bus1
        tcp: {host: 127.0.0.1, port: PORT}
        devices:
          - {device_id: 1, channels: [T1, T2, T3, T4, T5, T6, T7]}
    sensors:
      T1: {location: front bearing, max_C: 90}
    cnc:
      opcua: {endpoint: "opc.tcp://127.0.0.1:CNCPORT/cnc"}
    compensation:
      macro: 500
      clamp_um: 40
    models:
      store: STORE
      regimes:
        models: {variable: mlr-error_um-all}
        fallback_model: mlr-error_um-all
"""


def write_config(tmp_path: Path, store: Path, text: str = GOOD) -> Path:
    path = tmp_path / "config.yaml"
    text = text.replace("STORE", str(store)).replace("CNCPORT", str(free_tcp_port()))
    path.write_text(text.replace("PORT", str(free_tcp_port())), encoding="utf-8")
    return path


def refusal(path: Path) -> str:
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    return str(caught.value)


def test_good_config_loads_and_checks(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store)
    config = load_config(path)
    machine = config.machines[0]
    assert machine.sensor_names == [f"T{i}" for i in range(1, 8)]
    assert machine.compensation.limits().clamp_um == 40.0
    assert machine.quality_limits()["T1"].max_C == 90.0
    result = gateway("check-config", "--config", path)
    assert result.returncode == 0, result.stderr
    assert "machine vmc-1: 7 sensors, 1 models" in result.stdout


def test_missing_key_names_the_line_and_path(tmp_path: Path, store: Path) -> None:
    path = write_config(
        tmp_path,
        store,
        GOOD.replace('    cnc:\n      opcua: {endpoint: "opc.tcp://127.0.0.1:CNCPORT/cnc"}\n', ""),
    )
    message = refusal(path)
    assert message == f"{path}:2: machines[0].cnc: required key is missing"


def test_wrong_type(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store, GOOD.replace("cycle_s: 1.0", "cycle_s: fast"))
    message = refusal(path)
    assert message.startswith(f"{path}:3: machines[0].cycle_s:")
    assert "number" in message


def test_clamp_of_zero(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store, GOOD.replace("clamp_um: 40", "clamp_um: 0"))
    assert (
        refusal(path)
        == f"{path}:15: machines[0].compensation.clamp_um: Input should be greater than 0"
    )


def test_unknown_key(tmp_path: Path, store: Path) -> None:
    path = write_config(
        tmp_path, store, GOOD.replace("clamp_um: 40", "clamp_um: 40\n      clamp_mm: 0.04")
    )
    assert refusal(path) == (
        f"{path}:16: machines[0].compensation.clamp_mm: unknown key (not part of the configuration)"
    )


def test_password_in_the_file_is_refused(tmp_path: Path, store: Path) -> None:
    bad = GOOD.replace(
        'opcua: {endpoint: "opc.tcp://127.0.0.1:CNCPORT/cnc"}',
        'opcua: {endpoint: "opc.tcp://127.0.0.1:CNCPORT/cnc", password: hunter2}',
    )
    message = refusal(write_config(tmp_path, store, bad))
    assert "machines[0].cnc.opcua.password: unknown key" in message


def test_unknown_sensor_in_a_model(tmp_path: Path, store: Path) -> None:
    # The stored model needs T7, but no channel provides it.
    path = write_config(tmp_path, store, GOOD.replace("T6, T7]", "T6]"))
    result = gateway_in_process("check-config", "--config", path)
    assert result.returncode == 2
    assert (
        "model 'mlr-error_um-all' needs sensor(s) ['T7'] that no transmitter channel provides"
        in result.stderr
    )


def test_regime_naming_a_model_not_in_the_store(tmp_path: Path, store: Path) -> None:
    path = write_config(
        tmp_path,
        store,
        GOOD.replace("variable: mlr-error_um-all", "variable: mlr-error_um-spectrum"),
    )
    result = gateway_in_process("check-config", "--config", path)
    assert result.returncode == 2
    assert "regime 'variable' names model 'mlr-error_um-spectrum', which is not in" in result.stderr


def test_unreachable_endpoint(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store)
    result = gateway_in_process("check-config", "--config", path, "--connect")
    assert result.returncode == 2
    assert "machine vmc-1: CNC unreachable" in result.stderr
    assert "opc.tcp://127.0.0.1:" in result.stderr
    assert "bus1 (TCP 127.0.0.1:" in result.stderr and "cannot connect" in result.stderr
    assert result.stderr.count("\n") == 1  # one clear line, no library noise


def test_not_yaml(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text("machines:\n  - id: [unclosed\n")
    assert refusal(path).startswith(f"{path}:")
    assert "not valid YAML" in refusal(path)


def test_the_shipped_config_has_a_valid_simulator_section() -> None:
    from simulator.serve import load_simulator_config

    config = load_simulator_config(ROOT / "config.yaml")
    assert config.cnc.opcua is not None and config.transmitters.tcp is not None
    raw = yaml.safe_load((ROOT / "config.yaml").read_text())
    assert "machines" in raw


def test_the_old_key_quality_still_configures_plausibility_with_one_deprecation_line(
    tmp_path: Path, store: Path
) -> None:
    old = GOOD + "    quality: {plausibility_sigma: 6}\n"
    path = write_config(tmp_path, store, old)
    line = old.splitlines().index("    quality: {plausibility_sigma: 6}") + 1
    config = load_config(path)
    assert config.machines[0].plausibility.limits().sigma == 6.0
    notice = (
        f"{path}:{line}: machines[0].quality: deprecated key name; rename it to "
        "'plausibility' (machines[].plausibility), same settings"
    )
    assert config.deprecations == [notice]
    result = gateway_in_process("check-config", "--config", path)
    assert result.returncode == 0, result.stderr
    assert [ln for ln in result.stderr.splitlines() if "deprecated" in ln] == [f"warning: {notice}"]
    # A bad value under the old name is still located on its line.
    path.write_text(path.read_text().replace("plausibility_sigma: 6", "plausibility_sigma: 0"))
    assert refusal(path).startswith(f"{path}:{line}: machines[0].plausibility.plausibility_sigma")


def test_the_new_key_plausibility_loads_without_a_deprecation(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store, GOOD + "    plausibility: {plausibility_sigma: 6}\n")
    config = load_config(path)
    assert config.machines[0].plausibility.limits().sigma == 6.0
    assert config.deprecations == []


def test_run_logs_the_deprecation_line_of_the_old_key(tmp_path: Path, store: Path) -> None:
    """``run`` logs the same line as ``check-config``; the state folder is held by this
    test, so the run stops right after reading its configuration."""
    from gateway.process.instance_lock import hold_state_dir

    state_dir = tmp_path / "state"
    old = f"state_dir: {state_dir}\n" + GOOD + "    quality: {plausibility_sigma: 6}\n"
    path = write_config(tmp_path, store, old)
    line = old.splitlines().index("    quality: {plausibility_sigma: 6}") + 1
    with hold_state_dir(state_dir):
        result = gateway("run", "--config", path, timeout_s=60)
    assert result.returncode != 0 and "another gateway" in result.stderr, result.stderr
    logged = [ln for ln in result.stderr.splitlines() if "deprecated key name" in ln]
    assert len(logged) == 1, result.stderr
    assert f"{path}:{line}: machines[0].quality" in logged[0] and "'plausibility'" in logged[0]
