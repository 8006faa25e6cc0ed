"""Regenerate ``sparkplug_b_pb2.py`` and its type stub from the spec's ``sparkplug_b.proto``.

The generated module is committed so that the gateway needs only the protobuf runtime;
this compiles the ``.proto`` (Eclipse Tahu) with grpcio-tools' bundled ``protoc`` (a dev
dependency) and writes the module and ``sparkplug_b_pb2.pyi`` (the stub the type checker
reads: the module itself builds its classes at import, invisible to a checker), or with
``--check`` says whether the committed files are current.

    python -m gateway.sparkplug.regenerate [--check]
"""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: The specification's file as published upstream, beside its licence (not edited here).
VENDOR = HERE / "vendor"
PROTO = VENDOR / "sparkplug_b.proto"
GENERATED = HERE / "sparkplug_b_pb2.py"
STUB = HERE / "sparkplug_b_pb2.pyi"


def generate() -> dict[Path, str]:
    """The texts protoc makes of the ``.proto`` today: the module and its stub."""
    from grpc_tools import protoc  # dev dependency: only needed to regenerate

    with tempfile.TemporaryDirectory() as out:
        status = protoc.main(
            [
                "protoc",
                f"--proto_path={VENDOR}",
                f"--python_out={out}",
                f"--pyi_out={out}",
                str(PROTO),
            ]
        )
        if status != 0:
            raise RuntimeError(f"protoc failed on {PROTO} (status {status})")
        module = (Path(out) / GENERATED.name).read_text(encoding="utf-8")
        stub = (Path(out) / STUB.name).read_text(encoding="utf-8")
        return {GENERATED: module, STUB: _typed_extensions(stub)}


def _typed_extensions(stub: str) -> str:
    """The stub without protoc's ``Extensions: python_message._ExtensionDict`` lines.

    That class is the runtime's private one, which the protobuf type stubs do not
    define; every message inherits a correctly typed ``Extensions`` from
    ``message.Message`` (the Sparkplug payload declares extension ranges, the gateway
    uses none), so the line is dropped, and with it the then unused import.
    """
    stub = stub.replace(
        "from google.protobuf.internal import python_message as _python_message\n", ""
    )
    return re.sub(r"^\s*Extensions: _python_message\._ExtensionDict\n", "", stub, flags=re.M)


def main(argv: list[str]) -> int:
    texts = generate()
    if "--check" in argv:
        stale = [
            path
            for path, text in texts.items()
            if (path.read_text(encoding="utf-8") if path.exists() else "") != text
        ]
        for path in stale:
            print(f"{path} is stale: run python -m gateway.sparkplug.regenerate")
        if not stale:
            print(f"{GENERATED.name} and {STUB.name} are current")
        return 1 if stale else 0
    for path, text in texts.items():
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
