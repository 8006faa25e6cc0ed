"""The model store's guards on what a store holds, through real ``check-config`` and ``run``.

- A model file whose id is not its file name (two files' contents swapped: each
  checksum and signature still whole) is refused, naming the file and both ids.
"""

from __future__ import annotations

from pathlib import Path

from tests.cli import gateway
from tests.ports import free_tcp_port
from tests.test_run_command import bench_config

FALLBACK = "mlr-error_um-all"
VARIABLE = "mlr-error_um-variable"


def test_model_files_with_their_contents_swapped_are_refused_naming_both(tmp_path: Path) -> None:
    config = bench_config(tmp_path, free_tcp_port(), free_tcp_port())
    store = tmp_path / "models"
    fallback, variable = store / f"{FALLBACK}.json", store / f"{VARIABLE}.json"
    fallback_text, variable_text = fallback.read_bytes(), variable.read_bytes()
    fallback.write_bytes(variable_text)
    variable.write_bytes(fallback_text)
    for command in ("check-config", "run"):
        refused = gateway(command, "--config", config, timeout_s=120)
        assert refused.returncode == 2, (command, refused.stdout, refused.stderr)
        assert f"{fallback}: holds model '{VARIABLE}', not '{FALLBACK}'" in refused.stderr, (
            command,
            refused.stderr,
        )
        assert "Traceback" not in refused.stderr
    fallback.write_bytes(fallback_text)
    variable.write_bytes(variable_text)
    assert gateway("check-config", "--config", config, timeout_s=120).returncode == 0
