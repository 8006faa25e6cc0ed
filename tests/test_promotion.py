"""Promotion and rollback of a proposed model into a running gateway, over the real protocols.

The simulated machine serves its transmitters (an RTU bus on a socat pty pair,
or Modbus TCP) and its CNC (OPC UA or Modbus TCP); the gateway's loop runs on a
manual clock, cycle by cycle. A proposal (the augmented model ``analyze``
makes of data with a hidden thermal lag) is published into the machine's
store while the loop runs, then promoted from another process (``python -m
gateway models promote``) or by an operator through the SCADA method, with
asyncua's client over SignAndEncrypt. The bank must take it within a cycle,
warm, and give it back on rollback; a model the machine cannot run is refused
and the model in use stays.
"""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

from drivers.clock import ManualClock
from gateway.config import (
    CompensationSection,
    GatewayConfig,
    ModelsSection,
    OnlineCorrectionSection,
)
from gateway.demo.compensate import machine_config
from gateway.live.bank.lag_state import WarmLags
from gateway.live.loop import MachineLoop
from gateway.wiring import Gateway, build_buses, build_cnc, load_bank
from models.analysis import augmented
from models.online.proposals import PROMOTED, REJECTED, Proposal, ProposalStore
from models.online.streaming import StreamingAugmented
from simulator.params import load_params
from simulator.programs import SpeedProgram, program_by_name
from simulator.record import DEFAULT_PROGRAMS, record, write_recording
from tests import gateway_rig as rig
from tests.cli import gateway, gateway_in_process
from tests.ports import free_tcp_port
from tests.test_closed_loop import assert_every_write_was_safe, closed_loop, run_for

MACHINE = "vmc-demo"  # the machine closed_loop runs
PROGRAM = SpeedProgram(
    "busy", tuple((1200.0, float(s)) for s in (6000, 2000, 7000, 3000, 6500, 1500, 5000, 4000))
)


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo's plain models (per regime, all runs, without each sensor)."""
    return rig.fit_store(tmp_path_factory.mktemp("promotion"))


@pytest.fixture(scope="module")
def lag_document(tmp_path_factory: pytest.TempPathFactory, models_dir: Path) -> dict[str, Any]:
    """What the residual analysis makes of runs with a hidden thermal lag and speed effect."""
    folder = tmp_path_factory.mktemp("analysis")
    data = folder / "hidden.csv"
    programs = [program_by_name(name) for name in DEFAULT_PROGRAMS]
    write_recording(data, record(load_params(), programs, ["thermal_lag", "speed_direct"], seed=2))
    done = gateway_in_process("analyze", data, "--model", "mlr", "--store", folder / "store")
    assert done.returncode == 0, done.stderr
    (path,) = (folder / "store" / augmented.FOLDER).glob("*.json")
    document = augmented.load(path)
    assert any(e["effect"] == "thermal_lag" for e in document["effects"])
    assert not StreamingAugmented(document).uses_ambient  # the gateway reads no ambient here
    return document


def demo_models(store: Path) -> ModelsSection:
    """The ``models`` section closed_loop's machine has (the demo's), for ``store``."""
    link = {"host": "127.0.0.1", "port": 1}
    bus = {"name": "b", "tcp": link, "devices": [{"device_id": 1, "channels": ["T1"]}]}
    return machine_config(store, transmitters=[bus], cnc={"modbus": link}, cycle_s=30.0).models


def fresh_store(tmp_path: Path, models_dir: Path) -> Path:
    store = tmp_path / "models"
    shutil.copytree(models_dir, store)
    return store


def publish(store: Path, document: dict[str, Any], machine: str = MACHINE) -> Proposal:
    lag = next(e for e in document["effects"] if e["effect"] == "thermal_lag")
    return ProposalStore(store).publish(
        machine_id=machine,
        effect="thermal_lag",
        params=lag["params"],
        before_rmse_um=document["provenance"]["before"]["rmse_um"],
        after_rmse_um=document["provenance"]["after"]["rmse_um"],
        probe_rows=48,
        document=document,
    )


