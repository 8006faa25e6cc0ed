"""A long campaign of measured runs (many runs over months), for benchmarks and tests.

Built on the physics of :mod:`tests.synthetic` (each sensor a first-order lag of
the speed-driven heat input, the error a known combination of two sensors' rises
plus noise), with what a campaign on a production machine adds: runs of different
lengths, speed programmes of several levels in a different order each day, a room
level that changes from day to day, and, on request, no speed column (a recording
of temperatures and probe values only) or one run whose error is far off the
others (a probe or fixture fault on one day).

    write_campaign_csv(path, n_runs=43)          # the 43-run benchmark recording
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.synthetic import ERROR_WEIGHTS, SENSOR_GAINS, SENSOR_TAUS_S, first_order

#: Speed levels (r/min) a day's programme draws from, 40 min to 2 h each.
LEVELS_RPM = (0.0, 1500.0, 3000.0, 4500.0, 6000.0)


def _programme(rng: np.random.Generator, n: int, dt_s: float) -> np.ndarray:
    speed = np.empty(n)
    k = 0
    while k < n:
        hold = int(rng.uniform(2400.0, 7200.0) / dt_s)
        speed[k : k + hold] = rng.choice(LEVELS_RPM)
        k += hold
    return speed


def _sensor_lags(n_sensors: int) -> tuple[np.ndarray, np.ndarray]:
    """Time constants (s) and gains of ``n_sensors`` sensors: :mod:`tests.synthetic`'s seven,
    then more spread between its extremes."""
    taus, gains = np.asarray(SENSOR_TAUS_S), np.asarray(SENSOR_GAINS)
    extra = max(n_sensors - taus.size, 0)
    more_taus = np.geomspace(taus[0] * 1.1, taus[-1] * 0.95, extra)
    more_gains = np.linspace(gains[0] * 0.95, gains[-1] * 1.05, extra)
    return np.r_[taus, more_taus][:n_sensors], np.r_[gains, more_gains][:n_sensors]


def campaign(
    n_runs: int = 43,
    seed: int = 0,
    dt_s: float = 60.0,
    hours: tuple[float, float] = (4.0, 8.0),
    noise_um: float = 0.3,
    speed: bool = True,
    outlier_run: int | None = None,
    outlier_um: float = 12.0,
    n_sensors: int = len(SENSOR_TAUS_S),
) -> tuple[list[str], list[list]]:
    """(header, rows) of ``n_runs`` runs, each ``hours`` long (uniform), sampled every ``dt_s``.

    ``speed=False``: the speed was not recorded, ``speed_rpm`` is 0 on every row (the
    column the data format requires, filled as a user fills it). ``outlier_run`` (an
    index) adds a slow ramp up to ``outlier_um`` to that run's error, seen by no sensor.
    ``n_sensors`` above the seven of :mod:`tests.synthetic` adds sensors whose time
    constants and gains lie between theirs.
    """
    rng = np.random.default_rng(seed)
    taus, gains = _sensor_lags(n_sensors)
    sensors = [f"T{i + 1}" for i in range(n_sensors)]
    header = ["run", "time_s", "speed_rpm", *sensors, "error_um"]
    rows: list[list] = []
    for r in range(n_runs):
        n = int(rng.uniform(*hours) * 3600.0 / dt_s)
        rpm = _programme(rng, n, dt_s)
        drive = (rpm / 6000.0) ** 1.5
        room = 20.0 + rng.uniform(-2.0, 2.0)
        temps = np.column_stack(
            [
                room + g * 10 * first_order(drive, tau, dt_s)
                for tau, g in zip(taus, gains, strict=True)
            ]
        )
        temps += rng.normal(0, 0.02, temps.shape)
        error = sum(
            w * (temps[:, int(name[1:]) - 1] - temps[0, int(name[1:]) - 1])
            for name, w in ERROR_WEIGHTS.items()
        )
        error = error + rng.normal(0, noise_um, n)
        if outlier_run == r:
            error = error + outlier_um * np.linspace(0.0, 1.0, n)
        run = f"day{r + 1:02d}"
        for k in range(n):
            rows.append([run, k * dt_s, rpm[k] if speed else 0.0, *temps[k], error[k]])
    return header, rows


def write_campaign_csv(path: Path, **kwargs) -> Path:
    """The campaign as a measured-run CSV (section 1 of the data format); its path."""
    header, rows = campaign(**kwargs)
    lines = [",".join(header)]
    lines += [",".join([row[0], *(f"{v:.6g}" for v in row[1:])]) for row in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
