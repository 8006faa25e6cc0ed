"""The command line and the health check start without the heavy libraries.

A timing assertion would be flaky on a shared machine; which modules a fresh
interpreter has loaded after the import is the honest check (the timings are
in benchmarks/cli_start.py).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.cli import ROOT, gateway

HEAVY = {"numpy", "scipy", "pandas", "matplotlib", "sklearn", "asyncua", "pymodbus"}
HEAVY |= {"influxdb_client", "jinja2"}


def heavy_modules_after(code: str) -> list[str]:
    """The heavy modules a fresh interpreter holds after running ``code``."""
    probe = (
        f"{code}\nimport json, sys\n"
        f"print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in {sorted(HEAVY)!r})))"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True
    )
    return json.loads(done.stdout.splitlines()[-1])


@pytest.mark.parametrize(
    "module", ["gateway", "gateway.cli.main", "gateway.__main__", "gateway.outputs.heartbeat"]
)
def test_importing_loads_no_heavy_library(module: str) -> None:
    assert heavy_modules_after(f"import {module}") == []


@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["check-config", "--help"],
        ["run", "--help"],
        ["fit", "--help"],
        ["analyze", "--help"],
        ["export", "--help"],
    ],
)
def test_help_loads_no_heavy_library(args: list[str]) -> None:
    code = (
        "import sys\nfrom gateway.cli.main import main\n"
        f"sys.argv = ['gateway', *{args!r}]\n"
        "try:\n    main()\nexcept SystemExit as stop:\n    assert stop.code == 0, stop.code"
    )
    assert heavy_modules_after(code) == []


def test_help_still_lists_the_choices() -> None:
    done = gateway("fit", "--help")
    assert done.returncode == 0, done.stderr
    assert "[grey-mlr|lag-ridge|mlr|pca-quadratic|pls|ridge]" in " ".join(done.stdout.split())
    assert "[auto|run-start|recording-start]" in " ".join(done.stdout.split())


def test_catalogue_matches_the_modules_it_stands_in_for() -> None:
    """The option choices come from the catalogue; the registry must agree with it."""
    from models import catalogue
    from models.data import references
    from models.estimators.registry import METHODS
    from models.fit import conditioning

    assert tuple(sorted(METHODS)) == catalogue.METHOD_NAMES
    assert references.POLICIES is catalogue.POLICIES
    assert conditioning.DEFAULT_SENSOR_ACCURACY_C is catalogue.DEFAULT_SENSOR_ACCURACY_C
    assert conditioning.DEFAULT_MAX_BIAS_ERROR_UM is catalogue.DEFAULT_MAX_BIAS_ERROR_UM


def test_project_input_errors_are_caught_by_the_cli() -> None:
    """The CLI catches built-in types; every project input error must be one of them."""
    from drivers.yaml_loader import KeyPathError, YamlError
    from gateway.cli.options import INPUT_ERRORS
    from gateway.config import ConfigError
    from gateway.offline.export import ExportError
    from models.data.dataset import DataError
    from models.fit.ranking import SigmaFileError
    from models.store import StoreError

    errors = (DataError, StoreError, ConfigError, ExportError, YamlError, KeyPathError)
    for error in (*errors, SigmaFileError):
        assert issubclass(error, INPUT_ERRORS), error