def needing(document: dict[str, Any], sensor: str, model_id: str) -> dict[str, Any]:
    """The same model with its lag terms on ``sensor`` in place of its last effect sensor."""
    changed = json.loads(json.dumps(document))
    changed["effect_sensors"][-1] = sensor
    changed["model_id"] = model_id
    changed.pop("signature", None)  # a new model: signed when it is published
    return augmented.sealed(changed)


def rises_of(record: Any, reference_C: dict[str, float]) -> dict[str, float]:
    good = {n: t for n, t in record.temperatures_C.items() if t is not None}
    return {n: t - reference_C[n] for n, t in good.items() if record.quality[n] == "good"}


def test_cli_promotion_swaps_in_warm_and_rollback_restores(
    tmp_path: Path, models_dir: Path, lag_document: dict[str, Any]
) -> None:
    store = fresh_store(tmp_path, models_dir)
    model_id = lag_document["model_id"]
    outcome: dict[str, Any] = {}

    # The online correction on, fed by the simulator's probe cycle (macro #600, every 300 s).
    compensation = CompensationSection(
        macro=500, unit="mm", clamp_um=50.0, slew_um_per_min=20.0, probe_macro=600
    )
    online = {
        "compensation": compensation,
        "online_correction": OnlineCorrectionSection(enabled=True),
    }

    async def scenario() -> None:
        async with closed_loop(tmp_path, store, PROGRAM, update=online) as (closed, clock):
            loop = closed.loop
            await run_for(closed, clock, 3600.0)  # an hour of plain models: the machine is warm
            assert model_id not in {r.model_id for r in closed.trace.records}
            assert loop.online is not None and loop.online.accepted >= 5
            proposal = publish(store, lag_document)
            listed = await asyncio.to_thread(
                gateway, "models", "proposals", "--store", store, "--json"
            )
            assert listed.returncode == 0, listed.stderr
            assert [p["id"] for p in json.loads(listed.stdout)] == [proposal.id]
            await closed.step(clock)
            assert closed.trace.records[-1].model_id != model_id  # nothing without an operator

            done = await asyncio.to_thread(
                gateway, "models", "promote", proposal.id, "--store", store
            )
            assert done.returncode == 0, done.stderr
            assert "version 1" in done.stdout
            promoted_at = len(closed.trace.records)
            await closed.step(clock)  # the next cycle already runs the promoted model
            assert closed.trace.records[-1].model_id == model_id
            # The correction learnt the old model's residual: it starts again from zero.
            assert closed.trace.records[-2].correction_um != 0.0
            assert closed.trace.records[-1].correction_um == 0.0 and loop.online.accepted == 0
            assert loop.promotions.swaps == 1 and loop.promotions.version == 1
            await run_for(closed, clock, 1800.0)
            assert {r.model_id for r in closed.trace.records[promoted_at:]} == {model_id}

            done = await asyncio.to_thread(gateway, "models", "rollback", "--store", store)
            assert done.returncode == 0, done.stderr
            rolled_at = len(closed.trace.records)
            await run_for(closed, clock, 600.0)
            outcome.update(
                closed=closed,
                promoted_at=promoted_at,
                rolled_at=rolled_at,
                reference_C=dict(loop.reference.values_C),
                swaps=loop.promotions.swaps,
                in_bank=model_id in loop.bank,
            )
            assert_every_write_was_safe(closed)  # clamp and slew held through both swaps

    asyncio.run(scenario())
    records = outcome["closed"].trace.records
    promoted_at, rolled_at = outcome["promoted_at"], outcome["rolled_at"]
    assert outcome["swaps"] == 2 and not outcome["in_bank"]
    assert model_id not in {r.model_id for r in records[rolled_at:]}
    assert ProposalStore(store).get("P0001").status == REJECTED

    # Warm: the promoted model predicts what it would have, had it been stepped from the
    # first cycle on; started cold at the promotion it would have been far off.
    warm, cold = StreamingAugmented(lag_document), StreamingAugmented(lag_document)
    warm_um, cold_um, served_um = [], [], []
    for i, r in enumerate(records[:rolled_at]):
        rises = rises_of(r, outcome["reference_C"])
        expected = warm.step(r.time_s, rises, r.speed_rpm)
        if i >= promoted_at:
            assert r.model_id == model_id
            served_um.append(r.predicted_um)
            warm_um.append(expected)
            cold_um.append(cold.step(r.time_s, rises, r.speed_rpm))
    # Identical when every input was read every cycle; a cycle that missed one (a serial
    # timeout) held the whole stream but only that input's warm lag
    # (gateway/live/bank/lag_state.py).
    needed = StreamingAugmented(lag_document).sensors
    seen = [set(needed) & set(rises_of(r, outcome["reference_C"])) for r in records]
    complete = all(len(got) in (0, len(needed)) for got in seen)
    atol_um = 1e-9 if complete else 0.1
    np.testing.assert_allclose(served_um, warm_um, rtol=0, atol=atol_um)
    assert np.max(np.abs(np.array(warm_um) - np.array(cold_um))) > 0.5


