"""Independent generator of measured spindle thermal-error runs, for cross-checks.

This module is deliberately *not* the project's simulator. It was written from
scratch with numpy/scipy only, with its own physics, parameters, sampling and
sensor layout, so that a detector that passes on these data is not merely tuned
to the project's own simulator. It writes the project's measured-run CSV format::

    run,time_s,speed_rpm,T1,T2,T3,T4,T5,T6,ambient_C,error_um

Machine
-------
A 10 000 r/min motor spindle, modelled as a 4-node lumped thermal network plus
the room (a boundary temperature):

========  ==============================================  ===========
node      meaning                                         capacity
========  ==============================================  ===========
C         spindle cartridge (front + rear bearings)       12 kJ/K
M         motor stator                                    20 kJ/K
H         spindle housing / ram                           150 kJ/K
B         machine bed / base                              800 kJ/K
========  ==============================================  ===========

Conductances (W/K): C-coolant 10, C-H 8, M-coolant 12, M-H 6, H-room 18,
H-B 0.4 (the base is only weakly coupled to the spindle heat), B-room 80.
The coolant returns from the chiller at room temperature, so "coolant" links
are links to the room. Heat input with n the speed in 1000 r/min: bearings
``12 * n**1.3`` W into C, motor ``30 + 18 * n`` W into M while the spindle
turns (0 W at rest). The linear system is integrated exactly over each 30 s
sample interval (matrix exponential with a zero-order hold; speed changes fall
on sample instants). Every run starts cold (all nodes at room temperature) as a
separate test day; samples every 30 s, runs of 7-9.5 h.

Sensors
-------
Each sensor reads a fixed mix of node temperatures through its own first-order
lag, plus Gaussian noise (sigma 0.02 °C), rounded to 0.01 °C:

====  ==================  ========================  ========
col   location            mix                       lag
====  ==================  ========================  ========
T1    rear bearing        0.85 C + 0.15 H           20 s
T2    front bearing       0.90 C + 0.10 H           12 s
T3    motor housing       0.85 M + 0.15 H           30 s
T4    ram upper           0.80 H + 0.20 M           60 s
T5    ram lower           0.95 H + 0.05 C           45 s
T6    coolant return      0.60 C + 0.40 M           15 s
====  ==================  ========================  ========

No T sensor sees the bed B. ``ambient_C`` is a room sensor with a 300 s lag and
sigma 0.02 °C noise.

Z error
-------
``error = 1.4 dC - 0.35 dM + 2.4 dH + 3.0 dB`` (µm, d = rise since the run's
start), about 34 µm steady growth at 10 000 r/min, recorded with probe noise
sigma 0.2 µm rounded to 0.01 µm. With ``effect="none"`` the room is constant
(a run-specific level near 20 °C) and the base barely warms, so the error is a
linear function of the sensor rises up to lags and noise.

Hidden effects (``effect``)
---------------------------
``none``
    Nothing hidden.
``thermal_lag``
    80 % of the cartridge growth reaches the tool tip through a hidden
    first-order lag of 2700 s (spindle nose / tool holder), seen by no sensor.
``speed_direct``
    Instantaneous Z shift ``+0.55 n + 0.035 n**2`` µm (n in 1000 r/min;
    9 µm at 10 000 r/min), present as soon as the spindle turns.
``ambient``
    The room follows a sine of amplitude 2.5 °C and period 12 h, with a start
    phase that depends on the run; it reaches the error mainly through the bed
    (3.0 µm/K, time constant about 2.8 h), which no T sensor sees, and is
    measured by ``ambient_C``.
``drift``
    Linear trend of -2.0 µm/h in the error from each run's start.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy.linalg import expm

from tests.run_csv import runs_csv_writer

EFFECTS: tuple[str, ...] = ("none", "thermal_lag", "speed_direct", "ambient", "drift")

SAMPLE_S = 30.0
TOP_SPEED_RPM = 10_000

# --- thermal network (nodes C, M, H, B) -------------------------------------
NODES: tuple[str, ...] = ("C", "M", "H", "B")
CAPACITY_J_PER_K = np.array([12e3, 20e3, 150e3, 800e3])
# Conductances between nodes (W/K); "R" is the room (coolant returns at room temperature).
CONDUCTANCE_W_PER_K: dict[tuple[str, str], float] = {
    ("C", "R"): 10.0,
    ("C", "H"): 8.0,
    ("M", "R"): 12.0,
    ("M", "H"): 6.0,
    ("H", "R"): 18.0,
    ("H", "B"): 0.4,
    ("B", "R"): 80.0,
}
BEARING_W_PER_KRPM_POW = 12.0  # bearing loss = 12 * n**1.3 W
BEARING_EXPONENT = 1.3
MOTOR_IDLE_W = 30.0
MOTOR_W_PER_KRPM = 18.0

# --- sensors ----------------------------------------------------------------
# Mix weights over (C, M, H, B) and first-order lag per sensor.
SENSOR_MIX = np.array(
    [
        [0.85, 0.00, 0.15, 0.00],  # T1 rear bearing
        [0.90, 0.00, 0.10, 0.00],  # T2 front bearing
        [0.00, 0.85, 0.15, 0.00],  # T3 motor housing
        [0.00, 0.20, 0.80, 0.00],  # T4 ram upper
        [0.05, 0.00, 0.95, 0.00],  # T5 ram lower
        [0.60, 0.40, 0.00, 0.00],  # T6 coolant return
    ]
)
SENSOR_LAG_S = np.array([20.0, 12.0, 30.0, 60.0, 45.0, 15.0])
AMBIENT_LAG_S = 300.0
TEMP_NOISE_C = 0.02
ERROR_NOISE_UM = 0.2

# --- Z growth ---------------------------------------------------------------
GROWTH_UM_PER_K = np.array([1.4, -0.35, 2.4, 3.0])  # C, M, H, B

# --- hidden effects ---------------------------------------------------------
LAG_SHARE = 0.8  # share of the cartridge growth behind the hidden lag
LAG_TAU_S = 2700.0
SPEED_LINEAR_UM_PER_KRPM = 0.55
SPEED_QUADRATIC_UM_PER_KRPM2 = 0.035
AMBIENT_AMPLITUDE_C = 2.5
AMBIENT_PERIOD_S = 12 * 3600.0
DRIFT_UM_PER_H = -2.0

# --- speed programmes: (duration in minutes, speed in r/min) segments ---------
_PROGRAMME_SEGMENTS: dict[str, list[tuple[float, int]]] = {
    "const-3000": [(330, 3000), (150, 0)],
    "const-6000": [(300, 6000), (150, 0)],
    "const-9000": [(300, 9000), (180, 0)],
    "staircase": [
        (40, 2000),
        (40, 4000),
        (40, 6000),
        (40, 8000),
        (40, 10000),
        (40, 8000),
        (40, 6000),
        (40, 4000),
        (40, 2000),
        (120, 0),
    ],
    "spectrum": [
        (30, 5000),
        (50, 9000),
        (20, 2000),
        (60, 7000),
        (30, 10000),
        (45, 3000),
        (25, 8000),
        (60, 4000),
        (35, 9500),
        (40, 1000),
        (50, 6000),
        (105, 0),
    ],
    "rest-cycles": [
        (60, 7000),
        (30, 0),
        (45, 10000),
        (45, 0),
        (90, 5000),
        (30, 0),
        (60, 8000),
        (60, 0),
        (40, 3000),
        (90, 0),
    ],
    "warmup-production": [
        (10, 2500),
        (10, 5000),
        (10, 7500),
        (10, 10000),
        (80, 6500),
        (20, 0),
        (80, 6500),
        (20, 0),
        (80, 6500),
        (20, 2000),
        (120, 0),
    ],
}
PROGRAMS: tuple[str, ...] = tuple(_PROGRAMME_SEGMENTS)


def speed_profile(program: str) -> np.ndarray:
    """Speed (r/min) held over each 30 s interval of a programme, plus the final sample."""
    _check_choice("program", program, PROGRAMS)
    per_sample = [
        np.full(round(minutes * 60 / SAMPLE_S), speed, dtype=float)
        for minutes, speed in _PROGRAMME_SEGMENTS[program]
    ]
    speeds = np.concatenate(per_sample)
    return np.append(speeds, speeds[-1])


def _check_choice(kind: str, value: str, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ValueError(f"unknown {kind} {value!r}; choose one of {', '.join(choices)}")


def _state_space() -> tuple[np.ndarray, np.ndarray]:
    """Continuous system x' = A x + B u.

    States: 4 node temperatures, 6 sensor lag states, the ambient sensor and the
    hidden tool-holder lag (driven by the cartridge). Inputs: bearing heat (W),
    motor heat (W), room temperature (°C).
    """
    n_nodes = len(NODES)
    n_sensors = SENSOR_MIX.shape[0]
    n_states = n_nodes + n_sensors + 2
    A = np.zeros((n_states, n_states))
    B = np.zeros((n_states, 3))
    index = {name: i for i, name in enumerate(NODES)}
    for (a, b), g in CONDUCTANCE_W_PER_K.items():
        i = index[a]
        A[i, i] -= g / CAPACITY_J_PER_K[i]
        if b == "R":
            B[i, 2] += g / CAPACITY_J_PER_K[i]
        else:
            j = index[b]
            A[i, j] += g / CAPACITY_J_PER_K[i]
            A[j, j] -= g / CAPACITY_J_PER_K[j]
            A[j, i] += g / CAPACITY_J_PER_K[j]
    B[index["C"], 0] = 1.0 / CAPACITY_J_PER_K[index["C"]]
    B[index["M"], 1] = 1.0 / CAPACITY_J_PER_K[index["M"]]
    for s in range(n_sensors):
        row = n_nodes + s
        A[row, :n_nodes] = SENSOR_MIX[s] / SENSOR_LAG_S[s]
        A[row, row] = -1.0 / SENSOR_LAG_S[s]
    ambient_row = n_nodes + n_sensors
    A[ambient_row, ambient_row] = -1.0 / AMBIENT_LAG_S
    B[ambient_row, 2] = 1.0 / AMBIENT_LAG_S
    lag_row = ambient_row + 1
    A[lag_row, lag_row] = -1.0 / LAG_TAU_S
    A[lag_row, index["C"]] = 1.0 / LAG_TAU_S
    return A, B


def _discretise(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation over one sample interval."""
    n, m = B.shape
    augmented = np.zeros((n + m, n + m))
    augmented[:n, :n] = A * dt
    augmented[:n, n:] = B * dt
    phi = expm(augmented)
    return phi[:n, :n], phi[:n, n:]


