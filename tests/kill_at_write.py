"""Run ``python -m gateway ARGS`` and SIGKILL it just before its Nth change under a folder.

An audit hook (:func:`sys.addaudithook`) counts the file-system changes the command
makes under FOLDER (a file opened for writing, a rename or replace, a link, a
removal) and sends the process a real ``SIGKILL`` as the Nth begins, so every step
of a writer can be cut, whatever code does the writing. Fewer than N changes: the
command ends as it would.

``python -m tests.kill_at_write N FOLDER ARGS…`` runs one command so.
``python -m tests.kill_at_write --serve`` imports the command line once and then,
for each JSON line ``{"step", "folder", "args", "output"}`` on stdin, forks a child
that runs the command (its stdout and stderr into ``output``) and answers a JSON
line ``{"returncode": …}`` (negative: killed by that signal): many killed commands
without an interpreter's start-up each.

``KILL_AT_WRITE_SIGNAL=SIGSTOP`` (any signal name) sends that signal instead of
``SIGKILL``: a writer stopped mid-change, holding what it holds.
"""

from __future__ import annotations

import json
import os
import runpy
import signal
import sys
from typing import Any

WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC


def is_change(event: str, args: tuple[Any, ...]) -> str | None:
    """The path an audit event changes, or None."""
    if event == "open":
        path, mode, flags = args
        writing = any(c in mode for c in "wax+") if isinstance(mode, str) else False
        if writing or (isinstance(flags, int) and flags & WRITE_FLAGS):
            return os.fsdecode(path) if isinstance(path, str | bytes) else None
        return None
    if event in ("os.rename", "os.link", "os.remove", "os.unlink"):
        return os.fsdecode(args[0])
    return None


def kill_at(limit: int, folder: str) -> None:
    """SIGKILL this process (or ``$KILL_AT_WRITE_SIGNAL``) as its ``limit``-th change under
    ``folder`` begins."""
    folder = os.path.realpath(folder)
    sent = signal.Signals[os.environ.get("KILL_AT_WRITE_SIGNAL", "SIGKILL")]
    seen = [0]

    def hook(event: str, args: tuple[Any, ...]) -> None:
        path = is_change(event, args)
        if path is None or not os.path.realpath(path).startswith(folder + os.sep):
            return
        seen[0] += 1
        if seen[0] == limit or (seen[0] > limit and sent == signal.SIGKILL):
            os.kill(os.getpid(), sent)

    sys.addaudithook(hook)


def run_forked(request: dict[str, Any]) -> int:
    """Run one request in a forked child; its exit code (negative: the signal)."""
    from gateway.cli.main import main

    pid = os.fork()
    if pid == 0:
        output = os.open(request["output"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(output, 1)
        os.dup2(output, 2)
        kill_at(int(request["step"]), request["folder"])
        code = 0
        try:
            main.main(args=list(request["args"]), prog_name="gateway")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def serve() -> None:
    # Imported once, before the first fork: what the models commands load.
    import gateway.cli.main
    import gateway.cli.models  # noqa: F401
    import models.online.proposals  # noqa: F401

    for line in sys.stdin:
        code = run_forked(json.loads(line))
        sys.stdout.write(json.dumps({"returncode": code}) + "\n")
        sys.stdout.flush()


def main() -> None:
    if sys.argv[1] == "--serve":
        serve()
        return
    kill_at(int(sys.argv[1]), sys.argv[2])
    sys.argv = ["gateway", *sys.argv[3:]]
    runpy.run_module("gateway", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
