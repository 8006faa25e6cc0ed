"""Ways around the model signature, closed: each through the command line on real files.

- a key file others may write: whoever can replace the key signs any model with it.
"""

from __future__ import annotations

from pathlib import Path

from tests.cli import gateway_in_process
from tests.ports import free_tcp_port
from tests.test_model_signing import keyed_bench


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