def test_a_model_the_machine_cannot_run_is_refused_and_the_old_one_stays(
    tmp_path: Path, models_dir: Path, lag_document: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    store = fresh_store(tmp_path, models_dir)
    model_id = lag_document["model_id"]
    good = publish(store, lag_document)
    bad = publish(store, needing(lag_document, "T12", "needs-t12"))

    # Checked against the machine's configuration, the command line refuses it at once.
    config = tmp_path / "config.yaml"
    plant = rig.plant(ManualClock(), cnc=("modbus",))
    entry = rig.machine_entry(MACHINE, plant, store)
    config.write_text(yaml.safe_dump({"machines": [entry], "state_dir": str(tmp_path / "s")}))
    refused = gateway_in_process("models", "promote", bad.id, "--config", config)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        "error: it needs sensor(s) ['T12'] that no transmitter channel of machine vmc-demo "
        f"provides (channels: {sorted(rig.SENSORS)})"
    ]
    assert ProposalStore(store).versions.current().number == 0

    async def scenario() -> None:
        async with closed_loop(tmp_path / "loop", store, PROGRAM) as (closed, clock):
            loop = closed.loop
            await run_for(closed, clock, 600.0)
            ProposalStore(store).versions.promote(good.id, by="test")
            await closed.step(clock)
            assert closed.trace.records[-1].model_id == model_id
            # Promoted without the machine's check (--store): the loop itself refuses it.
            done = await asyncio.to_thread(gateway, "models", "promote", bad.id, "--store", store)
            assert done.returncode == 0, done.stderr
            with caplog.at_level(logging.ERROR, logger="gateway.live.bank.promotion"):
                await run_for(closed, clock, 300.0)
            assert {r.model_id for r in closed.trace.records[-10:]} == {model_id}
            assert "needs-t12" not in loop.bank
            assert (loop.promotions.swaps, loop.promotions.refused) == (1, 1)
            assert_every_write_was_safe(closed)

    (tmp_path / "loop").mkdir()
    asyncio.run(scenario())
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert any("needs-t12" in e and "needs sensor(s) ['T12']" in e for e in errors), errors
    # The store says what the machine runs: the refused model, and the one it kept serving.
    proposals = ProposalStore(store)
    assert proposals.get(bad.id).status == "refused"
    assert (
        "machine vmc-demo refused it: it needs sensor(s) ['T12']"
        in (proposals.get(bad.id).history[-1]["note"])
    )
    assert proposals.get(good.id).status == "promoted"
    assert proposals.get(good.id).history[-1]["note"] == (
        f"machine vmc-demo still runs it: it refused {bad.id}"
    )


