"""Liveness of the compensation loops, for a container health check.

Each machine loop calls :func:`submit_heartbeat` once a cycle (:func:`write_heartbeat`
off the event loop); it replaces ``<state_dir>/<machine>-heartbeat.json`` atomically
with::

    {"machine": "vmc-1", "wall_time": 1732370000.25, "time_s": 8113.0, "cycles": 8113,
     "health": {"failed_writes": 0, "external_changes": 0, "link_errors_total": 3,
                "sink_failures": 0, "sink_failures_by_sink": {}, "loop_restarts": 0,
                "forwarder_backlog": 12, "dropped_points": 0, ...}}

``wall_time`` is the wall clock (``time.time()``, s since the epoch) of the
process that wrote it, so another process (the checker) can compare it with its
own clock; ``time_s`` is the time the cycle's outputs carry (its logged points, its
Sparkplug data: in the plant the wall time of the cycle's start, with a simulated
clock machine time), kept for the record only. In the plant the two differ by the
cycle's length, also after a step of the system clock or a pause of the host.
``health`` holds the machine's counters since the gateway started (the same
ones SCADA shows under ``Machines/<id>/Health``).

:func:`check` is healthy when every heartbeat file in the state directory is
younger than ``max_age_s``; its message also names every non-zero failure
counter of :data:`REPORTED`, so ``docker inspect`` shows what went wrong.
``python -m gateway.outputs.heartbeat --state-dir DIR --max-age-s N`` runs it, prints
one line and exits 0 (healthy) or 1 (unhealthy), as Docker's ``HEALTHCHECK``
expects. It imports nothing but the standard library, so it starts fast even on
a small edge box.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NoReturn

from gateway.process.file_writer import HEARTBEATS, Done
from models.json_files import write_json_atomic

SUFFIX = "-heartbeat.json"
MACHINE_ID = re.compile(r"^[A-Za-z0-9_.-]+$")  # as gateway.config checks machine ids
#: Failure counters of a heartbeat's ``health`` that the check's message names when non-zero.
REPORTED = (
    "failed_writes",
    "external_changes",
    "link_errors_total",
    "sink_failures",
    "loop_restarts",
    "forwarder_restarts",
    "dropped_points",
    "rejected_points",
)


def heartbeat_path(state_dir: str | Path, machine_id: str) -> Path:
    if not MACHINE_ID.match(machine_id):
        raise ValueError(f"machine id '{machine_id}' is not a plain name ([A-Za-z0-9_.-]+)")
    return Path(state_dir) / f"{machine_id}{SUFFIX}"


def write_heartbeat(
    state_dir: str | Path,
    machine_id: str,
    time_s: float,
    cycles: int = 0,
    *,
    wall_time: float | None = None,
    health: Mapping[str, Any] | None = None,
) -> Path:
    """Record that ``machine_id``'s loop completed a cycle stamped ``time_s``.

    The file is written to a temporary name in the same directory and renamed
    over the old one, so a reader sees the old or the new heartbeat, never half
    of one. No fsync: a heartbeat lost in a power cut does not matter.
    """
    path = heartbeat_path(state_dir, machine_id)
    payload = _payload(machine_id, time_s, cycles, wall_time, health)
    return write_json_atomic(path, payload, indent=None, durable=False)


def submit_heartbeat(
    state_dir: str | Path,
    machine_id: str,
    time_s: float,
    cycles: int = 0,
    *,
    health: Mapping[str, Any] | None = None,
    done: Done | None = None,
) -> Path:
    """:func:`write_heartbeat` for the event loop: the heartbeat (its wall time taken
    now) is written by :data:`gateway.process.file_writer.HEARTBEATS`' thread, whose
    rename cannot hold up the other machines' cycles on a busy disk. ``done`` is called
    in that thread with the error, or None, once the file is written."""
    path = heartbeat_path(state_dir, machine_id)
    payload = _payload(machine_id, time_s, cycles, None, health)
    text = json.dumps(payload, ensure_ascii=False) + "\n"
    HEARTBEATS.submit(path, text, done)
    return path


def _payload(
    machine_id: str,
    time_s: float,
    cycles: int,
    wall_time: float | None,
    health: Mapping[str, Any] | None,
) -> dict[str, Any]:
    payload: dict[str, Any] = {
        "machine": machine_id,
        "wall_time": time.time() if wall_time is None else float(wall_time),
        "time_s": float(time_s),
        "cycles": int(cycles),
    }
    if health is not None:
        payload["health"] = dict(health)
    return payload


def check(state_dir: str | Path, max_age_s: float, now: float | None = None) -> tuple[bool, str]:
    """(healthy, one-line message): every heartbeat in ``state_dir`` younger than ``max_age_s``."""
    state_dir = Path(state_dir)
    now = time.time() if now is None else now
    try:
        files = sorted(p for p in state_dir.iterdir() if p.name.endswith(SUFFIX))
    except OSError as exc:
        return False, f"unhealthy: state dir {state_dir}: {exc.strerror or exc}"
    if not files:
        return False, f"unhealthy: no heartbeat in {state_dir} (no machine loop has run a cycle)"
    stale: list[str] = []
    fresh: list[str] = []
    for path in files:
        name = path.name.removesuffix(SUFFIX)
        try:
            beat = json.loads(path.read_text(encoding="utf-8"))
            name = str(beat.get("machine", name))
            wall_time = float(beat["wall_time"])
            if not math.isfinite(wall_time):
                raise ValueError("wall_time is not a number")
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            stale.append(f"machine {name}: unreadable heartbeat {path.name} ({exc})")
            continue
        age_s = now - wall_time
        counters = _reported(beat.get("health"))
        if age_s > max_age_s:
            stale.append(
                f"machine {name}: last heartbeat {age_s:.1f} s ago (max {max_age_s:g} s){counters}"
            )
        else:
            fresh.append(f"{name} {max(age_s, 0.0):.1f} s ago{counters}")
    if stale:
        return False, "unhealthy: " + "; ".join(stale)
    return True, "healthy: " + ", ".join(fresh)


def _reported(health: object) -> str:
    """' (sink_failures 3, loop_restarts 1)' for the non-zero counters; '' when none."""
    if not isinstance(health, dict):
        return ""
    found = [
        f"{key} {health[key]}"
        for key in REPORTED
        if isinstance(health.get(key), int | float) and health[key]
    ]
    return f" ({', '.join(found)})" if found else ""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        # Docker reserves health-check exit status 2; a usage error is "unhealthy" (1).
        self.print_usage(sys.stderr)
        self.exit(1, f"{self.prog}: error: {message}\n")


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(
        prog="python -m gateway.outputs.heartbeat",
        description="Exit 0 when every machine loop wrote a heartbeat within --max-age-s, else 1.",
    )
    parser.add_argument("--state-dir", type=Path, required=True, help="the config's state_dir")
    parser.add_argument(
        "--max-age-s", type=float, required=True, help="oldest acceptable heartbeat, s"
    )
    args = parser.parse_args(argv)
    if not (math.isfinite(args.max_age_s) and args.max_age_s > 0):
        parser.error("--max-age-s must be a finite number > 0")
    healthy, message = check(args.state_dir, args.max_age_s)
    print(message, file=sys.stdout if healthy else sys.stderr)
    return 0 if healthy else 1


if __name__ == "__main__":
    sys.exit(main())
