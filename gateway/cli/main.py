"""Command line: ``python -m gateway COMMAND …``.

Commands stay thin: they parse options, call ``models``, and print tables that
``gateway.offline.tables`` formats. Any input problem ends with one line on stderr that
says where it is and what was expected, and exit status 2.

At module level this file imports only click, the standard library and
``models.catalogue`` (plain names and numbers): numpy, scipy, pandas, sklearn,
matplotlib and the protocol libraries load inside the command that needs them,
so ``--help`` and the container's health check start in a fraction of a second
(benchmarks/cli_start.py, tests/test_cli_start.py).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from gateway import __version__
from gateway.cli.options import (
    FiniteFloatRange,
    config_option,
    input_errors_exit,
    json_option,
    log_level_option,
    parse_sensors,
    progress_option,
    quantity_option,
    reference_option,
    report_skipped,
    sensors_option,
    store_option,
    target_option,
    targets_option,
    write_json,
)
from models.catalogue import (
    DEFAULT_MAX_BIAS_ERROR_UM,
    DEFAULT_METHOD,
    DEFAULT_REPLAY_BASE,
    DEFAULT_SENSOR_ACCURACY_C,
    METHOD_NAMES,
    POLICIES,
)

T = TypeVar("T")

if TYPE_CHECKING:
    from gateway.config import GatewayConfig
    from simulator.serve import SimulatedPlant


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="gateway")
def main() -> None:
    """Spindle thermal-error gateway: fit, rank and store compensation models."""


def method_option(flag: str, help: str, also: tuple[str, ...] = ()) -> Callable[..., Any]:
    """``--method`` (fit) or ``--model`` (analyze, replay): a fitting method by name, into
    the command's ``method`` parameter; ``also``: choices the command adds (``auto``)."""
    return click.option(
        flag,
        "method",
        type=click.Choice((*METHOD_NAMES, *also)),
        default=DEFAULT_METHOD,
        show_default=True,
        help=help,
    )


@main.command()
@click.argument("data_csv", type=click.Path(path_type=Path))
@method_option(
    "--method", "The fitting method; the papers' methods (mlr, grey-mlr, pca-quadratic) by name."
)
@targets_option()
@sensors_option()
@click.option("--per-run", is_flag=True, help="One model per run, cross-evaluated on every run.")
@click.option("--regime-column", help="Column that labels each run's speed regime.")
@reference_option(POLICIES)
@store_option("The model store the fitted models are saved to.", required=True)
@json_option()
@progress_option()
@quantity_option(
    "--sensor-accuracy-C",
    DEFAULT_SENSOR_ACCURACY_C,
    "Stated accuracy of the temperature sensors, ± °C, for the bias sensitivity.",
    name="sensor_accuracy_C",
)
@quantity_option(
    "--max-bias-error-um",
    DEFAULT_MAX_BIAS_ERROR_UM,
    "Warn when one sensor off by its accuracy moves the compensation by more (µm).",
)
@click.option(
    "--collinearity",
    type=click.Choice(["short", "full"]),
    default="short",
    show_default=True,
    help="short: the condition number and the worst VIFs; full: every input's VIF and bias "
    "sensitivity (the JSON always holds every input).",
)
@input_errors_exit
def fit(
    data_csv: Path,
    method: str,
    targets: tuple[str, ...],
    sensors: str | None,
    per_run: bool,
    regime_column: str | None,
    reference: str,
    store_dir: Path,
    json_out: Path | None,
    progress: bool | None,
    sensor_accuracy_C: float,
    max_bias_error_um: float,
    collinearity: str,
) -> None:
    """Fit METHOD on DATA_CSV, validate it on held-out runs and save it to the store."""
    if per_run and regime_column:
        raise click.UsageError("--per-run and --regime-column exclude each other")
    chosen, data, sensor_list = _load_targets(data_csv, targets, sensors)
    from models.data.recording_checks import refuse_constant_target
    from models.data.targets import view

    for target in chosen:
        refuse_constant_target(view(data, target, sensor_list))
    # The fitting stack (scipy, scikit-learn) only once the file is known good.
    from gateway.offline.fit import FitRequest, run_fit_targets

    request = _request(
        FitRequest,
        (data_csv, method, chosen[0], sensor_list, reference, progress),
        store_dir=store_dir,
        per_run=per_run,
        regime_column=regime_column,
        sensor_accuracy_C=sensor_accuracy_C,
        max_bias_error_um=max_bias_error_um,
        collinearity=collinearity,
    )
    write_json(json_out, run_fit_targets(data, chosen, request, click.echo, _warn))


