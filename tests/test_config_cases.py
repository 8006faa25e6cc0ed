"""Bad configurations, one per file, each refused by ``check-config`` with one located line.

``tests/cases/config/NAME.yaml`` is a configuration (mostly ``config.yaml`` with
one mutation); ``NAME.expected`` is the one line ``check-config`` must print on
stderr, exit status 2. To add a case, add the pair; this test walks the folder.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from drivers.yaml_loader import MAX_BYTES, YamlError, load_yaml
from tests.cli import ROOT, gateway, gateway_in_process

CASES = ROOT / "tests" / "cases" / "config"
NAMES = sorted(p.stem for p in CASES.glob("*.yaml"))


def test_every_case_has_its_expected_message() -> None:
    expected = sorted(p.stem for p in CASES.glob("*.expected"))
    assert expected == NAMES
    assert len(NAMES) >= 50


@pytest.mark.parametrize("name", NAMES)
def test_bad_config_is_refused_with_one_located_line(name: str) -> None:
    case = CASES.relative_to(ROOT) / f"{name}.yaml"
    expected = (CASES / f"{name}.expected").read_text(encoding="utf-8").rstrip("\n")
    # The first case as a real process; the table in this process (tests/cli.py).
    run = gateway if name == NAMES[0] else gateway_in_process
    result = run("check-config", "--config", case)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines() == [expected]
    assert "Traceback" not in result.stdout + result.stderr
    # The line names the file, and (but for a folder) the line; a key path when there is one.
    assert re.match(rf"error: {re.escape(str(case))}(:\d+)?: \S", expected)


def test_the_shipped_configs_still_load() -> None:
    from gateway.config import load_config
    from simulator.serve import load_simulator_config

    assert load_config(ROOT / "config.yaml", check_host=True).machines[0].id == "vmc-1"
    assert load_config(ROOT / "deploy" / "config.docker.yaml").machines[0].id == "vmc-1"
    assert load_simulator_config(ROOT / "config.yaml").cnc.opcua is not None


def test_alias_bomb_is_refused_fast() -> None:
    started = time.perf_counter()
    with pytest.raises(YamlError, match="more than 100 YAML aliases"):
        load_yaml(CASES / "alias-bomb.yaml")
    assert time.perf_counter() - started < 2.0


def test_aliases_that_grow_without_many_of_them_are_refused_fast(tmp_path: Path) -> None:
    # 90 aliases only, but 9**10 values once expanded: the value budget stops it.
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 11)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    started = time.perf_counter()
    with pytest.raises(YamlError, match="aliases expand to more than 100000 values"):
        load_yaml(path)
    assert time.perf_counter() - started < 2.0


def test_a_file_over_the_size_limit_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "huge.yaml"
    path.write_text("# padding\n" * (MAX_BYTES // 10 + 1), encoding="utf-8")
    with pytest.raises(YamlError, match=f"at most {MAX_BYTES} bytes"):
        load_yaml(path)


def test_merge_keys_may_override_and_aliases_keep_their_lines(tmp_path: Path) -> None:
    path = tmp_path / "ok.yaml"
    path.write_text("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n", encoding="utf-8")
    document = load_yaml(path)
    assert document.data == {"base": {"x": 1, "y": 2}, "c": {"x": 3, "y": 2}}
    assert document.lines[("c", "x")] == 4
    assert document.locate(("c", "x")) == f"{path}:4: c.x"


def test_a_default_stale_s_follows_a_long_cycle(tmp_path: Path) -> None:
    """A sensor without its own stale_s is not made stale by one missed read either."""
    from gateway.config import load_config

    text = (ROOT / "config.yaml").read_text(encoding="utf-8")
    path = tmp_path / "slow.yaml"
    path.write_text(text.replace("cycle_s: 1.0 ", "cycle_s: 30.0"), encoding="utf-8")
    limits = load_config(path).machines[0].quality_limits()
    assert limits["T2"].stale_s == 60.0
    assert load_config(ROOT / "config.yaml").machines[0].quality_limits()["T2"].stale_s == 10.0


@pytest.mark.parametrize(
    "name", ["password-env-unset", "sparkplug-password-env-unset", "web-user-password-file-missing"]
)
def test_run_refuses_what_check_config_refuses_with_the_same_line(name: str) -> None:
    case = CASES.relative_to(ROOT) / f"{name}.yaml"
    expected = (CASES / f"{name}.expected").read_text(encoding="utf-8").rstrip("\n")
    result = gateway("run", "--config", case, timeout_s=120)
    assert result.returncode == 2
    assert result.stderr.splitlines() == [expected]


@pytest.mark.parametrize(
    ("name", "key"),
    [
        ("sparkplug-password-env-unset", "sparkplug.password_env"),
        ("web-user-password-env-unset", "web.users[0].password_env"),
        ("password-env-unset", "machines[0].cnc.opcua.password_env"),
    ],
)
def test_a_password_env_set_but_empty_is_refused(
    name: str, key: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SPINDLE_GATEWAY_CASE_UNSET_PASSWORD", "")
    case = CASES.relative_to(ROOT) / f"{name}.yaml"
    result = gateway_in_process("check-config", "--config", case)
    assert result.returncode == 2, result.stdout
    assert re.fullmatch(
        rf"error: {re.escape(str(case))}:\d+: {re.escape(key)}: environment variable "
        r"SPINDLE_GATEWAY_CASE_UNSET_PASSWORD \(password_env\) is empty\n",
        result.stderr,
    ), result.stderr


def refused(load: Callable[[Path], object], path: Path, text: str, message: str) -> None:
    """``text`` written to ``path`` is refused by ``load`` with the message ``path:message``
    (a regular expression: line, field, what was expected)."""
    path.write_text(text, encoding="utf-8")
    with pytest.raises(YamlError, match=rf"^{re.escape(str(path))}:{message}"):
        load(path)


def test_programmes_file_is_read_by_the_same_loader(tmp_path: Path) -> None:
    from simulator.programs import load_programs

    path = tmp_path / "programs.yaml"
    twice = "programs:\n  warm: [[[10, 2000]]]\n  warm: [[[20, 4000]]]\n"
    refused(load_programs, path, twice, "3: programs.warm: key given")
    negative = "programs:\n  warm: [[[10, 2000]]]\n  cold: [[[-5, 0]]]\n"
    refused(load_programs, path, negative, "3: programs.cold: .*positive")
    assert set(load_programs()) >= {"iso230-spectrum", "const4000"}


def test_machine_parameters_file_is_read_by_the_same_loader(tmp_path: Path) -> None:
    from simulator.params import load_params_file

    path = tmp_path / "params.yaml"
    infinite = "sensor_noise_C: 0.05\nsensors:\n  T1: {lag_s: .inf}\n"
    refused(load_params_file, path, infinite, "3: sensors.T1.lag_s: .inf is")
    refused(
        load_params_file, path, "sensors:\n  T1:\n    lag_s: -1\n", "3: sensors.T1.lag_s: Input"
    )
    path.write_text("sensor_noise_C: 0.05\n", encoding="utf-8")
    assert load_params_file(path).sensor_noise_C == 0.05
