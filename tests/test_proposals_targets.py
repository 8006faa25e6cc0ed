"""Promotion and rollback per target: a machine that compensates several axes has one
promoted model per axis in the same place (every regime); promoting or rolling back one
target's model leaves the other targets' models in force."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from models.analysis import augmented
from models.online.proposals import PROMOTED, REJECTED, SUPERSEDED, ProposalError, ProposalStore
from tests.cli import gateway_in_process


def axis_document(model_id: str, target: str) -> dict[str, Any]:
    return augmented.sealed(
        {
            "format": augmented.FORMAT,
            "format_version": augmented.FORMAT_VERSION,
            "model_id": model_id,
            "effects": [{"effect": "thermal_lag", "params": {"tau_s": 1800.0}, "terms": 1}],
            "target": {"name": target, "unit": "µm"},
        }
    )


def publish(store: ProposalStore, model_id: str, target: str):
    return store.publish(
        machine_id="vmc-1",
        effect="thermal_lag",
        params={"tau_s": 1800.0},
        before_rmse_um=2.4,
        after_rmse_um=0.9,
        probe_rows=40,
        document=axis_document(model_id, target),
    )


def in_force(store: ProposalStore) -> dict[str, str]:
    return {e.document["target"]["name"]: e.model_id for e in store.versions.current().active}


def test_promoting_one_axis_keeps_the_other_axes(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    z = publish(store, "z-lag", "ch5_um")
    x = publish(store, "x-lag", "ch1_um")
    store.versions.promote(z.id)
    store.versions.promote(x.id)  # same machine, same place (every regime), another target
    assert in_force(store) == {"ch5_um": "z-lag", "ch1_um": "x-lag"}
    assert store.get(z.id).status == PROMOTED
    z2 = publish(store, "z-lag2", "ch5_um")
    store.versions.promote(z2.id)  # the same target: supersedes z only
    assert in_force(store) == {"ch1_um": "x-lag", "ch5_um": "z-lag2"}
    assert store.get(z.id).status == SUPERSEDED and store.get(x.id).status == PROMOTED


def test_rolling_back_one_target_leaves_the_others(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    z, x, z2 = (
        publish(store, "z-lag", "ch5_um"),
        publish(store, "x-lag", "ch1_um"),
        publish(store, "z-lag2", "ch5_um"),
    )
    for proposal in (z, x, z2):
        store.versions.promote(proposal.id)
    x2 = publish(store, "x-lag2", "ch1_um")
    store.versions.promote(x2.id)  # the latest change is X's
    version = store.versions.rollback(target="ch5_um")
    assert version.target == "ch5_um" and "for target ch5_um" in version.describe()
    assert in_force(store) == {"ch1_um": "x-lag2", "ch5_um": "z-lag"}
    assert store.get(z2.id).status == REJECTED and store.get(z.id).status == PROMOTED
    store.versions.rollback(target="ch5_um")  # further back: before z was promoted
    assert in_force(store) == {"ch1_um": "x-lag2"}
    with pytest.raises(ProposalError, match="nothing to roll back for target ch5_um"):
        store.versions.rollback(target="ch5_um")
    store.versions.rollback()  # a plain rollback undoes the last change (Z's rollback)
    assert in_force(store) == {"ch1_um": "x-lag2", "ch5_um": "z-lag"}


def test_models_rollback_target_on_the_command_line(tmp_path: Path) -> None:
    store = ProposalStore(tmp_path)
    z, x = publish(store, "z-lag", "ch5_um"), publish(store, "x-lag", "ch1_um")
    store.versions.promote(z.id)
    store.versions.promote(x.id)
    done = gateway_in_process("models", "rollback", "--store", tmp_path, "--target", "ch5_um")
    assert done.returncode == 0, done.stderr
    assert "for target ch5_um; promoted models: x-lag" in done.stdout
    assert in_force(store) == {"ch1_um": "x-lag"}
    none = gateway_in_process("models", "rollback", "--store", tmp_path, "--target", "ch9_um")
    assert none.returncode == 2 and "nothing to roll back for target ch9_um" in none.stderr
