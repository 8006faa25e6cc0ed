"""``run`` refuses a model store it cannot use with the line ``check-config`` prints: the
file, the line and the key of that machine's ``models.store`` (it said "model store …:
no such folder" with neither, even for a store path that is a file)."""

from __future__ import annotations

import pytest

from tests.cli import ROOT, gateway

CASES = ROOT / "tests" / "cases" / "config"


@pytest.mark.parametrize("name", ["model-store-is-a-file", "model-store-missing"])
def test_run_refuses_a_model_store_with_the_line_check_config_prints(name: str) -> None:
    case = CASES.relative_to(ROOT) / f"{name}.yaml"
    expected = (CASES / f"{name}.expected").read_text(encoding="utf-8").rstrip("\n")
    assert f"{case}:" in expected and "machines[0].models.store: " in expected
    result = gateway("run", "--config", case, timeout_s=120)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines() == [expected]


def test_a_store_option_naming_a_file_says_so_with_the_option() -> None:
    """``score --store`` and ``models … --store`` with a file: the option, the path and
    what was expected (they said "no such folder")."""
    from tests.cli import gateway_in_process

    readme = ROOT / "README.md"
    expected = f"error: --store {readme}: is a file; a model store folder was expected"
    for command in (
        ("score", CASES / "model-store-is-a-file.yaml", "--model", "m", "--store", readme),
        ("models", "versions", "--store", readme),
    ):
        result = gateway_in_process(*command)
        assert result.returncode == 2, result.stdout + result.stderr
        assert result.stderr.splitlines()[-1] == expected
