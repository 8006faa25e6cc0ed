"""``make fit`` and ``make reports`` use the method every command defaults to.

The commands are read from ``make -n`` (the Makefile as make expands it; ``-o`` keeps
the virtualenv step out), and ``make fit``'s command is run for real into a temporary
store.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

from models.catalogue import DEFAULT_METHOD

ROOT = Path(__file__).resolve().parents[1]


def make_commands(target: str) -> list[list[str]]:
    """The ``python -m gateway …`` commands ``make target`` runs, as argument lists."""
    done = subprocess.run(
        ["make", "-n", "-o", ".venv/.installed", target],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    commands = []
    for line in done.stdout.replace("\\\n", " ").splitlines():
        if "-m gateway " in line:
            words = shlex.split(line.split("-m gateway ", 1)[1].split(";", 1)[0])
            commands.append(words)
    assert commands, done.stdout
    return commands


def test_fit_and_reports_use_the_default_method() -> None:
    assert DEFAULT_METHOD == "lag-ridge"
    for target, command, option in (("fit", "fit", "--method"), ("reports", "analyze", "--model")):
        for words in make_commands(target):
            assert words[0] == command, words
            if option in words:  # named: it must be the default
                assert words[words.index(option) + 1] == DEFAULT_METHOD, (target, words)


def test_make_fit_stores_a_lag_ridge_model(tmp_path: Path) -> None:
    (words,) = make_commands("fit")
    words[words.index("--store") + 1] = str(tmp_path / "models")
    done = subprocess.run(
        [sys.executable, "-m", "gateway", *words, "--no-progress"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    stored = sorted(p.name for p in (tmp_path / "models").glob("*.json"))
    assert stored == [f"{DEFAULT_METHOD}-ch5_um-all.json"], stored
