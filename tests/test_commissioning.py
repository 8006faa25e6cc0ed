"""docs/commissioning.md, executed: every ``sh`` block of the page, in order, in one shell.

The configuration files are the page's ``yaml`` blocks (each names its file on its
first line); the commands are its ``sh`` blocks. Only the ports change: free ones in
place of the page's 15020 and 15021. The outcome of each step is then checked on
what the commands left behind.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

from gateway.outputs.local_store import LocalStore
from models.data.dataset import load_runs
from tests.ports import free_tcp_port

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "commissioning.md"
PAGE_PORTS = ("15020", "15021")
FENCE = re.compile(r"^```(\w+)\n(.*?)^```", re.S | re.M)
FILE_LINE = re.compile(r"^# file: (\S+)\n")


def page_blocks(text: str) -> tuple[dict[str, str], str]:
    """The page's configuration files by name, and its shell commands as one script."""
    files, commands = {}, []
    for language, body in FENCE.findall(text):
        if language == "yaml":
            named = FILE_LINE.match(body)
            assert named, f"a yaml block of {PAGE.name} names no file: {body[:40]!r}"
            files[named.group(1)] = body
        elif language == "sh":
            commands.append(body)
    return files, "".join(commands)


def command_folder(folder: Path) -> Path:
    """``spindle-gateway`` for the shell: this interpreter running this checkout."""
    bin_dir = folder / "bin"
    bin_dir.mkdir()
    script = bin_dir / "spindle-gateway"
    script.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m gateway "$@"\n', encoding="utf-8")
    script.chmod(0o755)
    return bin_dir


def run_page(folder: Path) -> subprocess.CompletedProcess[str]:
    text = PAGE.read_text(encoding="utf-8")
    for page_port in PAGE_PORTS:
        text = text.replace(page_port, str(free_tcp_port()))
    files, script = page_blocks(text)
    for name, body in files.items():
        (folder / name).write_text(body, encoding="utf-8")
    env = {
        **os.environ,
        "PATH": f"{command_folder(folder)}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": str(ROOT),
    }
    out_file, err_file = folder / "page.out", folder / "page.err"
    with out_file.open("w") as out, err_file.open("w") as err:
        shell = subprocess.Popen(
            ["bash", "-e", "-c", script],
            cwd=folder,
            env=env,
            stdout=out,
            stderr=err,
            start_new_session=True,  # its background jobs in one group, ended below
        )
        try:
            shell.wait(timeout=240)
        finally:
            with contextlib.suppress(ProcessLookupError):  # a job left behind by a failure
                os.killpg(shell.pid, signal.SIGKILL)
            shell.wait()
    return subprocess.CompletedProcess(
        shell.args, shell.returncode, out_file.read_text(), err_file.read_text()
    )


def test_the_commissioning_walkthrough_runs_as_written(tmp_path: Path) -> None:
    done = run_page(tmp_path)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    # 1. The provisional model.
    assert (tmp_path / "provisional" / "mlr-error_um-all.json").is_file()
    # 2–4. Training and validation logged with the probe, exported apart, fitted.
    training = load_runs(tmp_path / "training.csv")
    validation = load_runs(tmp_path / "validation.csv")
    assert training.n_samples >= 60, training.n_samples  # 4 machine hours, a probe per 120 s
    assert validation.n_samples >= 10, validation.n_samples  # 2 machine hours; load drops some
    assert training.time_s.max() < validation.time_s.min() or set(training.run_ids).isdisjoint(
        validation.run_ids
    )
    fit = json.loads((tmp_path / "fit.json").read_text(encoding="utf-8"))
    assert fit["method"] == "ridge"
    assert (tmp_path / "models" / "ridge-error_um-all.json").is_file()
    # 5. The score of the validation run, no refit.
    score = json.loads((tmp_path / "score.json").read_text(encoding="utf-8"))
    assert score["model_id"] == "ridge-error_um-all" and score["refit"] is False
    assert score["pooled"]["n_samples"] == validation.n_samples
    assert set(score["per_run"]) == set(validation.run_ids)
    # On the bench the logged clock is 600× compressed (see the page), so the figure checks
    # the procedure, not a machine's accuracy: finite, and below the uncompensated error.
    uncompensated_um = float(np.sqrt(np.mean(np.asarray(validation.error_um) ** 2)))
    assert math.isfinite(score["pooled"]["rmse_um"])
    assert score["pooled"]["rmse_um"] < uncompensated_um, (score["pooled"], uncompensated_um)
    assert "no refit" in done.stdout
    # 6. Live: the fitted model compensated the machine (cycles logged under its id).
    with LocalStore(tmp_path / "data" / "points.sqlite", set_aside_damaged=False) as store:
        cycles = store.query("spindle_cycle", "vmc-1")
    live = [p for p in cycles if p.tags.get("model_id") == "ridge-error_um-all"]
    assert live, {p.tags.get("model_id") for p in cycles}
    written = [p for p in live if "written_cnc" in p.fields]
    assert written and max(abs(p.fields["applied_um"]) for p in written) > 1.0, written[-3:]
    # 7. The monitor's proposals and the version in force were listed.
    assert "proposal" in done.stdout.lower(), done.stdout[-2000:]
