"""The proposal store and the versions of the promoted set (files only, no gateway)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from models.analysis import augmented
from models.online.proposals import (
    PROMOTED,
    PROPOSED,
    REJECTED,
    SUPERSEDED,
    ModelVersions,
    ProposalError,
    ProposalStore,
)
from tests.cli import gateway, gateway_in_process


def document(model_id: str, tau_s: float = 1800.0) -> dict[str, Any]:
    """A sealed augmented-model document; the store checks only format, id and checksum."""
    return augmented.sealed(
        {
            "format": augmented.FORMAT,
            "format_version": augmented.FORMAT_VERSION,
            "model_id": model_id,
            "effects": [{"effect": "thermal_lag", "params": {"tau_s": tau_s}, "terms": 1}],
            "target": {"name": "error_um", "unit": "µm"},
        }
    )


def publish(store: ProposalStore, model_id: str, machine: str = "vmc-1", **extra: Any):
    """Publish a thermal_lag proposal of ``document(model_id)``; ``extra`` overrides any field."""
    fields: dict[str, Any] = {
        "machine_id": machine,
        "effect": "thermal_lag",
        "params": {"tau_s": 1800.0},
        "before_rmse_um": 2.4,
        "after_rmse_um": 0.9,
        "probe_rows": 40,
        "document": document(model_id),
    }
    return store.publish(**(fields | extra))


def test_publish_list_get_round_trip(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    first = publish(store, "m-lag", created_s=1000.0)
    second = publish(store, "m-lag2", machine="vmc-2")
    assert (first.id, second.id) == ("P0001", "P0002")
    assert (tmp_path / "proposals" / "P0001.json").is_file()
    again = store.get("P0001")
    assert again == first
    assert again.status == PROPOSED and again.created_s == 1000.0
    assert again.document["sha256"] == document("m-lag")["sha256"]
    assert [p.id for p in store.list()] == ["P0001", "P0002"]
    assert [p.id for p in store.list(machine_id="vmc-2")] == ["P0002"]
    saved = json.loads((tmp_path / "proposals" / "P0002.json").read_text(encoding="utf-8"))
    assert saved["format"] == "thermal-gateway-model-proposal"
    assert saved["params"] == {"tau_s": 1800.0} and saved["probe_rows"] == 40
    assert "thermal_lag (tau_s 1800)" in first.describe()
    assert "2.40 → 0.90 µm on 40 probe rows" in first.describe()
    assert not list((tmp_path / "proposals").glob("*.tmp"))


def test_publish_refuses_a_changed_document_and_bad_figures(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    changed = document("m")
    changed["effects"][0]["params"]["tau_s"] = 60.0
    with pytest.raises(ProposalError, match="checksum mismatch"):
        publish(store, "m", document=changed)
    with pytest.raises(ProposalError, match="after_rmse_um must be a finite"):
        publish(store, "m", after_rmse_um=float("nan"))
    with pytest.raises(ProposalError, match="not an augmented model"):
        publish(store, "x", document={"format": "spindle-thermal-model", "model_id": "x"})
    assert store.list() == []


def test_unknown_id_names_what_the_store_has(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    publish(store, "m")
    with pytest.raises(KeyError, match=r"proposal 'P0009' is not in .* \(have: P0001\)"):
        store.get("P0009")
    with pytest.raises(KeyError, match=re.escape("'../x'")):
        store.get("../x")


def test_promote_supersede_rollback_and_statuses(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    versions = store.versions
    assert versions.current().number == 0 and versions.pointer_key() is None
    p1, p2 = publish(store, "m-one"), publish(store, "m-two")

    v1 = versions.promote(p1.id, by="test", time_s=10.0)
    key1 = versions.pointer_key()
    assert (v1.number, v1.previous, [e.model_id for e in v1.active]) == (1, 0, ["m-one"])
    assert store.get(p1.id).status == PROMOTED

    v2 = versions.promote(p2.id, by="test", time_s=20.0)
    assert (v2.number, v2.previous, [e.model_id for e in v2.active]) == (2, 1, ["m-two"])
    assert versions.pointer_key() != key1
    assert store.get(p1.id).status == SUPERSEDED and store.get(p2.id).status == PROMOTED

    v3 = versions.rollback(by="test", time_s=30.0)
    assert (v3.number, v3.restores, v3.previous) == (3, 1, 0)
    assert [e.model_id for e in versions.current().active] == ["m-one"]
    assert store.get(p1.id).status == PROMOTED and store.get(p2.id).status == REJECTED
    assert [h["status"] for h in store.get(p1.id).history] == [
        PROPOSED,
        PROMOTED,
        SUPERSEDED,
        PROMOTED,
    ]

    v4 = versions.rollback(by="test", time_s=40.0)
    assert (v4.number, v4.restores, v4.active) == (4, 0, ())
    assert store.get(p1.id).status == REJECTED
    with pytest.raises(ProposalError, match="nothing to roll back"):
        versions.rollback()

    # Nothing is deleted: every version is still there, in order.
    assert [v.number for v in versions.history()] == [0, 1, 2, 3, 4]
    assert [v.action for v in versions.history()] == [
        "start",
        "promote",
        "promote",
        "rollback",
        "rollback",
    ]
    # A fresh reader of the same folder sees the same version in force.
    assert ModelVersions(tmp_path).current() == v4


def test_only_an_open_proposal_is_promoted_or_rejected(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    p1, p2 = publish(store, "m-one"), publish(store, "m-two")
    store.versions.promote(p1.id)
    with pytest.raises(ProposalError, match="P0001 is promoted; only a proposed one"):
        store.versions.promote(p1.id)
    with pytest.raises(ProposalError, match="roll back a promoted one"):
        store.reject(p1.id)
    assert store.reject(p2.id, note="not now").status == REJECTED
    with pytest.raises(ProposalError, match="P0002 is rejected"):
        store.versions.promote(p2.id)
    assert store.versions.current().number == 1


def test_machines_and_places_are_kept_apart(tmp_path: Path) -> None:
    """A promotion supersedes only the entry of the same machine in the same place."""
    store = ProposalStore(tmp_path)
    a = publish(store, "a-all", machine="vmc-1")
    b = publish(store, "b-all", machine="vmc-2")
    c = publish(store, "a-const", machine="vmc-1", replaces="mlr-constant")
    store.versions.promote(a.id)
    store.versions.promote(b.id)
    version = store.versions.promote(c.id)
    assert sorted(e.model_id for e in version.active) == ["a-all", "a-const", "b-all"]
    assert [e.model_id for e in version.for_machine("vmc-2")] == ["b-all"]
    assert {p.status for p in store.list()} == {PROMOTED}


def test_a_damaged_proposal_file_is_named(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    publish(store, "m")
    (tmp_path / "proposals" / "P0001.json").write_text('{"format": ', encoding="utf-8")
    with pytest.raises(ProposalError, match=r"P0001.json: line 1, column \d+: not JSON"):
        store.get("P0001")


def test_command_line_errors_are_one_line_and_exit_2(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    publish(store, "m")
    unknown = gateway("models", "promote", "P0007", "--store", tmp_path)
    assert unknown.returncode == 2
    assert unknown.stderr.splitlines() == [
        f"error: proposal 'P0007' is not in {tmp_path / 'proposals'} (have: P0001)"
    ]
    nothing = gateway_in_process("models", "rollback", "--store", tmp_path)
    assert nothing.returncode == 2
    assert nothing.stderr.splitlines() == [
        f"error: nothing to roll back in {tmp_path}: version 0 is the store's own models"
    ]
    rejected = gateway_in_process(
        "models", "reject", "P0001", "--store", tmp_path, "--note", "too few probes"
    )
    assert rejected.returncode == 0, rejected.stderr
    assert store.get("P0001").history[-1]["note"] == "too few probes"
    again = gateway_in_process("models", "promote", "P0001", "--store", tmp_path)
    assert again.returncode == 2 and "P0001 is rejected" in again.stderr
    assert "Traceback" not in unknown.stderr + nothing.stderr + again.stderr
    listed = gateway_in_process("models", "versions", "--store", tmp_path)
    assert listed.returncode == 0 and "version 0: the store's own models" in listed.stdout
