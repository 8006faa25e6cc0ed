"""``fit``, ``analyze``, ``score`` and ``replay`` on several targets in one command: each
target's figures equal the run on that target alone (to 1e-9), the file read once.

The synthetic file has three error columns (x_um, y_um, z_um) from the same temperatures,
y_um with one empty cell: its run alone skips that row, and so must its section of a
run on every target.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from tests.cli import gateway, gateway_in_process
from tests.synthetic import write_axes_csv

TARGETS = ("x_um", "y_um", "z_um")


@pytest.fixture(scope="module")
def axes_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("axes")
    return write_axes_csv(folder / "axes.csv", empty_rows={"y_um": 10}, n_runs=4, n=200)


def assert_same(one: Any, alone: Any, where: str = "") -> None:
    """Equal JSON values, numbers to 1e-9 (relative and absolute)."""
    if isinstance(alone, dict):
        assert isinstance(one, dict) and one.keys() == alone.keys(), where
        for key in alone:
            assert_same(one[key], alone[key], f"{where}.{key}")
    elif isinstance(alone, list):
        assert isinstance(one, list) and len(one) == len(alone), where
        for k, (a, b) in enumerate(zip(one, alone, strict=True)):
            assert_same(a, b, f"{where}[{k}]")
    elif isinstance(alone, float) and not isinstance(one, bool):
        assert math.isclose(one, alone, rel_tol=1e-9, abs_tol=1e-9) or (
            math.isnan(one) and math.isnan(alone)
        ), f"{where}: {one} != {alone}"
    else:
        assert one == alone, f"{where}: {one!r} != {alone!r}"


def run_json(tmp_path: Path, name: str, *args: str | Path) -> dict[str, Any]:
    out = tmp_path / f"{name}.json"
    result = gateway_in_process(*args, "--json", out)
    assert result.returncode == 0, result.stderr
    return json.loads(out.read_text(encoding="utf-8"))


def without(payload: dict[str, Any], *keys: str) -> dict[str, Any]:
    return {k: v for k, v in payload.items() if k not in keys}


def test_fit_every_target_equals_each_alone(tmp_path: Path, axes_csv: Path) -> None:
    fit = ("fit", axes_csv, "--method", "mlr", "--no-progress")
    together = run_json(tmp_path, "all", *fit, "--target", "all", "--store", tmp_path / "all")
    assert list(together) == ["method", "targets"]
    assert list(together["targets"]) == list(TARGETS)
    for target in TARGETS:
        alone = run_json(tmp_path, target, *fit, "--target", target, "--store", tmp_path / target)
        assert "targets" not in alone and alone["target"] == target
        one = together["targets"][target]
        assert_same(without(one, "saved"), without(alone, "saved"), target)
        assert list(one["saved"]) == [f"mlr-{target}-all"]
        stored = json.loads(Path(one["saved"][f"mlr-{target}-all"]).read_text())
        single = json.loads(Path(alone["saved"][f"mlr-{target}-all"]).read_text())
        assert stored["target"]["name"] == target
        assert stored["validation"] == single["validation"]
        assert stored["params"] == single["params"]
    y = together["targets"]["y_um"]["validations"]["all"]["pooled"]["n_samples"]
    x = together["targets"]["x_um"]["validations"]["all"]["pooled"]["n_samples"]
    assert y == x - 1  # the row with y_um's empty cell is left out of y_um alone


def test_analyze_two_targets_equal_each_alone(tmp_path: Path, axes_csv: Path) -> None:
    analyze = ("analyze", axes_csv, "--model", "mlr", "--no-progress")
    pair = ("--target", "z_um", "--target", "y_um")
    together = run_json(tmp_path, "pair", *analyze, *pair)
    assert list(together) == ["targets"] and list(together["targets"]) == ["z_um", "y_um"]
    for target in ("z_um", "y_um"):
        alone = run_json(tmp_path, target, *analyze, "--target", target)
        assert_same(together["targets"][target], alone, target)


def test_score_each_model_on_its_target(tmp_path: Path, axes_csv: Path) -> None:
    store = tmp_path / "store"
    fitted = gateway_in_process("fit", axes_csv, "--method", "mlr", "--target", "all",
                                "--store", store, "--no-progress")  # fmt: skip
    assert fitted.returncode == 0, fitted.stderr
    models = [arg for t in TARGETS for arg in ("--model", f"mlr-{t}-all")]
    together = run_json(tmp_path, "all", "score", axes_csv, "--store", store, *models)
    assert list(together["targets"]) == list(TARGETS)
    for target in TARGETS:
        alone = run_json(tmp_path, target, "score", axes_csv, "--store", store,
                         "--model", f"mlr-{target}-all")  # fmt: skip
        assert alone["target"] == target
        assert_same(together["targets"][target], alone, target)
    chosen = run_json(tmp_path, "x", "score", axes_csv, "--store", store, *models,
                      "--target", "x_um")  # fmt: skip
    assert chosen["model_id"] == "mlr-x_um-all"  # one target: today's JSON
    refused = gateway_in_process("score", axes_csv, "--store", store,
                                 "--model", "mlr-x_um-all", "--model", "mlr-y_um-all",
                                 "--target", "z_um")  # fmt: skip
    assert refused.returncode == 2
    assert "--target z_um: no --model predicts it" in refused.stderr


def test_replay_two_targets_equal_each_alone(tmp_path: Path, axes_csv: Path) -> None:
    replay = ("replay", axes_csv, "--model", "mlr", "--no-progress")
    together = run_json(tmp_path, "pair", *replay, "--target", "x_um", "--target", "y_um")
    assert list(together) == ["model", "targets"]
    for target in ("x_um", "y_um"):
        alone = run_json(tmp_path, target, *replay, "--target", target)
        assert_same(without(together["targets"][target], "elapsed_s"),
                    without(alone, "elapsed_s"), target)  # fmt: skip


def test_target_all_as_a_process_sections_and_refusals(tmp_path: Path, axes_csv: Path) -> None:
    """The command a user types: one section per target on stdout; a file without an error
    column is refused with its header."""
    done = gateway("fit", axes_csv, "--method", "mlr", "--target", "all",
                   "--store", tmp_path / "s", "--no-progress")  # fmt: skip
    assert done.returncode == 0, done.stderr
    for k, target in enumerate(TARGETS, start=1):
        assert f"=== target {target} ({k} of 3) ===" in done.stdout
        assert f"saved mlr-{target}-all" in done.stdout
    assert "note: y_um: skipped 1 row(s)" in done.stderr
    bare = tmp_path / "bare.csv"
    bare.write_text("run,time_s,speed_rpm,T1,error\nR1,0,0,20,1\n", encoding="utf-8")
    refused = gateway_in_process("fit", bare, "--target", "all", "--store", tmp_path / "b")
    assert refused.returncode == 2
    assert "--target all: no error column" in refused.stderr and "bare.csv" in refused.stderr


def test_one_store_of_every_target_gives_one_bank_per_axis(tmp_path: Path, axes_csv: Path) -> None:
    """``fit --target all --store`` writes each target's model into one store: the single-axis
    bank refuses the mix as before, an axis's bank holds its own target's model only."""
    from gateway.live.bank.model_bank import ModelBank

    store = tmp_path / "models"
    fitted = gateway_in_process("fit", axes_csv, "--method", "mlr", "--target", "all",
                                "--store", store, "--no-progress")  # fmt: skip
    assert fitted.returncode == 0, fitted.stderr
    assert sorted(p.stem for p in store.glob("*.json")) == [f"mlr-{t}-all" for t in TARGETS]
    with pytest.raises(ValueError, match="its models predict different targets"):
        ModelBank.from_store(store)
    for target in TARGETS:
        bank = ModelBank.from_store(store, target=target)
        assert list(bank.models) == [f"mlr-{target}-all"] and bank.target.name == target
    with pytest.raises(ValueError, match=f"model store {store}: no model predicts target q_um"):
        ModelBank.from_store(store, target="q_um")


def test_a_progress_bar_names_each_target(tmp_path: Path, axes_csv: Path) -> None:
    done = gateway_in_process("fit", axes_csv, "--method", "mlr", "--target", "x_um",
                              "--target", "z_um", "--store", tmp_path, "--progress")  # fmt: skip
    assert done.returncode == 0, done.stderr
    bars = done.stderr.replace("\r", "\n")
    assert "target x_um:" in bars and "target z_um: 100%" in bars and "2/2" in bars
    assert "held-out folds" in bars  # each target's own bars, below the targets' bar


def axis_machine(store: Path) -> Any:
    """A machine reading T1 … T7 (one Modbus TCP module) whose models are in ``store``."""
    from gateway.config import MachineSection

    link = {"host": "127.0.0.1", "port": 1}
    channels = [f"T{i}" for i in range(1, 8)]
    bus = {"name": "b", "tcp": link, "devices": [{"device_id": 1, "channels": channels}]}
    return MachineSection.model_validate(
        {
            "id": "vmc-axes",
            "cycle_s": 30.0,
            "transmitters": [bus],
            "cnc": {"modbus": link},
            "compensation": {"macro": 500, "unit": "mm", "clamp_um": 50.0},
            "models": {"store": str(store), "regimes": {"fallback_model": "mlr-z_um-all"}},
        }
    )


def test_an_axis_bank_takes_its_own_promoted_model_and_leaves_the_others(
    tmp_path: Path, axes_csv: Path
) -> None:
    """Two axes' augmented models promoted for one machine: the z_um bank serves its own and
    neither takes nor refuses x_um's (which stays promoted for the x_um bank)."""
    from gateway.live.bank.model_bank import ModelBank
    from gateway.live.bank.promotion import Promotions
    from models.analysis import augmented
    from models.online.proposals import PROMOTED, ProposalStore

    store, found = tmp_path / "models", tmp_path / "analysed"
    pair = ("--target", "x_um", "--target", "z_um", "--no-progress")
    for command in (("fit", "--method", "mlr", "--store", store),
                    ("analyze", "--model", "mlr", "--store", found)):  # fmt: skip
        done = gateway_in_process(command[0], axes_csv, *pair, *command[1:])
        assert done.returncode == 0, done.stderr
    proposals = ProposalStore(store)
    published = {}
    for path in sorted((found / augmented.FOLDER).glob("*.json")):
        document = {**augmented.load(path), "model_id": f"promoted-{path.stem}"}
        document.pop("signature", None)  # a new model: signed when it is published
        document = augmented.sealed(document)
        target = document["target"]["name"]
        published[target] = proposals.publish(
            machine_id="vmc-axes", effect="thermal_lag", params={}, before_rmse_um=1.0,
            after_rmse_um=0.9, probe_rows=40, document=document,
        )  # fmt: skip
        proposals.versions.promote(published[target].id)
    assert sorted(published) == ["x_um", "z_um"]
    machine = axis_machine(store)
    for target, other in (("z_um", "x_um"), ("x_um", "z_um")):
        bank = ModelBank.from_store(store, target=target)
        outcome = Promotions(machine, running=True).load(bank)
        assert outcome.refused == {}, outcome.refused
        assert outcome.swapped == [published[target].model_id]
        assert bank.serving(f"mlr-{target}-all") == published[target].model_id
        assert proposals.get(published[other].id).status == PROMOTED
    # The live loop's one bank of every axis (several targets) takes both, each in its
    # axis's own place: promoted for every regime, neither takes the other's.
    bank = ModelBank.from_store(store, several_targets=True)
    outcome = Promotions(machine, running=True).load(bank)
    assert outcome.refused == {}, outcome.refused
    assert sorted(outcome.swapped) == sorted(p.model_id for p in published.values())
    for target in ("z_um", "x_um"):
        assert bank.serving(f"mlr-{target}-all") == published[target].model_id
        served = bank.usable(f"mlr-{target}-all", set(bank.get(f"mlr-{target}-all").sensors),
                             target)  # fmt: skip
        assert served is not None and served.model_id == published[target].model_id


def test_analyze_writes_each_targets_report_in_its_own_folder(
    tmp_path: Path, axes_csv: Path
) -> None:
    done = gateway_in_process("analyze", axes_csv, "--model", "mlr", "--target", "x_um",
                              "--target", "z_um", "--report", tmp_path / "report",
                              "--no-progress")  # fmt: skip
    assert done.returncode == 0, done.stderr
    for target in ("x_um", "z_um"):
        page = tmp_path / "report" / target / "index.html"
        assert page.is_file() and f"wrote {page}" in done.stdout
        assert target in page.read_text(encoding="utf-8")
