"""A plant of 1000 machines in one configuration, sharing one model store.

``check-config`` runs as a process on a generated configuration; its CPU time (not
its wall time, which the test machine's load decides) is bounded well below what
checking the shared store once per machine cost (about 47 ms a machine, 47 s).

``run`` runs as a process on 1000 machines served over Modbus TCP by the lean device
servers of benchmarks/poll_vs_telegraf.py (each machine's transmitters and CNC on a
port of its own; ``simulate`` serves one machine per process): every machine writes
its first heartbeat, and the gateway's CPU until then is bounded below what building
each machine's sensor relations again cost (20.7 s of CPU, 12 s of it the relations).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.gateway_rig import DEVICES, fit_store

ROOT = Path(__file__).resolve().parent.parent
MACHINES = 1000
MAX_CPU_S = 20.0
#: ``run``: wall time from the process start until every machine has cycled, bounded for a
#: loaded test machine (8.4 s of CPU; 36 s of wall at a load average of 13 on 2 cores) …
MAX_START_S = 120.0
#: … and the gateway's CPU by then (8.4–10.4 s measured; 20.7 s when every machine built
#: its own sensor relations).
MAX_START_CPU_S = 15.0


def machine(index: int, store: Path, port: int | None = None) -> dict[str, Any]:
    """One machine: its own CNC (the macro needs one writer), the shared store.

    ``port``: the machine's transmitters and CNC both on that Modbus TCP port (one
    machine of :class:`benchmarks.poll_vs_telegraf.Devices`); else ports nobody serves.
    """
    return {
        "id": f"m{index:04d}",
        "cycle_s": 1.0,
        "transmitters": [
            {
                "name": "bus1",
                "tcp": {"host": "127.0.0.1", "port": 15020 if port is None else port},
                "timeout_s": 0.5,
                "devices": [DEVICES[0], {"device_id": 2, "channels": ["T9", None]}],
            }
        ],
        "cnc": {
            "modbus": {
                "host": "127.0.0.1",
                "port": 20000 + index if port is None else port,
                "timeout_s": 0.5,
            }
        },
        "compensation": {"slew_um_per_min": 2000.0},
        "models": {
            "store": str(store),
            "regimes": {
                "models": {"variable": "mlr-error_um-variable"},
                "fallback_model": "mlr-error_um-all",
            },
        },
    }


def write_config(folder: Path, machines: int, ports: list[int] | None = None) -> Path:
    store = fit_store(folder)
    document = {
        "state_dir": str(folder / "state"),
        "machines": [
            machine(i, store, None if ports is None else ports[i]) for i in range(machines)
        ],
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


@dataclass
class StartUp:
    """When the machines of one ``run`` process first cycled (s since the process started)."""

    machines: int
    cycling: int = 0
    built_s: float | None = None  # "running N machine(s)": the configuration loaded, loops built
    first_cycle_s: float | None = None
    all_cycling_s: float | None = None
    #: the process's CPU (user + system) when the last machine first cycled
    all_cycling_cpu_s: float | None = None


def process_cpu_s(pid: int) -> float:
    """utime + stime of a whole process (every thread), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure_start(config: Path, machines: int, state_dir: Path, within_s: float) -> StartUp:
    """Run ``python -m gateway run`` until every machine has written its heartbeat (each
    loop writes ``<id>-heartbeat.json`` at the end of every cycle, the first one included)
    or ``within_s`` passed; then stop it with SIGTERM (SIGKILL after 10 s)."""
    seen: set[str] = set()
    result = StartUp(machines)
    log = config.parent / "run.log"
    with log.open("w") as out:
        started = time.monotonic()
        command = ["-m", "gateway", "run", "--config", str(config), "--log-level", "error"]
        proc = subprocess.Popen(
            [sys.executable, *command],
            cwd=ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
        try:
            while len(seen) < machines and time.monotonic() - started < within_s:
                assert proc.poll() is None, log.read_text()[-3000:]
                now_s = time.monotonic() - started
                if result.built_s is None and _printed(log, "running "):
                    result.built_s = now_s
                names = os.listdir(state_dir) if state_dir.is_dir() else []
                seen.update(n for n in names if n.endswith("-heartbeat.json"))
                if seen and result.first_cycle_s is None:
                    result.first_cycle_s = now_s
                if len(seen) == machines:
                    result.all_cycling_s = now_s
                    result.all_cycling_cpu_s = process_cpu_s(proc.pid)
                time.sleep(0.05)
        finally:
            # Stopping saves 1000 machines' lag states durably (minutes on a loaded disk);
            # only the start is measured here, so a stop that takes long is cut short.
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    result.cycling = len(seen)
    return result


def _printed(log: Path, start: str) -> bool:
    with log.open() as text:
        return any(line.startswith(start) for line in text.read(200_000).splitlines())


def test_run_of_1000_machines_cycles_every_machine(tmp_path: Path) -> None:
    from benchmarks.poll_vs_telegraf import Devices

    devices = Devices(MACHINES)
    try:
        config = write_config(tmp_path, MACHINES, devices.ports)
        start = measure_start(config, MACHINES, tmp_path / "state", MAX_START_S)
    finally:
        devices.close()
    assert start.cycling == MACHINES, start
    assert start.all_cycling_s is not None and start.all_cycling_s < MAX_START_S, start
    assert start.all_cycling_cpu_s is not None, start
    assert start.all_cycling_cpu_s < MAX_START_CPU_S, start


def test_libyaml_parse_gives_the_python_parse_and_every_line(tmp_path: Path) -> None:
    from drivers.yaml_loader import _load_checked, _load_fast, _read_text

    config = write_config(tmp_path, 50)
    text = _read_text(config)
    fast = _load_fast(config, text)
    assert fast is not None, "a good file is parsed by libyaml"
    slow = _load_checked(config, text)
    assert fast.data == slow.data
    assert fast.lines == slow.lines
    assert (
        fast.line_of(("machines", 49, "cnc", "modbus", "port"))
        == text.splitlines().index("      port: 20049") + 1
    )


def test_a_bad_big_file_is_located_as_before(tmp_path: Path) -> None:
    from drivers.yaml_loader import YamlError, load_yaml

    config = write_config(tmp_path, 200)
    lines = config.read_text(encoding="utf-8").splitlines()
    at = lines.index("  cycle_s: 1.0", len(lines) // 2)
    lines.insert(at + 1, "  cycle_s: 2.0")
    config.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(YamlError) as refused:
        load_yaml(config)
    assert str(refused.value).startswith(f"{config}:{at + 2}: machines[")
    assert f"key given twice (lines {at + 1} and {at + 2})" in str(refused.value)


def test_a_deeply_nested_file_is_refused_not_crashed_on(tmp_path: Path) -> None:
    # libyaml's own composer recurses in C: 500 000 nested lists crash the process.
    path = tmp_path / "deep.yaml"
    path.write_text("machines: " + "[" * 500_000, encoding="utf-8")
    code = "from drivers.yaml_loader import load_yaml; import sys; load_yaml(sys.argv[1])"
    done = subprocess.run(
        [sys.executable, "-c", code, str(path)], cwd=ROOT, capture_output=True, text=True
    )
    assert done.returncode == 1, (done.returncode, done.stderr[-500:])
    assert f"{path}:1: nested too deeply to be a configuration" in done.stderr
