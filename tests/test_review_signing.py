"""Ways around the model signature, closed: each through the command line on real files.

- a key file others may write: whoever can replace the key signs any model with it;
- a signature value that is not ASCII: ``hmac.compare_digest`` raises TypeError on
  such strings, which reached the operator as a traceback instead of a refusal;
- two machines sharing a store, only one naming the key: the store's key was the one
  the last machine configured, so the keyed machine's promotions went unchecked.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import yaml

from tests.cli import gateway, gateway_in_process
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


def test_machines_sharing_a_store_must_name_the_same_key(tmp_path: Path) -> None:
    """bench-1 names the key; bench-2, on the same store, names none. Loading bench-2's
    models dropped the store's key, so a running gateway promoted (SCADA, console) and
    ran an unsigned model for bench-1. Now check-config and run refuse the configuration,
    naming the machine, the store and the key."""
    config, key, _ = keyed_bench(tmp_path, free_tcp_port(), free_tcp_port())
    data = yaml.safe_load(config.read_text())
    second = copy.deepcopy(data["machines"][0])
    second["id"] = "bench-2"
    second["cnc"]["modbus"]["port"] = free_tcp_port()
    del second["models"]["signing_key_file"]
    data["machines"].append(second)
    config.write_text(yaml.safe_dump(data))

    for command, run in (("check-config", gateway_in_process), ("run", gateway)):
        refused = run(command, "--config", config)
        assert refused.returncode == 2, (command, refused.stderr)
        assert "machines[1].models" in refused.stderr, refused.stderr
        assert "machine 'bench-2' names none, but shares the model store" in refused.stderr
        assert f"with machine 'bench-1' (machines[0]), which names signing key {key}" in (
            refused.stderr
        )
        assert "Traceback" not in refused.stderr

    second["models"]["signing_key_file"] = str(key)  # the same key: accepted
    config.write_text(yaml.safe_dump(data))
    checked = gateway_in_process("check-config", "--config", config)
    assert checked.returncode == 0, checked.stderr
