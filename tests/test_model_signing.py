"""Signed models and checked format versions, through the command line and a running gateway.

A forged model (its intercept moved by +30 µm, its checksum recomputed) carries
a whole checksum: only the signature (HMAC-SHA256 with a key kept outside the
store, :mod:`models.signing`) tells it from the real one. With
``models.signing_key_file`` configured, ``check-config`` and ``run`` refuse a
store model, a proposal or a version in force that is unsigned or wrongly
signed, naming the file; the running gateway keeps the models it has. A
document of a newer format version than this software reads is refused the same
way, key or not.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest
import yaml

from models import signing
from models.analysis import augmented
from models.online.proposals import ProposalStore
from models.store import ModelStore, StoreError, _checksum, load_file
from tests import served_bench as bench
from tests.cli import gateway, gateway_in_process
from tests.ports import free_tcp_port
from tests.served_bench import read_macro_mm, wait_until
from tests.test_promotion_kill import MACHINE, offset_model
from tests.test_run_command import bench_config

FALLBACK = "mlr-error_um-all.json"  # the model bench-1 runs on its constant program


def write_key(path: Path) -> Path:
    path.write_text(os.urandom(32).hex() + "\n")
    path.chmod(0o600)
    return path


def keyed_bench(tmp_path: Path, bus: int, cnc: int) -> tuple[Path, Path, Path]:
    """bench_config's machine with a signing key; its store's models re-saved (signed)."""
    config = bench_config(tmp_path, bus, cnc)
    key = write_key(tmp_path / "model.key")
    data = yaml.safe_load(config.read_text())
    data["machines"][0]["models"]["signing_key_file"] = str(key)
    config.write_text(yaml.safe_dump(data))
    store = tmp_path / "models"
    signing.configure(store, key)
    try:
        for path in store.glob("*.json"):
            ModelStore(store).save(json.loads(path.read_text()))
    finally:
        signing.configure(store, None)
    return config, key, store


def forge(document: dict[str, Any], shift_um: float) -> dict[str, Any]:
    """A stored model with its intercept moved and its checksum recomputed (signature kept)."""
    forged = json.loads(json.dumps(document))
    forged["params"]["intercept_um"] += shift_um
    forged["sha256"] = _checksum(forged)
    return forged


def test_a_forged_or_unsigned_model_is_refused_by_check_config_and_run(tmp_path: Path) -> None:
    config, _, store = keyed_bench(tmp_path, free_tcp_port(), free_tcp_port())
    assert all("signature" in json.loads(p.read_text()) for p in store.glob("*.json"))
    checked = gateway_in_process("check-config", "--config", config)
    assert checked.returncode == 0, checked.stderr

    path = store / FALLBACK
    signed = json.loads(path.read_text())
    path.write_text(json.dumps(forge(signed, 30.0)))
    for command in ("check-config", "run"):
        refused = gateway(command, "--config", config, timeout_s=120)
        assert refused.returncode == 2, (command, refused.stderr)
        assert f"{path}: the model's signature does not match" in refused.stderr
        assert "Traceback" not in refused.stderr

    unsigned = {k: v for k, v in signed.items() if k != "signature"}
    path.write_text(json.dumps(unsigned))
    refused = gateway_in_process("check-config", "--config", config)
    assert refused.returncode == 2
    assert f"{path}: the model is not signed" in refused.stderr
    assert "python -m gateway models sign --store" in refused.stderr

    # Only a store declared unsigned is not checked: the same unsigned file loads there.
    data = yaml.safe_load(config.read_text())
    del data["machines"][0]["models"]["signing_key_file"]
    config.write_text(yaml.safe_dump(data))
    refused = gateway_in_process("check-config", "--config", config)  # the default key
    assert refused.returncode == 2, refused.stdout
    assert "signature does not match the signing key" in refused.stderr  # not that key
    data["machines"][0]["models"]["signing"] = False
    config.write_text(yaml.safe_dump(data))
    checked = gateway_in_process("check-config", "--config", config)
    assert checked.returncode == 0, checked.stderr
    assert "unsigned (models.signing: false)" in checked.stdout


def test_a_key_others_can_read_or_inside_the_store_is_refused(tmp_path: Path) -> None:
    config, key, store = keyed_bench(tmp_path, free_tcp_port(), free_tcp_port())
    key.chmod(0o644)
    refused = gateway_in_process("check-config", "--config", config)
    assert refused.returncode == 2
    assert f"model signing key {key}: readable by every user" in refused.stderr
    inside = write_key(store / "model.key")
    data = yaml.safe_load(config.read_text())
    data["machines"][0]["models"]["signing_key_file"] = str(inside)
    config.write_text(yaml.safe_dump(data))
    refused = gateway_in_process("check-config", "--config", config)
    assert refused.returncode == 2
    assert "signing_key_file" in refused.stderr and "inside the model store" in refused.stderr


def test_fit_signs_with_the_key_of_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, key, _ = keyed_bench(tmp_path, free_tcp_port(), free_tcp_port())
    monkeypatch.setenv(signing.KEY_ENV, str(key))
    refit = tmp_path / "refit"
    done = gateway_in_process("fit", tmp_path / "training.csv", "--store", refit)
    assert done.returncode == 0, done.stderr
    files = list(refit.glob("*.json"))
    assert files and all("signature" in json.loads(p.read_text()) for p in files)
    assert load_file(files[0])[1].signature is not None
    monkeypatch.setenv(signing.KEY_ENV, str(write_key(tmp_path / "other.key")))
    with pytest.raises(StoreError, match="signature does not match"):
        load_file(files[0])


def publish_signed(store: Path, key: Path, offset_um: float, model_id: str) -> str:
    signing.configure(store, key)
    try:
        proposal = ProposalStore(store).publish(
            machine_id=MACHINE,
            effect="offset",
            params={"offset_um": offset_um},
            before_rmse_um=2.0,
            after_rmse_um=1.5,
            probe_rows=10,
            document=offset_model(store, model_id, offset_um),
        )
    finally:
        signing.configure(store, None)
    assert "signature" in proposal.document
    return proposal.id


def forged_document(document: dict[str, Any], shift_um: float) -> dict[str, Any]:
    forged = json.loads(json.dumps(document))
    forged["coefficients"]["all_um_per_unit"][0] += shift_um
    forged["coefficients"]["intercept_um"] += shift_um
    return augmented.sealed(forged)  # checksum recomputed, the old signature kept


def test_a_forged_promotion_is_refused_and_the_running_gateway_keeps_its_models(
    tmp_path: Path,
) -> None:
    bus, cnc = free_tcp_port(), free_tcp_port()
    config, key, store = keyed_bench(tmp_path, bus, cnc)
    good = publish_signed(store, key, 0.5, "offset-good")
    bad = publish_signed(store, key, 0.0, "offset-bad")
    proposal_file = store / "proposals" / f"{bad}.json"
    raw = json.loads(proposal_file.read_text())
    raw["document"] = forged_document(raw["document"], 30.0)
    proposal_file.write_text(json.dumps(raw))

    log_path = tmp_path / "run.log"
    with bench.bench_running(config, cnc, log_path) as running:
        refused = gateway("models", "promote", bad, "--config", config, timeout_s=120)
        assert refused.returncode == 2
        assert f"{proposal_file}, its model: the model's signature does not match" in (
            refused.stderr
        )
        promoted = gateway("models", "promote", good, "--config", config, timeout_s=120)
        assert promoted.returncode == 0, promoted.stderr
        assert wait_until(lambda: "models version 1 in force" in log_path.read_text(), 60)

        # Someone with write access to the store writes a version with the forged copy.
        version = json.loads((store / "versions" / "1.json").read_text())
        version["version"] = 2
        version["active"][0]["document"] = forged_document(version["active"][0]["document"], 30)
        (store / "versions" / "2.json").write_text(json.dumps(version))
        (store / "versions" / "current.json").write_text(json.dumps({"version": 2}))
        expected = "the promoted set cannot be read"
        assert wait_until(lambda: expected in log_path.read_text(), 60)
        assert "versions/2.json, model of P0001: the model's signature does not match" in (
            log_path.read_text()
        )
        assert "models version 2 in force" not in log_path.read_text()
        values = [read_macro_mm(cnc) for _ in range(10)]
        assert running.poll() is None
        assert all(abs(v) <= 0.050 for v in values)


def test_documents_of_a_newer_format_version_are_refused_naming_the_file(
    tmp_path: Path,
) -> None:
    config = bench_config(tmp_path, free_tcp_port(), free_tcp_port())
    store = tmp_path / "models"
    proposals = ProposalStore(store)
    ids = [
        proposals.publish(
            machine_id=MACHINE,
            effect="offset",
            params={},
            before_rmse_um=2.0,
            after_rmse_um=1.5,
            probe_rows=10,
            document=offset_model(store, f"offset-{i}", 0.1 * i),
        ).id
        for i in range(2)
    ]
    # A proposal whose model is of a newer format (checksum recomputed): not promoted.
    path = store / "proposals" / f"{ids[0]}.json"
    raw = json.loads(path.read_text())
    raw["document"] = augmented.sealed(raw["document"] | {"format_version": 3})
    path.write_text(json.dumps(raw))
    refused = gateway("models", "promote", ids[0], "--config", config, timeout_s=120)
    assert refused.returncode == 2
    assert f"{path}, its model: format_version 3 is not supported" in refused.stderr
    assert not (store / "versions" / "1.json").exists()

    # The version in force holding a model of a newer format: check-config and run refuse it.
    promoted = gateway_in_process("models", "promote", ids[1], "--store", store)
    assert promoted.returncode == 0, promoted.stderr
    version_file = store / "versions" / "1.json"
    version = json.loads(version_file.read_text())
    entry = version["active"][0]
    entry["document"] = augmented.sealed(entry["document"] | {"format_version": 3})
    version_file.write_text(json.dumps(version))
    refused = gateway("check-config", "--config", config, timeout_s=120)
    assert refused.returncode == 2
    assert f"{version_file}, model of {ids[1]}: format_version 3 is not supported" in (
        refused.stderr
    )

    # A version file and a proposal file of a newer format of their own.
    version["format_version"] = 2
    version_file.write_text(json.dumps(version))
    refused = gateway_in_process("models", "versions", "--store", store)
    assert refused.returncode == 2
    assert f"{version_file}: format_version 2 is not supported" in refused.stderr
    (store / "versions" / "current.json").unlink()  # version 0 in force: nothing to read
    version_file.unlink()
    raw["format_version"] = 2
    path.write_text(json.dumps(raw))
    refused = gateway_in_process("models", "proposals", "--store", store)
    assert refused.returncode == 2
    assert f"{path}: format_version 2 is not supported" in refused.stderr

    # An augmented model of the store of a newer format.
    folder = store / augmented.FOLDER
    folder.mkdir()
    newer = folder / "offset-9.json"
    document = offset_model(store, "offset-9", 0.0) | {"format_version": 3}
    newer.write_text(json.dumps(augmented.sealed(document)))
    refused = gateway_in_process("check-config", "--config", config)
    assert refused.returncode == 2
    assert f"{newer}: format_version 3 is not supported" in refused.stderr
