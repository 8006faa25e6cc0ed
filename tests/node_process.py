"""The node-opcua clients of tests/node (an OPC UA stack independent of asyncua), run as
processes of their own while the test's event loop keeps serving."""

from __future__ import annotations

import asyncio
from pathlib import Path

NODE_DIR = Path(__file__).parent / "node"


async def run_node(*args: str, timeout_s: float = 30.0) -> tuple[int, bytes, bytes]:
    """``node ARGS`` in tests/node: (exit status, stdout, stderr); killed after ``timeout_s``."""
    assert (NODE_DIR / "node_modules" / "node-opcua-client").is_dir(), (
        "tests/node/node_modules is missing: run scripts/setup-system.sh (npm ci in tests/node)"
    )
    proc = await asyncio.create_subprocess_exec(
        "node",
        *args,
        cwd=NODE_DIR,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        out, err = await asyncio.wait_for(proc.communicate(), timeout=timeout_s)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    assert proc.returncode is not None
    return proc.returncode, out, err
