"""Regenerate ``sparkplug_b_pb2.py`` from the spec's ``sparkplug_b.proto`` (Eclipse Tahu).

The generated module is committed so that the gateway needs only the protobuf runtime;
this compiles the ``.proto`` with grpcio-tools' bundled ``protoc`` (a dev dependency)
and writes the result, or with ``--check`` says whether the committed file is current.

    python -m gateway.sparkplug.regenerate [--check]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: The specification's file as published upstream, beside its licence (not edited here).
VENDOR = HERE / "vendor"
PROTO = VENDOR / "sparkplug_b.proto"
GENERATED = HERE / "sparkplug_b_pb2.py"


def generate() -> str:
    """The text protoc makes of the ``.proto`` today."""
    from grpc_tools import protoc  # dev dependency: only needed to regenerate

    with tempfile.TemporaryDirectory() as out:
        status = protoc.main(
            ["protoc", f"--proto_path={VENDOR}", f"--python_out={out}", str(PROTO)]
        )
        if status != 0:
            raise RuntimeError(f"protoc failed on {PROTO} (status {status})")
        return (Path(out) / "sparkplug_b_pb2.py").read_text(encoding="utf-8")


def main(argv: list[str]) -> int:
    text = generate()
    if "--check" in argv:
        current = GENERATED.read_text(encoding="utf-8") if GENERATED.exists() else ""
        if current != text:
            print(f"{GENERATED} is stale: run python -m gateway.sparkplug.regenerate")
            return 1
        print(f"{GENERATED} is current")
        return 0
    GENERATED.write_text(text, encoding="utf-8")
    print(f"wrote {GENERATED}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