def test_a_check_of_the_configuration_reads_the_promoted_set_and_writes_nothing(
    tmp_path: Path, models_dir: Path, lag_document: dict[str, Any]
) -> None:
    """Only the running loop records a refusal in the store; check-config only looks."""
    store = fresh_store(tmp_path, models_dir)
    bad = publish(store, needing(lag_document, "T12", "needs-t12"))
    assert gateway_in_process("models", "promote", bad.id, "--store", store).returncode == 0
    config = tmp_path / "config.yaml"
    entry = rig.machine_entry(MACHINE, rig.plant(ManualClock(), cnc=("modbus",)), store)
    config.write_text(yaml.safe_dump({"machines": [entry], "state_dir": str(tmp_path / "s")}))
    before = (store / "proposals" / f"{bad.id}.json").read_bytes()
    checked = gateway_in_process("check-config", "--config", config)
    assert checked.returncode == 0, checked.stderr
    assert "models version 1" in checked.stdout
    assert (store / "proposals" / f"{bad.id}.json").read_bytes() == before
    assert ProposalStore(store).get(bad.id).status == PROMOTED


# -- over SCADA ----------------------------------------------------------------------------

OPERATOR = ("alice", "op-secret-1")
VIEWER = ("victor", "view-secret-2")


def scada_gateway(tmp_path: Path) -> dict[str, Any]:
    """The gateway-wide sections of a config with SCADA on: an operator and a viewer
    (their password files in ``tmp_path``), state and points in ``tmp_path``."""
    secrets = {}
    for name, password in (OPERATOR, VIEWER):
        secrets[name] = tmp_path / f"{name}.secret"
        secrets[name].write_text(password + "\n")
    return {
        "state_dir": str(tmp_path / "state"),
        "logging": {"local_store": str(tmp_path / "points.sqlite")},
        "scada": {
            "port": free_tcp_port(),
            "pki_dir": str(tmp_path / "pki"),
            "users": [
                {
                    "username": OPERATOR[0],
                    "password_file": str(secrets[OPERATOR[0]]),
                    "role": "operator",
                },
                {"username": VIEWER[0], "password_file": str(secrets[VIEWER[0]])},
            ],
        },
    }


def scada_config(tmp_path: Path, store: Path, plant: Any) -> GatewayConfig:
    entry = rig.machine_entry(MACHINE, plant, store, cycle_s=30.0)
    entry["sensors"] = {name: {"max_rate_C_per_s": 50.0, "stale_s": 120.0} for name in rig.SENSORS}
    return GatewayConfig.model_validate({"machines": [entry], **scada_gateway(tmp_path)})


async def scada_client(endpoint: str, pki_dir: Path, folder: Path, user: tuple[str, str]) -> Client:
    """asyncua's client over SignAndEncrypt, its certificate trusted by the gateway."""
    folder.mkdir(parents=True, exist_ok=True)
    cert, key = folder / "client_cert.der", folder / "client_key.pem"
    client = Client(endpoint, timeout=10)
    await setup_self_signed_certificate(
        key, cert, client.application_uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {}
    )
    shutil.copy(cert, pki_dir / "trusted" / f"{folder.name}.der")
    await client.set_security(
        SecurityPolicyBasic256Sha256,
        str(cert),
        str(key),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )
    client.set_user(user[0])
    client.set_password(user[1])
    await client.connect()
    return client


