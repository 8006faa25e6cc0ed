"""Running ``python -m gateway …`` the way users and scripts do: a real subprocess.

:func:`gateway_in_process` runs the same command through click in the test's own
process: a fresh interpreter per call (numpy, scipy, sklearn imported again) would be
much of the suite's CPU and tests nothing more. Each command keeps at least one test
that runs it as a process (and a case of each table of refused inputs); commands that
serve, are signalled, or run beside a gateway always run as processes.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def gateway(*args: str | Path | int, timeout_s: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def gateway_in_process(*args: str | Path | int) -> subprocess.CompletedProcess[str]:
    """``gateway(*args)`` without a new interpreter: the same exit status and streams.

    An exception the command lets escape is written to stderr as a traceback, as the
    interpreter would, so a test that asserts none is printed still sees it.
    """
    from click.testing import CliRunner

    from gateway.cli.main import main

    argv = [str(a) for a in args]
    with contextlib.chdir(ROOT):
        result = CliRunner().invoke(main, argv, prog_name="gateway")
    stderr = result.stderr
    if result.exc_info is not None and not isinstance(result.exception, SystemExit):
        stderr += "".join(traceback.format_exception(*result.exc_info))
    return subprocess.CompletedProcess(argv, result.exit_code, result.stdout, stderr)