def _warn(text: str) -> None:
    click.echo(text, err=True)


def _load_targets(
    data_csv: Path, targets: tuple[str, ...], sensors: str | None, sparse_target: bool = False
) -> tuple[list[str], Any, list[str] | None]:
    """The targets (``all`` expanded), the runs of DATA_CSV read once with every target
    (:func:`_load_reported`) and the --sensors list."""
    from models.data.targets import chosen_targets

    chosen = chosen_targets(data_csv, targets)
    data, sensor_list = _load_reported(data_csv, chosen, sensors, sparse_target)
    return chosen, data, sensor_list


def _load_reported(
    data_csv: Path, target: str | list[str], sensors: str | None, sparse_target: bool = False
) -> tuple[Any, list[str] | None]:
    """The runs of DATA_CSV (skipped rows, notes and remarks on the whole recording said on
    stderr) and the --sensors list; several targets: read once with all of them."""
    from models.data.recording_checks import recording_remarks
    from models.data.targets import load_targets

    sensor_list = parse_sensors(sensors)
    targets = [target] if isinstance(target, str) else target
    data = load_targets(data_csv, targets, sensor_list, sparse_target)
    report_skipped(data)
    for remark in recording_remarks(data):
        _warn(f"warning: {remark}")
    return data, sensor_list


def _request(make: Callable[..., T], common: tuple[Any, ...], **options: Any) -> T:
    """An offline command's request: the options every such command has (DATA_CSV,
    method, target, sensors, reference, progress: its first fields) and its own ``options``."""
    *named, progress = common
    return make(*named, sys.stderr.isatty() if progress is None else progress, **options)


@main.command()
@click.argument("sigma_csv", type=click.Path(path_type=Path))
@json_option("Write the ranking.")
@click.option(
    "--tolerance-pct",
    type=FiniteFloatRange(min=0.0),
    default=1.0,
    show_default=True,
    help="Accuracies closer than this (%) are tied; robustness (SD) decides.",
)
@input_errors_exit
def regimes(sigma_csv: Path, json_out: Path | None, tolerance_pct: float) -> None:
    """Rank per-regime models from their cross-evaluation σ table (paper 002)."""
    from models.fit.ranking import format_report, rank_regimes, read_sigma_csv

    report = rank_regimes(read_sigma_csv(sigma_csv), tolerance_pct=tolerance_pct)
    click.echo(format_report(report))
    write_json(json_out, report.as_json())


@main.command()
@click.argument("data_csv", type=click.Path(path_type=Path))
@sensors_option("Temperature columns to test (default: every T<n>).")
@click.option("--alpha", type=FiniteFloatRange(0.0, 1.0, min_open=True), default=0.05)
@quantity_option("--band-rpm", 100.0, "Speeds are grouped to the nearest multiple of this, r/min.")
@target_option()
@json_option()
@input_errors_exit
def significance(
    data_csv: Path,
    sensors: str | None,
    alpha: float,
    band_rpm: float,
    target: str,
    json_out: Path | None,
) -> None:
    """Does spindle speed change the temperatures? MANOVA + per-sensor ANOVA (paper 000)."""
    from models.fit.significance import anova_oneway, format_table, manova_oneway, speed_groups

    data, sensor_list = _load_reported(data_csv, target, sensors)
    groups = speed_groups(data.speed_rpm, band_rpm)
    values = data.temperatures(sensor_list)
    names = sensor_list or list(data.sensors)
    manova = manova_oneway(values, groups, alpha=alpha)
    anova = anova_oneway(values, groups, names, alpha=alpha)
    click.echo(f"{data_csv.name}: {data.n_samples} samples in {manova.n_groups} speed groups")
    click.echo(format_table(manova, anova))
    write_json(
        json_out, {"manova": manova.as_dict(), "anova": [result.as_dict() for result in anova]}
    )