def test_scada_operator_promotes_and_rolls_back_viewer_is_refused(
    tmp_path: Path, models_dir: Path, lag_document: dict[str, Any]
) -> None:
    store = fresh_store(tmp_path, models_dir)
    model_id = lag_document["model_id"]
    clock = ManualClock()
    plant = rig.plant(clock, program="const8000", cnc=("modbus",))

    async def scenario() -> None:
        await plant.start()
        config = scada_config(tmp_path, store, plant)
        app = Gateway(config, clock=clock)
        loop = app.loops[0]
        assert app.scada is not None
        await app.scada.start()
        operator = viewer = None
        try:

            async def cycle() -> Any:
                clock.advance(30.0)
                await plant.update()
                record = await loop.run_cycle()
                await asyncio.sleep(0.05)  # the SCADA publish tasks of the cycle
                return record

            for _ in range(20):
                await cycle()
            proposal = publish(store, lag_document)
            await cycle()

            ns = app.scada.namespace_index
            viewer = await scada_client(
                app.scada.endpoint, config.scada.pki_dir, tmp_path / "v", VIEWER
            )
            operator = await scada_client(
                app.scada.endpoint, config.scada.pki_dir, tmp_path / "o", OPERATOR
            )
            machine = viewer.get_node(ua.NodeId(MACHINE, ns))

            def node(name: str) -> Any:
                return viewer.get_node(ua.NodeId(f"{MACHINE}.{name}", ns))

            assert await node("Proposals.NewestId").read_value() == proposal.id
            assert await node("Proposals.NewestEffect").read_value() == "thermal_lag"
            assert await node("Proposals.NewestAfterUm").read_value() == pytest.approx(
                proposal.after_rmse_um
            )
            opened = json.loads(await node("Proposals.OpenJson").read_value())
            assert [p["id"] for p in opened] == [proposal.id]
            assert "document" not in opened[0]

            promote = ua.NodeId(f"{MACHINE}.PromoteProposal", ns)
            rollback = ua.NodeId(f"{MACHINE}.RollbackModels", ns)
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await machine.call_method(promote, proposal.id)
            assert refused.value.code == ua.StatusCodes.BadUserAccessDenied
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await machine.call_method(rollback)
            assert refused.value.code == ua.StatusCodes.BadUserAccessDenied
            assert ProposalStore(store).get(proposal.id).status == "proposed"

            as_operator = operator.get_node(ua.NodeId(MACHINE, ns))
            with pytest.raises(ua.UaStatusCodeError) as unknown:
                await as_operator.call_method(promote, "P0042")
            assert unknown.value.code == ua.StatusCodes.BadNotFound
            result = await as_operator.call_method(promote, proposal.id)
            assert "version 1" in result and proposal.id in result
            record = await cycle()
            assert record.model_id == model_id
            await cycle()
            assert await node("Proposals.ModelsVersion").read_value() == 1
            assert await node("Proposals.NewestStatus").read_value() == PROMOTED
            assert await node("ModelId").read_value() == model_id
            assert await node("Health.ModelSwaps").read_value() == 1
            with pytest.raises(ua.UaStatusCodeError) as again:  # promoted already
                await as_operator.call_method(promote, proposal.id)
            assert again.value.code == ua.StatusCodes.BadInvalidState
            assert "is promoted" in await node("Proposals.LastAction").read_value()

            result = await as_operator.call_method(rollback)
            assert "version 2" in result
            record = await cycle()
            assert record.model_id != model_id and model_id not in loop.bank
            await cycle()
            assert await node("Proposals.ModelsVersion").read_value() == 2
            assert await node("Health.ModelSwaps").read_value() == 2
            assert await node("Proposals.OpenCount").read_value() == 0
        finally:
            for client in (operator, viewer):
                if client is not None:
                    await client.disconnect()
            await app.scada.stop()
            await loop.close()
            await plant.stop()

    asyncio.run(scenario())


async def run_with_auto_promote(
    tmp_path: Path, store: Path, document: dict[str, Any], auto: bool
) -> list[str | None]:
    """Publish a proposal into a running loop; the models of the last three cycles."""
    models = demo_models(store).model_copy(update={"auto_promote": auto})
    async with closed_loop(tmp_path, store, PROGRAM, update={"models": models}) as (closed, clock):
        assert closed.loop.promotions.auto_promote is auto
        await run_for(closed, clock, 300.0)
        publish(store, document)
        await run_for(closed, clock, 120.0)
        return [r.model_id for r in closed.trace.records[-3:]]


