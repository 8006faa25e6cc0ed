"""Suite-wide test marks, and the event loop every test runs on.

Every ``asyncio.run`` in the tests runs on uvloop, the loop the gateway's commands
run on by default (gateway/process/event_loop.py); tests/test_event_loop.py runs the live
loop on asyncio's own loop, the other choice of the config's ``event_loop``.

The end-to-end files below run whole plants (simulator servers, the gateway, a
container, machine days on an accelerated clock) and take most of the suite's
time. They carry the ``slow`` mark so that a newcomer can run the rest first
(``make test-quick``); ``make test`` and CI always run everything.
"""

from __future__ import annotations

import asyncio
import os
import tempfile
from pathlib import Path

import pytest
import uvloop

from gateway.process.event_loop import DEFAULT
from models import signing
from tests import gateway_rig as rig
from tests import opcua_template

if DEFAULT == "uvloop":
    asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())

# Each in-process OPC UA server starts from a copy of one standard address space.
opcua_template.install()


def _test_signing_key() -> Path:
    """Models are signed by default (models/signing.py): every model the tests fit, in this
    process or in the commands they start, is signed with one key of this test run, named
    by SPINDLE_MODEL_KEY_FILE; never the key of the user running the tests. Shared by
    pytest-xdist's workers (the same run id), which share one fitted store."""
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID") or str(os.getpid())
    folder = Path(tempfile.gettempdir()) / f"spindle-test-keys-{os.getuid()}"
    return signing.create_key(folder / f"{run}.key")


os.environ[signing.KEY_ENV] = str(_test_signing_key())

#: Test files whose every test is an end-to-end run (measured as the slowest files).
SLOW_FILES = frozenset(
    {
        "test_bus_hub.py",
        "test_closed_loop.py",
        "test_container.py",
        "test_monitor_days.py",
        "test_monitor_loop.py",
        "test_promotion.py",
        "test_run_command.py",
    }
)


@pytest.fixture(scope="session", autouse=True)
def _one_fit_per_run(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The demo models tests/gateway_rig.py fits: once per run, not once per worker.
    A worker's temporary folder is ``popen-gwN`` inside the run's, which all share."""
    base = tmp_path_factory.getbasetemp()
    rig.share_fits_in(base.parent if base.name.startswith("popen-gw") else base)


#: The files that hold a worker longest (wall time on two cores, most first): they are
#: handed out first, so that no worker starts one of them when the others are done.
#: ``scripts/test.sh`` passes ``--no-loadscope-reorder``, which keeps this order
#: (xdist would otherwise hand out the files with the most tests first, and these,
#: with few tests each, last).
LONGEST_FIRST = (
    "test_lag_ridge.py",
    "test_closed_loop.py",
    "test_analyze.py",
    "test_reconnect.py",
    "test_real_data.py",
    "test_container.py",
    "test_scada.py",
    "test_independent_generators.py",
    "test_influx.py",
    "test_monitor_loop.py",
    "test_shutdown.py",
    "test_demo.py",
    "test_bus_hub.py",
    "test_scada_guards.py",
    "test_demo_effect.py",
    "test_regime_rules.py",
    "test_promotion.py",
    "test_retention.py",
    "test_write_path.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
