"""A second independent generator: a 1-D finite-difference shaft in its housing.

Written apart from the project's simulator (``simulator/``) and from the lumped
network of ``tests/independent_machine.py``, with other physics, numerics,
sampling and sensor layout, so that the residual analysis and the error's
reference (``models/data/references.py``) are checked on data they were not built on.
It writes the measured-run CSV format of the interface contract (§1)::

    run,time_s,speed_rpm,T2,T4,T7,T9,T11,T12,ambient_C,error_um

Machine
-------
An 8000 r/min motor spindle. The shaft and the housing are two parallel 1-D
rods of ``CELLS`` (12) finite-difference cells of 40 mm each along the spindle
axis (cell 0 at the nose): axial conduction inside each rod, an exchange between
the rods (strong through the front and rear bearings, weak across the motor's
air gap), convection from the housing to the room and a coolant jacket at room
temperature around the motor section. Heat (n in 1000 r/min): front bearing
``2 n**1.5`` W and rear bearing ``1.2 n**1.5`` W (half into the shaft, half into
the housing), rotor ``3 + 1.5 n`` W into the shaft's motor cells and stator
``5 + 3 n`` W into the housing's motor cells while the spindle turns. Time
steps of ``STEP_S`` (10 s), backward Euler (one LU factorisation), sampled
every ``SAMPLE_S`` (60 s).

Sensors
-------
Six, named as on a machine that numbers its channels by location (``T2`` …
``T12``), each a mix of cells through its own first-order lag, with Gaussian
noise (0.03 °C) and rounded to 0.01 °C: ``T2`` front bearing ring, ``T4`` rear
bearing ring, ``T7`` an infrared pyrometer on the shaft between the bearings,
``T9`` the motor housing, ``T11`` the nose flange, ``T12`` the coolant return.
``ambient_C`` reads the room through a 120 s lag.

Z error
-------
The nose moves by the shaft's growth from the rear (locating) bearing to the
nose, plus the housing's growth from its rear mounting flange to that bearing
(11.5 µm/m/K), recorded by a probe zeroed on the cold machine at rest, with
noise 0.3 µm, rounded to 0.01 µm. A run opening at speed was zeroed before the
spindle started; its first logged reading already holds the growth of its first
minute.

Runs
----
Five programmes of 5–6.5 h: two open with 10–15 min at rest, three open with
the spindle already turning; two lose 25–40 min of rows to a logging gap;
``time_s`` is the clock of day (seconds since midnight) of the run's own day, so
it restarts on each run.

Hidden effects (``effect``)
---------------------------
``none`` nothing hidden; ``thermal_lag`` a tool holder following the nose cell
through a 40 min lag, 2 µm/K, seen by no sensor; ``speed_direct`` an axial
shortening ``−(0.7 n + 0.08 n**2)`` µm as soon as the spindle turns;
``ambient`` a room sine of 3 °C and 16 h (run-dependent phase) that reaches the
error through the column (3 h lag, 5 µm/K), which no T sensor sees; ``drift``
+1.5 µm/h from each run's start; ``unsensed_heat`` a rotary union at the rear
heated by friction ``∝ n**2`` (heat that no sensor sees), 1.5 h lag, up to about
17 µm.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy.linalg import lu_factor, lu_solve

from tests.run_csv import runs_csv_writer

EFFECTS: tuple[str, ...] = (
    "none",
    "thermal_lag",
    "speed_direct",
    "ambient",
    "drift",
    "unsensed_heat",
)

CELLS = 12
CELL_M = 0.04
STEP_S = 10.0
SAMPLE_S = 60.0
FRONT_CELL, REAR_CELL = 1, 10
MOTOR_CELLS = slice(4, 8)
# --- rods ---------------------------------------------------------------------
SHAFT_CELL_J_PER_K = 3.6e6 * 3.85e-3 * CELL_M  # steel, 70 mm shaft
HOUSING_CELL_J_PER_K = 3.9e6 * 0.02 * CELL_M  # cast iron tube
SHAFT_AXIAL_W_PER_K = 45.0 * 3.85e-3 / CELL_M
HOUSING_AXIAL_W_PER_K = 50.0 * 0.02 / CELL_M
BEARING_LINK_W_PER_K = 3.0
AIR_GAP_W_PER_K = 0.3
HOUSING_ROOM_W_PER_K = 0.6
JACKET_W_PER_K = 4.0
# --- heat (n in 1000 r/min) ---------------------------------------------------
FRONT_W_PER_KRPM15, REAR_W_PER_KRPM15 = 2.0, 1.2
ROTOR_W, ROTOR_W_PER_KRPM = 3.0, 1.5
STATOR_W, STATOR_W_PER_KRPM = 5.0, 3.0
# --- growth -------------------------------------------------------------------
EXPANSION_UM_PER_K_CELL = 11.5e-6 * CELL_M * 1e6  # µm per K of one cell
# --- sensors: (shaft weights, housing weights, lag) ------------------------------
SENSOR_NAMES = ("T2", "T4", "T7", "T9", "T11", "T12")
TEMP_NOISE_C = 0.03
ERROR_NOISE_UM = 0.3
AMBIENT_LAG_S = 120.0
# --- hidden effects -----------------------------------------------------------
HOLDER_TAU_S, HOLDER_UM_PER_K = 2400.0, 2.0
SPEED_UM_PER_KRPM, SPEED_UM_PER_KRPM2 = -0.7, -0.08
ROOM_AMPLITUDE_C, ROOM_PERIOD_S = 3.0, 16 * 3600.0
COLUMN_TAU_S, COLUMN_UM_PER_K = 3 * 3600.0, 5.0
DRIFT_UM_PER_H = 1.5
UNION_TAU_S, UNION_K_PER_KRPM2, UNION_UM_PER_K = 5400.0, 0.12, 3.0

# (minutes, r/min) segments; a leading 0 r/min segment is the run's at-rest lead-in
_PROGRAMMES: dict[str, list[tuple[float, int]]] = {
    "rest-const": [(15, 0), (210, 6000), (90, 0)],
    "speed-steps": [(90, 8000), (60, 3000), (60, 6000), (90, 0)],
    "rest-spectrum": [(10, 0), (40, 4000), (30, 7500), (50, 2000), (40, 8000), (60, 5000), (90, 0)],
    "speed-spectrum": [(45, 4000), (30, 7000), (45, 1500), (60, 6500), (30, 2500), (90, 0)],
    "speed-duty": [(60, 5000), (30, 0), (60, 7000), (30, 0), (60, 2000), (60, 0)],
}
PROGRAMS: tuple[str, ...] = tuple(_PROGRAMMES)
#: rows lost to a logging gap: (programme, start minute, length in minutes)
_GAPS = {"rest-spectrum": (150, 25), "speed-duty": (100, 40)}


def speed_profile(program: str) -> np.ndarray:
    """Speed (r/min) held over each ``STEP_S`` step, plus the final instant."""
    steps = [
        np.full(round(minutes * 60 / STEP_S), speed, dtype=float)
        for minutes, speed in _PROGRAMMES[program]
    ]
    speeds = np.concatenate(steps)
    return np.append(speeds, speeds[-1])


def _conduction() -> tuple[np.ndarray, np.ndarray]:
    """Capacities (2·CELLS,) and the conductance matrix G (W/K, to the room on the diagonal)."""
    n = 2 * CELLS
    capacity = np.r_[np.full(CELLS, SHAFT_CELL_J_PER_K), np.full(CELLS, HOUSING_CELL_J_PER_K)]
    G = np.zeros((n, n))

    def link(i: int, j: int, g: float) -> None:
        G[i, i] += g
        G[j, j] += g
        G[i, j] -= g
        G[j, i] -= g

    for i in range(CELLS - 1):
        link(i, i + 1, SHAFT_AXIAL_W_PER_K)
        link(CELLS + i, CELLS + i + 1, HOUSING_AXIAL_W_PER_K)
    for i in range(CELLS):
        bearing = i in (FRONT_CELL, REAR_CELL)
        link(i, CELLS + i, BEARING_LINK_W_PER_K if bearing else AIR_GAP_W_PER_K)
        G[CELLS + i, CELLS + i] += HOUSING_ROOM_W_PER_K
    for i in range(CELLS)[MOTOR_CELLS]:
        G[CELLS + i, CELLS + i] += JACKET_W_PER_K
    return capacity, G


def _heat_w(krpm: float) -> np.ndarray:
    q = np.zeros(2 * CELLS)
    if krpm <= 0:
        return q
    front, rear = FRONT_W_PER_KRPM15 * krpm**1.5, REAR_W_PER_KRPM15 * krpm**1.5
    for cell, watts in ((FRONT_CELL, front), (REAR_CELL, rear)):
        q[cell] += watts / 2
        q[CELLS + cell] += watts / 2
    motor = range(CELLS)[MOTOR_CELLS]
    for i in motor:
        q[i] += (ROTOR_W + ROTOR_W_PER_KRPM * krpm) / len(motor)
        q[CELLS + i] += (STATOR_W + STATOR_W_PER_KRPM * krpm) / len(motor)
    return q


def _room_loss_w_per_k(G: np.ndarray) -> np.ndarray:
    """Each cell's conductance to the room (the row sums of G)."""
    return G.sum(axis=1)


