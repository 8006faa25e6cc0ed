"""``compensation.axes``: a multi-axis machine's configuration, checked against its store.

The single-axis form is one axis named Z; a file with ``axes`` reads each axis's
write keys and models from its own section. The refusals that need no store are
cases of ``tests/cases/config/`` (``axes-*``); those that need the store's models
(what each axis's models predict) are here, through ``check-config``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.config import load_config
from tests.axes_rig import axes_store
from tests.cli import gateway, gateway_in_process
from tests.ports import free_tcp_port

GOOD = """\
machines:
  - id: vmc-3
    transmitters:
      - name: bus1
        tcp: {host: 127.0.0.1, port: PORT}
        devices:
          - {device_id: 1, channels: [T1, T2, T3, T4, T5, T6, T7]}
    cnc:
      opcua: {endpoint: "opc.tcp://127.0.0.1:CNCPORT/cnc"}
    compensation:
      handshake_macro: 510
      alive_macro: 511
      axes:
        Z:
          macro: 500
          target: z_um
          clamp_um: 40
          slew_um_per_min: 20
          models: {variable: mlr-z_um-all}
          fallback_model: mlr-z_um-all
        X:
          macro: 502
          unit: um
          sign: -1
          clamp_um: 30
          slew_um_per_min: 12
          deadband_um: 0.2
          hold_on_loss_s: 30
          fallback_model: mlr-x_um-all
        Y:
          macro: 503
          fallback_model: mlr-y_um-all
    models:
      store: STORE
      regimes: {window_s: 1200}
"""


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return axes_store(tmp_path_factory.mktemp("axes-store"))


def write_config(tmp_path: Path, store: Path, text: str = GOOD) -> Path:
    path = tmp_path / "config.yaml"
    text = text.replace("STORE", str(store)).replace("CNCPORT", str(free_tcp_port()))
    path.write_text(text.replace("PORT", str(free_tcp_port())), encoding="utf-8")
    return path


def test_a_multi_axis_machine_loads_and_checks(tmp_path: Path, store: Path) -> None:
    path = write_config(tmp_path, store)
    machine = load_config(path).machines[0]
    axes = machine.axis_sections()
    assert list(axes) == ["Z", "X", "Y"]  # the configured order: the order of writes
    assert [a.macro for a in axes.values()] == [500, 502, 503]
    assert axes["X"].limits().clamp_um == 30.0 and axes["X"].unit == "um"
    assert axes["X"].sign == -1 and axes["X"].hold_on_loss_s == 30.0
    assert axes["Y"].clamp_um == 50.0  # a key left out: today's default
    # The section's own per-axis fields read the first axis's (a single-axis reader's view).
    assert machine.compensation.macro == 500 and machine.compensation.clamp_um == 40.0
    assert machine.written_macros() == {
        "axes.Z.macro": 500,
        "axes.X.macro": 502,
        "axes.Y.macro": 503,
        "handshake_macro": 510,
        "alive_macro": 511,
    }
    result = gateway("check-config", "--config", path)
    assert result.returncode == 0, result.stderr
    assert "machine vmc-3: 7 sensors, 3 models" in result.stdout
    assert (
        "compensation of axes Z z_um → #500 (mm), X x_um → #502 (um), Y y_um → #503 (mm)"
        in result.stdout
    )


def test_the_single_axis_form_is_one_axis_named_z(tmp_path: Path, store: Path) -> None:
    single = GOOD.split("      axes:")[0] + (
        "      macro: 505\n      clamp_um: 25\n    models:\n      store: STORE\n"
        "      regimes: {fallback_model: mlr-z_um-all}\n"
    )
    machine = load_config(write_config(tmp_path, store, single)).machines[0]
    assert machine.compensation.axes is None
    (name, axis), *others = machine.axis_sections().items()
    assert (name, axis.macro, axis.clamp_um, axis.fallback_model) == (
        "Z",
        505,
        25.0,
        "mlr-z_um-all",
    )
    assert not others
    assert machine.written_macros() == {"macro": 505, "handshake_macro": 510, "alive_macro": 511}


X_AXIS = """\
        X:
          macro: 502
          unit: um
          sign: -1
          clamp_um: 30
          slew_um_per_min: 12
          deadband_um: 0.2
          hold_on_loss_s: 30
          fallback_model: mlr-x_um-all
"""
Y_AXIS = "        Y:\n          macro: 503\n          fallback_model: mlr-y_um-all\n"


def refused_at(tmp_path: Path, store: Path, text: str, needle: str) -> str:
    """check-config's one line refusing ``text``, which must name the line of ``needle``."""
    path = write_config(tmp_path, store, text)
    result = gateway_in_process("check-config", "--config", path)
    assert result.returncode == 2, result.stdout
    assert len(result.stderr.splitlines()) == 1, result.stderr
    line = text.splitlines().index(needle) + 1
    assert result.stderr.startswith(f"error: {path}:{line}: "), (line, result.stderr)
    return result.stderr


def test_an_axis_whose_model_predicts_another_target_is_refused(
    tmp_path: Path, store: Path
) -> None:
    text = GOOD.replace(X_AXIS, "").replace(
        "fallback_model: mlr-z_um-all", "fallback_model: mlr-x_um-all"
    )
    error = refused_at(tmp_path, store, text, "          fallback_model: mlr-x_um-all")
    assert "compensation.axes.Z.fallback_model: model 'mlr-x_um-all' predicts x_um, " in error
    assert "but axis Z compensates z_um" in error


def test_an_axis_whose_models_disagree_is_refused(tmp_path: Path, store: Path) -> None:
    text = (
        GOOD.replace(Y_AXIS, "")
        .replace("          target: z_um\n", "")
        .replace("models: {variable: mlr-z_um-all}", "models: {variable: mlr-y_um-all}")
    )
    error = refused_at(tmp_path, store, text, "          fallback_model: mlr-z_um-all")
    assert "compensation.axes.Z.fallback_model: model 'mlr-z_um-all' predicts z_um, " in error
    assert "but axis Z compensates y_um" in error


def test_two_axes_compensating_one_target_are_refused(tmp_path: Path, store: Path) -> None:
    text = GOOD.replace("          fallback_model: mlr-y_um-all\n", "          target: x_um\n")
    error = refused_at(tmp_path, store, text, "          target: x_um")
    assert "compensation.axes.Y.target: axis Y would compensate x_um, " in error
    assert "which axis X compensates" in error


def test_an_axis_target_no_model_predicts_is_refused(tmp_path: Path, store: Path) -> None:
    text = GOOD.replace("          fallback_model: mlr-y_um-all\n", "          target: ch9_um\n")
    error = refused_at(tmp_path, store, text, "          target: ch9_um")
    assert "compensation.axes.Y.target: no model in " in error
    assert "predicts ch9_um (axis Y)" in error


def test_an_axis_naming_a_model_not_in_the_store_is_refused(tmp_path: Path, store: Path) -> None:
    text = GOOD.replace("mlr-y_um-all", "mlr-w_um-all")
    error = refused_at(tmp_path, store, text, "      store: STORE")
    assert "models.store: machine vmc-3: axis Y fallback names model 'mlr-w_um-all', " in error


def test_a_single_axis_store_of_several_targets_is_still_refused(
    tmp_path: Path, store: Path
) -> None:
    single = GOOD.split("      axes:")[0] + (
        "      macro: 505\n    models:\n      store: STORE\n"
        "      regimes: {fallback_model: mlr-z_um-all}\n"
    )
    error = refused_at(tmp_path, store, single, "      store: STORE")
    assert "its models predict different targets" in error