@main.command()
@click.option("--record", "record_path", type=click.Path(path_type=Path), help="Write runs here.")
@click.option(
    "--program",
    "programs",
    multiple=True,
    help="Speed programme (repeatable): iso230-spectrum, spectrum-swapped, spectrum-const4000, "
    "const2000, const4000, const6000, const8000 or production-<seed>. Default: the first six.",
)
@click.option(
    "--effect",
    "effects",
    multiple=True,
    help="Hidden effect (repeatable): thermal_lag, speed_direct, ambient, drift, cooler or none.",
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@quantity_option("--sample-s", 60.0, "Seconds between the rows written.")
@click.option(
    "--params",
    "params_file",
    type=click.Path(path_type=Path),
    help="YAML overriding the machine's default parameters (simulator/machine.yaml).",
)
@config_option(
    show_default=True, help="Without --record: serve the machine its 'simulator' section describes."
)
@click.option(
    "--probe-period-s",
    type=FiniteFloatRange(min=0, min_open=True),
    help="Machine seconds between probe measurements (overrides config / machine.yaml).",
)
@click.option(
    "--probe-noise-um",
    type=FiniteFloatRange(min=0),
    help="Probe measurement noise, 1 σ in µm (overrides config / machine.yaml).",
)
@input_errors_exit
def simulate(
    record_path: Path | None,
    programs: tuple[str, ...],
    effects: tuple[str, ...],
    seed: int,
    sample_s: float,
    params_file: Path | None,
    config_path: Path,
    probe_period_s: float | None,
    probe_noise_um: float | None,
) -> None:
    """Run the simulated machine: serve it over its protocols, or record runs (--record)."""
    from models.json_files import atomic_text
    from simulator.programs import program_by_name
    from simulator.record import DEFAULT_PROGRAMS, record

    if record_path is None:
        serve_simulator(config_path, probe_period_s, probe_noise_um)
        return
    params = with_probe(load_machine_params(params_file), probe_period_s, probe_noise_um)
    chosen = [program_by_name(name) for name in (programs or DEFAULT_PROGRAMS)]
    recording = record(params, chosen, effects or ("none",), seed=seed, sample_s=sample_s)
    with atomic_text(record_path) as out:  # a full disk leaves no half file behind
        out.write(recording.to_csv())
    runs = ", ".join(p.name for p in chosen)
    click.echo(
        f"wrote {record_path}: {len(recording.rows)} rows, runs {runs}, "
        f"effects {', '.join(effects) or 'none'}, seed {seed}"
    )


def load_machine_params(params_file: Path | None):
    from simulator.params import load_params, load_params_file

    return load_params() if params_file is None else load_params_file(params_file)


def with_probe(params, period_s: float | None, noise_um: float | None):
    """The machine parameters with the probe period and/or noise of the command line."""
    probe = {k: v for k, v in (("period_s", period_s), ("noise_um", noise_um)) if v is not None}
    return params.model_copy(update={"probe": params.probe.model_copy(update=probe)})


def serve_simulator(
    config_path: Path, probe_period_s: float | None = None, probe_noise_um: float | None = None
) -> None:
    from gateway.process import event_loop
    from simulator.serve import SimulatedPlant, load_simulator_config

    config = load_simulator_config(config_path).with_probe(probe_period_s, probe_noise_um)
    plant = SimulatedPlant(config)
    click.echo(
        f"serving simulated machine '{plant.machine.params.name}' (programme {config.program}, "
        f"×{config.speedup:g} machine time); Ctrl-C or SIGTERM stops"
    )
    probe = plant.machine.params.probe
    click.echo(f"  probe #{probe.macro}: every {probe.period_s:g} s, noise {probe.noise_um:g} µm")
    for endpoint in plant.endpoints:
        click.echo(f"  {type(endpoint).__name__}: {describe_endpoint(endpoint)}")
    event_loop.run(_serve_until_signalled(plant))
    click.echo("stopped")


async def _serve_until_signalled(plant: SimulatedPlant) -> None:
    """Serve until SIGINT or SIGTERM, as ``run`` does. Handlers set on the loop also
    replace a SIGINT that the process inherited as ignored (a shell script starting it
    in the background), where the interpreter's own Ctrl-C would never fire."""
    import asyncio
    import signal

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    await plant.serve_until(stop)


def describe_endpoint(endpoint: object) -> str:
    for attribute in ("endpoint", "address", "serial_port"):
        value = getattr(endpoint, attribute, None)
        if value:
            return str(value)
    return ""


def setup_logging(level: str) -> None:
    import logging

    logging.basicConfig(
        level=getattr(logging, level.upper()),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    quiet_protocol_libraries()


def quiet_protocol_libraries() -> None:
    """The drivers report every link failure themselves, once, with the device named."""
    import logging

    for name in ("pymodbus", "asyncua"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


@main.command("check-config")
@config_option()
@click.option("--connect", is_flag=True, help="Also try every CNC and transmitter once.")
@input_errors_exit
def check_config(config_path: Path, connect: bool) -> None:
    """Validate the configuration (and the model stores it names) without running."""
    from gateway.config import load_config
    from gateway.process import event_loop

    quiet_protocol_libraries()
    config = load_config(config_path, check_host=True)
    for line in config.deprecations:
        click.echo(f"warning: {line}", err=True)
    # The runtime (protocol clients, the model stack) only once the file is known good:
    # a bad file is refused in well under a second.
    from gateway.wiring import check_connections, load_located_bank

    for index, machine in enumerate(config.machines):
        bank = load_located_bank(config, index)
        click.echo(
            f"machine {machine.id}: {len(machine.sensor_names)} sensors, "
            f"{len(bank.models)} models in {machine.models.store}{compensated(machine, bank)}, "
            f"{promotion_summary(machine)}, {signing_summary(machine)}"
        )
    if connect:
        problems = event_loop.run(check_connections(config), config.event_loop)
        if problems:
            raise ValueError("; ".join(problems))
        click.echo("every CNC and transmitter answered")
    click.echo(f"{config_path}: ok")


def compensated(machine, bank) -> str:
    """`` (target …), compensation → #500 (mm)``; for ``compensation.axes`` each axis's
    target and macro."""
    comp = machine.compensation
    if comp.axes is None:
        return f" (target {bank.target}), compensation → #{comp.macro} ({comp.unit})"
    from gateway.live.axis import axis_targets

    targets = axis_targets(machine, bank)
    axes = ", ".join(
        f"{name} {targets[name]} → #{axis.macro} ({axis.unit})" for name, axis in comp.axes.items()
    )
    return f", compensation of axes {axes}"


def signing_summary(machine) -> str:
    """Where the key the machine's models are checked with is (models.signing)."""
    from models import signing

    key_file = signing.key_file_for_store(machine.models.store)
    if key_file is None:
        return f"models of {machine.models.store} unsigned (models.signing: false)"
    return f"models signed, signing key {key_file}"


def promotion_summary(machine) -> str:
    """The promoted-models version in force and the open proposals (gateway.live.bank.promotion)."""
    from models.online.proposals import ProposalStore

    store = ProposalStore(machine.models.store)
    opened = [p for p in store.list(machine_id=machine.id) if p.open]
    auto = "auto-promote" if machine.models.auto_promote else "promoted by an operator only"
    return (
        f"models version {store.versions.current().number}, {len(opened)} open proposal(s) ({auto})"
    )


@main.command()
@config_option()
@log_level_option("info")
@input_errors_exit
def run(config_path: Path, log_level: str) -> None:
    """Run the compensation loop for every machine in the configuration."""
    import gc
    import logging

    from gateway.config import load_config
    from gateway.process.instance_lock import StateDirInUseError, hold_state_dir

    setup_logging(log_level)
    config = load_config(config_path, check_host=True)
    for line in config.deprecations:
        logging.getLogger("gateway.config").warning("%s", line)
    try:
        with hold_state_dir(Path(config.state_dir)):
            serve_config(config)
    except StateDirInUseError as exc:
        raise StateDirInUseError(f"{config_path}: {exc}") from None
    # The interpreter's last garbage collection walks every object of the OPC UA
    # address spaces and the models: seconds on an edge box, after the state is
    # saved. Frozen objects are left to the process exit, so a stop takes < 1 s.
    gc.freeze()
    click.echo("stopped")


def serve_config(config: GatewayConfig) -> None:
    """Every machine's loop until SIGINT or SIGTERM (the state folder already held)."""
    import asyncio
    import signal

    from gateway.process import event_loop
    from gateway.wiring import Gateway  # the runtime only once the file is known good

    gateway_app = Gateway(config)

    async def serve() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await gateway_app.run(stop)

    click.echo(
        f"running {len(config.machines)} machine(s): {', '.join(m.id for m in config.machines)}"
    )
    event_loop.run(serve(), config.event_loop)


@main.command()
@json_option("Write the figures as JSON.")
@click.option("--program", default="production-7", show_default=True, help="The unseen programme.")
@click.option("--seed", type=click.IntRange(min=0), default=1, show_default=True)
@click.option("--speedup", type=FiniteFloatRange(min=1), default=400.0, show_default=True)
@click.option("--cycle-s", type=FiniteFloatRange(min=0.1), default=15.0, show_default=True)
@click.option(
    "--workdir", type=click.Path(path_type=Path), default=Path(".cache/demo"), show_default=True
)
@log_level_option("warning")
@click.option(
    "--effect",
    type=click.Choice(["thermal_lag", "speed_direct", "ambient", "drift", "cooler"]),
    help="Hide this effect in the machine (the models lack it): the residual monitor finds it, "
    "the demo promotes its proposal, the compensation runs with it.",
)
@input_errors_exit
def demo(
    json_out: Path | None,
    program: str,
    seed: int,
    speedup: float,
    cycle_s: float,
    workdir: Path,
    log_level: str,
    effect: str | None,
) -> None:
    """Simulate a machine, fit its models, compensate an unseen programme, show the gain."""
    from gateway.demo.compensate import demo as run_demo
    from gateway.process import event_loop

    setup_logging(log_level)
    result = event_loop.run(
        run_demo(
            workdir,
            program=program,
            seed=seed,
            speedup=speedup,
            cycle_s=cycle_s,
            version=__version__,
            say=click.echo,
            effect=effect,
        )
    )
    write_json(json_out, result)


def parse_time_s(value: str | None) -> float | None:
    """An ISO 8601 date/time (UTC unless it says otherwise) or Unix seconds."""
    from datetime import UTC, datetime

    if value is None:
        return None
    try:
        return float(value)
    except ValueError:
        pass
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        raise click.BadParameter(f"'{value}': expected an ISO 8601 time or Unix seconds") from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return moment.timestamp()


@main.command()
@click.argument("out_csv", type=click.Path(path_type=Path))
@click.option("--from", "start", help="Start (ISO 8601 or Unix s); default: the beginning.")
@click.option("--to", "stop", help="End, exclusive (ISO 8601 or Unix s); default: now.")
@click.option("--machine", help="Machine id (default: the only machine in the config).")
@config_option()
@progress_option()
@input_errors_exit
def export(
    out_csv: Path,
    start: str | None,
    stop: str | None,
    machine: str | None,
    config_path: Path,
    progress: bool | None,
) -> None:
    """Write logged data as a measured-run CSV (for fit and analyze)."""
    from gateway.config import load_config
    from gateway.offline.export import ExportError, PointSource, export_runs
    from gateway.outputs.influx import InfluxReader
    from gateway.outputs.local_store import LocalStore

    config = load_config(config_path)
    ids = [m.id for m in config.machines]
    if machine is None:
        if len(ids) != 1:
            raise click.UsageError(f"--machine is needed: the config has {', '.join(ids)}")
        machine = ids[0]
    elif machine not in ids:
        raise click.UsageError(
            f"no machine '{machine}' in {config_path} (machines: {', '.join(ids)})"
        )
    influx = config.logging.influxdb
    source: PointSource
    if influx is not None:
        source = InfluxReader(
            influx.url_value(),
            influx.token(),
            influx.org_value(),
            influx.bucket_value(),
            influx.timeout_s,
        )
        where = f"InfluxDB {influx.url_value()} bucket {influx.bucket_value()}"
    else:
        if not config.logging.local_store.exists():
            raise ValueError(
                f"{config.logging.local_store}: no local store yet (has the gateway run?)"
            )
        source = LocalStore(config.logging.local_store, set_aside_damaged=False)
        where = f"local store {config.logging.local_store}"
    try:
        shown = sys.stderr.isatty() if progress is None else progress
        window_s = (parse_time_s(start), parse_time_s(stop))
        result = export_runs(source, machine, *window_s, out_csv, progress=shown)
    except ExportError as exc:
        raise ValueError(str(exc)) from None
    finally:
        source.close()
    click.echo(f"wrote {out_csv} from {where}: {result.rows} rows in {len(result.runs)} run(s)")
    if result.implausible_values:
        click.echo(
            f"note: {result.implausible_values} logged value(s) were not plausible for their unit "
            "(NaN, infinite or out of range) and were left empty",
            err=True,
        )
    if result.rows_without_probe:
        click.echo(
            f"note: {result.rows_without_probe} cycles had no probe measurement and were left out",
            err=True,
        )


@main.command()
@click.argument("data_csv", type=click.Path(path_type=Path))
@method_option(
    "--model",
    "The declared model whose residual is analysed; auto: every one, keeping the one "
    "whose analysis leaves the lowest held-out RMSE (that figure is then optimistic by the "
    "choice: add --nested for one that is not).",
    also=("auto",),
)
@targets_option()
@sensors_option("The model's declared temperature inputs, e.g. T1,T7 (default: every T<n>).")
@reference_option(POLICIES)
@json_option()
@click.option(
    "--report",
    "report_dir",
    type=click.Path(path_type=Path),
    help="Write an HTML report with plots into this folder.",
)
@store_option("Save the augmented model here (sub-folder augmented/).")
@quantity_option(
    "--tolerance-um",
    2.5,
    "The held-out RMSE the compensation must reach (the machine's tolerance), µm.",
)
@click.option(
    "--probe-rows",
    is_flag=True,
    help="The target is known only at some rows (a logged history: the probe's measured "
    "error): rows with an empty target feed the effect terms; fit and figures use the others, "
    "the target as measured (no reference subtracted).",
)
@click.option(
    "--nested",
    is_flag=True,
    help="Also score the whole analysis (effect search, and with --model auto the choice of "
    "the base) by an outer leave-one-run-out: every choice made without the run scored. "
    "One analysis per base and run: about a minute on fl_thermal.csv with --model auto.",
)
@progress_option()
@input_errors_exit
def analyze(
    data_csv: Path,
    method: str,
    targets: tuple[str, ...],
    sensors: str | None,
    reference: str,
    json_out: Path | None,
    report_dir: Path | None,
    store_dir: Path | None,
    tolerance_um: float,
    probe_rows: bool,
    nested: bool,
    progress: bool | None,
) -> None:
    """Fit the model, trace its held-out residual to the effect it lacks, add it, compare."""
    chosen, data, sensor_list = _load_targets(data_csv, targets, sensors, probe_rows)
    # The analysis stack (scipy, scikit-learn) only once the file is known good.
    from gateway.offline.analyze import AnalyzeRequest, TooFewProbeRowsError, run_analyze_targets

    request = _request(
        AnalyzeRequest,
        (data_csv, method, chosen[0], sensor_list, reference, progress),
        store_dir=store_dir,
        report_dir=report_dir,
        tolerance_um=tolerance_um,
        probe_rows=probe_rows,
        nested=nested,
    )
    try:
        result = run_analyze_targets(data, chosen, request, click.echo, _warn)
    except TooFewProbeRowsError as exc:
        raise click.UsageError(str(exc)) from None
    write_json(json_out, result)


@main.command()
@click.argument("data_csv", type=click.Path(path_type=Path))
@targets_option()
@method_option("--model", "The declared model (its sensors feed the base).")
@sensors_option()
@click.option(
    "--base",
    type=click.Choice(["lagged", "declared"]),
    default=DEFAULT_REPLAY_BASE,
    show_default=True,
    help="lagged: the model's sensors plus first-order lags, ridge, fitted for online use; "
    "declared: the model as fit fits it.",
)
@click.option(
    "--augmented",
    "augmented_file",
    type=click.Path(path_type=Path),
    help="An analyze --store result to replay instead of --model.",
)
@click.option(
    "--probe-interval-min",
    "intervals",
    type=FiniteFloatRange(min=0, min_open=True),
    multiple=True,
    help="Minutes between probes (repeatable; default 60).",
)
@click.option(
    "--filter-kind",
    "filter_kinds",
    type=click.Choice(["bias", "bias-rate", "bias-gain"]),
    multiple=True,
    help="Filter kinds the nested choice may pick from (repeatable; default bias).",
)
@store_option(
    "Save the lagged base fitted on every run, with its online-correction parameters "
    "for the first interval, as an augmented model (sub-folder augmented/)."
)
@json_option()
@progress_option()
@input_errors_exit
def replay(
    data_csv: Path,
    targets: tuple[str, ...],
    method: str,
    sensors: str | None,
    base: str,
    augmented_file: Path | None,
    intervals: tuple[float, ...],
    filter_kinds: tuple[str, ...],
    store_dir: Path | None,
    json_out: Path | None,
    progress: bool | None,
) -> None:
    """Replay measured runs causally through the online probe correction, leave-one-run-out."""
    from gateway.offline.replay import run_replay_targets
    from models.data.targets import chosen_targets

    result = run_replay_targets(
        data_csv,
        chosen_targets(data_csv, targets),
        method,
        parse_sensors(sensors),
        intervals or (60.0,),
        click.echo,
        base=base,
        augmented_file=augmented_file,
        store_dir=store_dir,
        version=__version__,
        filter_kinds=filter_kinds,
        progress=sys.stderr.isatty() if progress is None else progress,
        note=_warn,
    )
    write_json(json_out, result)


@main.command()
@click.argument("data_csv", type=click.Path(path_type=Path))
@click.option(
    "--model",
    "model_specs",
    required=True,
    multiple=True,
    help="A model file (fit or analyze --store), or a model id looked up in --store. "
    "Repeatable: one model per target, each scoring the target it predicts.",
)
@store_option("The model store to look --model up in (its augmented/ folder too).")
@targets_option("Measured error column, µm (default: the model's target).", default=None)
@json_option()
@progress_option()
@input_errors_exit
def score(
    data_csv: Path,
    model_specs: tuple[str, ...],
    store_dir: Path | None,
    targets: tuple[str, ...],
    json_out: Path | None,
    progress: bool | None,
) -> None:
    """Apply a stored model to measured runs as the gateway would, without refitting."""
    from gateway.offline.score import score_targets
    from models.data.targets import chosen_targets

    chosen = chosen_targets(data_csv, targets)
    shown = sys.stderr.isatty() if progress is None else progress
    write_json(
        json_out,
        score_targets(data_csv, model_specs, store_dir, chosen, click.echo, _warn, shown),
    )


def _add_models_group() -> None:
    from gateway.cli.models import models_group  # click only at load, like this module

    main.add_command(models_group)


_add_models_group()