def _lag(values: np.ndarray, tau_s: float, dt_s: float, start: float = 0.0) -> np.ndarray:
    a = np.exp(-dt_s / tau_s)
    out = np.empty_like(values)
    state = start
    for k, u in enumerate(values):
        state = a * state + (1 - a) * u
        out[k] = state
    return out


def _simulate(program: str, effect: str, rng: np.random.Generator) -> pd.DataFrame:
    capacity, G = _conduction()
    to_room = _room_loss_w_per_k(G)
    # Backward Euler on rises x above the run's initial room level r0:
    # (C/dt + G) x_{k+1} = C/dt x_k + q_k + to_room·(room_k − r0)
    lu = lu_factor(np.diag(capacity / STEP_S) + G)
    speed = speed_profile(program)
    krpm = speed / 1000.0
    steps = speed.size
    t = np.arange(steps) * STEP_S
    phase = rng.uniform(0, 2 * np.pi)
    room = np.zeros(steps)
    if effect == "ambient":
        room = ROOM_AMPLITUDE_C * (np.sin(2 * np.pi * t / ROOM_PERIOD_S + phase) - np.sin(phase))
    rises = np.zeros((steps, 2 * CELLS))
    for k in range(steps - 1):
        rhs = capacity / STEP_S * rises[k] + _heat_w(krpm[k]) + to_room * room[k + 1]
        rises[k + 1] = lu_solve(lu, rhs)
    shaft, housing = rises[:, :CELLS], rises[:, CELLS:]

    growth_cells = shaft[:, : REAR_CELL + 1].sum(axis=1) + housing[:, REAR_CELL:].sum(axis=1)
    error = EXPANSION_UM_PER_K_CELL * growth_cells
    if effect == "thermal_lag":
        error += HOLDER_UM_PER_K * _lag(shaft[:, 0], HOLDER_TAU_S, STEP_S)
    elif effect == "speed_direct":
        error += SPEED_UM_PER_KRPM * krpm + SPEED_UM_PER_KRPM2 * krpm**2
    elif effect == "ambient":
        error += COLUMN_UM_PER_K * _lag(room, COLUMN_TAU_S, STEP_S)
    elif effect == "drift":
        error += DRIFT_UM_PER_H * t / 3600.0
    elif effect == "unsensed_heat":
        error += UNION_UM_PER_K * _lag(UNION_K_PER_KRPM2 * krpm**2, UNION_TAU_S, STEP_S)

    mixes = {
        "T2": (0.8 * shaft[:, FRONT_CELL] + 0.2 * housing[:, FRONT_CELL], 30.0),
        "T4": (0.8 * shaft[:, REAR_CELL] + 0.2 * housing[:, REAR_CELL], 30.0),
        "T7": (shaft[:, 5:7].mean(axis=1), 5.0),
        "T9": (housing[:, MOTOR_CELLS].mean(axis=1), 60.0),
        "T11": (housing[:, 0], 45.0),
        "T12": (0.7 * housing[:, MOTOR_CELLS].mean(axis=1) + 0.3 * shaft[:, 5], 120.0),
    }
    level = 21.0 + rng.uniform(-2.0, 2.0)
    offsets = rng.uniform(-0.4, 0.4, len(SENSOR_NAMES))  # each sensor's calibration
    sample = slice(None, None, round(SAMPLE_S / STEP_S))
    start_clock_s = rng.integers(5 * 3600, 8 * 3600) // 60 * 60  # the run's morning start
    frame = pd.DataFrame({"time_s": (start_clock_s + t[sample]).astype(int)})
    frame.insert(0, "run", program)
    frame["speed_rpm"] = speed[sample].astype(int)
    for offset, name in zip(offsets, SENSOR_NAMES, strict=True):
        mix, lag_s = mixes[name]
        reading = level + offset + _lag(mix, lag_s, STEP_S)[sample]
        frame[name] = np.round(reading + rng.normal(0, TEMP_NOISE_C, reading.size), 2)
    ambient = level + _lag(room, AMBIENT_LAG_S, STEP_S)[sample]
    frame["ambient_C"] = np.round(ambient + rng.normal(0, TEMP_NOISE_C, ambient.size), 2)
    measured = error[sample] + rng.normal(0, ERROR_NOISE_UM, frame.shape[0])
    frame["error_um"] = np.round(measured, 2)
    if program in _GAPS:
        start_min, minutes = _GAPS[program]
        minute = (frame["time_s"] - frame["time_s"].iloc[0]) / 60.0
        frame = frame[(minute < start_min) | (minute >= start_min + minutes)]
    return frame


def generate_runs(
    effect: str = "none", seed: int = 0, programs: Sequence[str] | None = None
) -> pd.DataFrame:
    """Measured runs for the chosen programmes (default: all), one block per run."""
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; choose one of {', '.join(EFFECTS)}")
    chosen = list(PROGRAMS if programs is None else programs)
    frames = []
    for program in chosen:
        if program not in PROGRAMS:
            raise ValueError(f"unknown program {program!r}; choose one of {', '.join(PROGRAMS)}")
        rng = np.random.default_rng([seed, PROGRAMS.index(program), 15])
        frames.append(_simulate(program, effect, rng))
    return pd.concat(frames, ignore_index=True)


#: ``write_csv(path, effect, seed, programs)``: the runs as a measured-run CSV; its path.
write_csv = runs_csv_writer(generate_runs)