_AD, _BD = _discretise(*_state_space(), SAMPLE_S)


def _simulate_run(program: str, effect: str, rng: np.random.Generator) -> pd.DataFrame:
    speed = speed_profile(program)
    n_samples = speed.size
    time_s = np.arange(n_samples) * SAMPLE_S
    krpm = speed / 1000.0
    running = speed > 0

    room_level = 20.0 + rng.uniform(-1.5, 1.5)
    phase = rng.uniform(0.0, 2.0 * np.pi)
    if effect == "ambient":
        omega = 2.0 * np.pi / AMBIENT_PERIOD_S
        # Room at the middle of each interval (held over it) and at the sample instants.
        mid_s = time_s + SAMPLE_S / 2
        room_mid = room_level + AMBIENT_AMPLITUDE_C * np.sin(omega * mid_s + phase)
        room_start = room_level + AMBIENT_AMPLITUDE_C * np.sin(phase)
    else:
        room_mid = np.full(n_samples, room_level)
        room_start = room_level

    bearing_w = BEARING_W_PER_KRPM_POW * krpm**BEARING_EXPONENT
    motor_w = np.where(running, MOTOR_IDLE_W + MOTOR_W_PER_KRPM * krpm, 0.0)
    inputs = np.column_stack([bearing_w, motor_w, room_mid])

    states = np.empty((n_samples, _AD.shape[0]))
    states[0] = room_start  # cold start: everything at room temperature
    for k in range(n_samples - 1):
        states[k + 1] = _AD @ states[k] + _BD @ inputs[k]

    n_nodes = len(NODES)
    n_sensors = SENSOR_MIX.shape[0]
    node_rise = states[:, :n_nodes] - states[0, :n_nodes]
    sensors = states[:, n_nodes : n_nodes + n_sensors]
    ambient = states[:, n_nodes + n_sensors]
    hidden_lag_rise = states[:, n_nodes + n_sensors + 1] - states[0, n_nodes + n_sensors + 1]

    error = node_rise @ GROWTH_UM_PER_K
    if effect == "thermal_lag":
        c = NODES.index("C")
        error += GROWTH_UM_PER_K[c] * LAG_SHARE * (hidden_lag_rise - node_rise[:, c])
    elif effect == "speed_direct":
        error += SPEED_LINEAR_UM_PER_KRPM * krpm + SPEED_QUADRATIC_UM_PER_KRPM2 * krpm**2
    elif effect == "drift":
        error += DRIFT_UM_PER_H * time_s / 3600.0

    temps = np.round(sensors + rng.normal(0.0, TEMP_NOISE_C, sensors.shape), 2)
    ambient_c = np.round(ambient + rng.normal(0.0, TEMP_NOISE_C, n_samples), 2)
    error_um = np.round(error + rng.normal(0.0, ERROR_NOISE_UM, n_samples), 2)

    frame = pd.DataFrame(
        {"run": program, "time_s": time_s.astype(int), "speed_rpm": speed.astype(int)}
    )
    for s in range(n_sensors):
        frame[f"T{s + 1}"] = temps[:, s]
    frame["ambient_C"] = ambient_c
    frame["error_um"] = error_um
    return frame


def generate_runs(
    effect: str = "none", seed: int = 0, programs: Sequence[str] | None = None
) -> pd.DataFrame:
    """Measured runs for the chosen programmes (default: all), one contiguous block per run."""
    _check_choice("effect", effect, EFFECTS)
    chosen = list(PROGRAMS if programs is None else programs)
    for program in chosen:
        _check_choice("program", program, PROGRAMS)
    frames = []
    for program in chosen:
        # Per-run stream, so a run's data do not depend on which other runs are generated.
        rng = np.random.default_rng([seed, PROGRAMS.index(program)])
        frames.append(_simulate_run(program, effect, rng))
    return pd.concat(frames, ignore_index=True)


#: ``write_csv(path, effect, seed, programs)``: the runs as a measured-run CSV; its path.
write_csv = runs_csv_writer(generate_runs)