def test_auto_promote_only_when_the_config_says_so(
    tmp_path: Path, models_dir: Path, lag_document: dict[str, Any]
) -> None:
    """``models.auto_promote: true`` promotes a new proposal at the next cycle; the
    default (false) leaves it waiting for an operator."""
    model_id = lag_document["model_id"]
    assert ModelsSection(store=tmp_path).auto_promote is False
    for auto in (False, True):
        folder = tmp_path / str(auto)
        store = fresh_store(folder, models_dir)
        (folder / "loop").mkdir()
        served = asyncio.run(run_with_auto_promote(folder / "loop", store, lag_document, auto))
        status = ProposalStore(store).get("P0001").status
        if auto:
            assert served[-2:] == [model_id, model_id] and status == PROMOTED
        else:
            assert model_id not in served and status == "proposed"


def test_warm_lags_give_a_new_stream_the_state_of_one_stepped_from_the_start(
    lag_document: dict[str, Any],
) -> None:
    """Pure arithmetic: the same recursion, so the same numbers; and the state survives a save."""
    rng = np.random.default_rng(3)
    sensors = [f"T{i}" for i in range(1, 10)]
    warm = WarmLags(sensors, None)
    from_start = StreamingAugmented(lag_document)
    time_s, rises = 0.0, dict.fromkeys(sensors, 0.0)
    for k in range(2000):
        time_s += float(rng.uniform(20.0, 40.0)) + (1500.0 if k % 700 == 699 else 0.0)  # gaps
        rises = {s: v + float(rng.normal(0.0, 0.05)) + 0.01 for s, v in rises.items()}
        speed = 1000.0 * (k // 200 % 7)
        warm.step(time_s, rises, speed)
        from_start.step(time_s, rises, speed)
    restored = WarmLags(sensors, None)
    restored.import_state(json.loads(json.dumps(warm.export_state())))
    late = StreamingAugmented(lag_document)
    state, why = restored.state_for(late)
    assert state is not None, why
    late.import_state(state)
    time_s += 1500.0  # the promoted model's first step crosses a gap, the rises moved in it
    rises = {s: v + 1.0 for s, v in rises.items()}
    for _ in range(100):
        time_s += 30.0
        expected = from_start.step(time_s, rises, 4000.0)
        assert late.step(time_s, rises, 4000.0) == pytest.approx(expected, abs=1e-9)
    off_grid = json.loads(json.dumps(lag_document))
    next(e for e in off_grid["effects"] if e["effect"] == "thermal_lag")["params"]["tau_s"] = 1234
    state, why = warm.state_for(StreamingAugmented(off_grid))
    assert state is None and "1234 s is not a searched time constant" in why


def test_a_restarted_loop_starts_with_the_promoted_set(
    tmp_path: Path, models_dir: Path, lag_document: dict[str, Any]
) -> None:
    store = fresh_store(tmp_path, models_dir)
    ProposalStore(store).versions.promote(publish(store, lag_document).id, by="test")
    plant = rig.plant(ManualClock(), cnc=("modbus",))
    machine = GatewayConfig.model_validate(
        {"machines": [rig.machine_entry(MACHINE, plant, store)]}
    ).machines[0]
    bank = load_bank(machine)
    assert bank.serving("mlr-error_um-variable") == lag_document["model_id"]
    loop = MachineLoop(machine, ManualClock(), build_buses(machine), build_cnc(machine), bank)
    assert loop.promotions.version == 1 and loop.promotions.swaps == 0
    assert [m.model_id for m in loop.effects.models] == [lag_document["model_id"]]
    done = gateway_in_process("check-config", "--config", write_machine_config(tmp_path, machine))
    assert done.returncode == 0, done.stderr
    assert "models version 1, 0 open proposal(s) (promoted by an operator only)" in done.stdout


def write_machine_config(tmp_path: Path, machine: Any) -> Path:
    path = tmp_path / "config.yaml"
    document = {
        "machines": [machine.model_dump(mode="json", exclude_none=True)],
        "state_dir": str(tmp_path / "state"),
        "logging": {"local_store": str(tmp_path / "points.sqlite")},
    }
    path.write_text(yaml.safe_dump(document))
    return path
