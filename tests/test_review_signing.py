"""Ways around the model signature, closed: each through the command line on real files.

- a key file others may write: whoever can replace the key signs any model with it;
- a signature value that is not ASCII: ``hmac.compare_digest`` raises TypeError on
  such strings, which reached the operator as a traceback instead of a refusal.
"""

from __future__ import annotations

import json
from pathlib import Path

from tests.cli import gateway_in_process
from tests.ports import free_tcp_port
from tests.test_model_signing import FALLBACK, keyed_bench


def test_a_key_file_others_or_the_group_may_write_is_refused(tmp_path: Path) -> None:
    config, key, _ = keyed_bench(tmp_path, free_tcp_port(), free_tcp_port())
    for mode in (0o602, 0o620):
        key.chmod(mode)
        refused = gateway_in_process("check-config", "--config", config)
        assert refused.returncode == 2, (oct(mode), refused.stdout)
        assert f"model signing key {key}: writable by" in refused.stderr
        assert "Traceback" not in refused.stderr
    key.chmod(0o640)  # readable by a group, writable by its owner only: the documented setup
    checked = gateway_in_process("check-config", "--config", config)
    assert checked.returncode == 0, checked.stderr


def test_a_signature_that_is_not_ascii_is_refused_without_a_traceback(tmp_path: Path) -> None:
    config, _, store = keyed_bench(tmp_path, free_tcp_port(), free_tcp_port())
    path = store / FALLBACK
    document = json.loads(path.read_text())
    document["signature"]["value"] = "é" * 64
    path.write_text(json.dumps(document))
    refused = gateway_in_process("check-config", "--config", config)
    assert refused.returncode == 2
    assert f"{path}: the model's signature does not match" in refused.stderr
    assert "Traceback" not in refused.stderr
