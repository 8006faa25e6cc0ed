"""A plant of 1000 machines in one configuration, sharing one model store.

``check-config`` runs as a process on a generated configuration; its CPU time (not
its wall time, which the test machine's load decides) is bounded well below what
checking the shared store once per machine cost (about 47 ms a machine, 47 s).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml

from tests.gateway_rig import DEVICES, fit_store

ROOT = Path(__file__).resolve().parent.parent
MACHINES = 1000
MAX_CPU_S = 20.0


def machine(index: int, store: Path) -> dict[str, Any]:
    """One machine: its own CNC (the macro needs one writer), the shared store."""
    return {
        "id": f"m{index:04d}",
        "cycle_s": 1.0,
        "transmitters": [
            {
                "name": "bus1",
                "tcp": {"host": "127.0.0.1", "port": 15020},
                "timeout_s": 0.5,
                "devices": [DEVICES[0], {"device_id": 2, "channels": ["T9", None]}],
            }
        ],
        "cnc": {"modbus": {"host": "127.0.0.1", "port": 20000 + index, "timeout_s": 0.5}},
        "compensation": {"slew_um_per_min": 2000.0},
        "models": {
            "store": str(store),
            "regimes": {
                "models": {"variable": "mlr-error_um-variable"},
                "fallback_model": "mlr-error_um-all",
            },
        },
    }


def write_config(folder: Path, machines: int) -> Path:
    store = fit_store(folder)
    document = {
        "state_dir": str(folder / "state"),
        "machines": [machine(i, store) for i in range(machines)],
    }
    path = folder / "config.yaml"
    # Through JSON: plain nested data, so the dump repeats the devices rather than aliasing them.
    path.write_text(yaml.safe_dump(json.loads(json.dumps(document))), encoding="utf-8")
    return path


def run_measured(*args: str | Path) -> tuple[int, str, float]:
    """Run ``python -m gateway …``; (exit status, stdout, CPU seconds of the process)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", *map(str, args)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout is not None
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, out, usage.ru_utime + usage.ru_stime


def test_check_config_of_1000_machines_sharing_a_store(tmp_path: Path) -> None:
    config = write_config(tmp_path, MACHINES)
    code, out, cpu_s = run_measured("check-config", "--config", config)
    assert code == 0, out[-2000:]
    checked = [line for line in out.splitlines() if line.startswith("machine m")]
    assert len(checked) == MACHINES
    assert all("12 models in" in line for line in checked), checked[:3]
    assert out.splitlines()[-1] == f"{config}: ok"
    assert cpu_s < MAX_CPU_S, f"check-config took {cpu_s:.1f} s of CPU for {MACHINES} machines"
