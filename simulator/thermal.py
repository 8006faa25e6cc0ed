"""Lumped-parameter thermal network of the spindle and its structure.

Nodes i (bearing, shaft, motor, headstock, column) with heat capacity C_i;
conduction G_ij between nodes; convection h_i(n) = base_i + per_krpm_i · n/1000
to the room at T_a; heat sources growing with speed n (r/min):

    C_i dT_i/dt = Q_i(n) − Σ_j G_ij (T_i − T_j) − h_i(n) (T_i − T_a) [− G_c (T_i − T_c)]

    Q_bearing = c_b · (n/1000)^e         (friction, e ≈ 1.3–1.7)
    Q_motor   = idle + k_m · n/1000      (while turning)

and, with the cooler effect, a coolant at T_c(t) exchanging G_c with the
bearing cartridge (a cooling jacket). In matrix form dT/dt = A(n) T + b(n, t).
Over one sub-step of h seconds with the speed and the boundary temperatures
held, the exact solution is

    T(t+h) = Φ T(t) + Γ b,   Φ = e^{A h},   Γ = A⁻¹ (Φ − I)

(A is invertible: every node loses heat to the room). Φ and Γ are cached per
speed, so a long recording costs a few small matrix products per sub-step.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.linalg import expm

from simulator.params import NODES, MachineParams


class ThermalNetwork:
    def __init__(
        self, params: MachineParams, step_s: float, coolant_conductance_W_per_K: float = 0.0
    ):
        self.params = params
        self.step_s = step_s
        self.index = {name: i for i, name in enumerate(NODES)}
        self.capacity = np.array([params.heat_capacity_J_per_K[n] for n in NODES])
        conduction = np.zeros((len(NODES), len(NODES)))
        for pair, g in params.conductance_W_per_K.items():
            a, _, b = pair.partition("-")
            i, j = self.index[a], self.index[b]
            conduction[i, i] += g
            conduction[j, j] += g
            conduction[i, j] -= g
            conduction[j, i] -= g
        self.conduction = conduction
        self.coolant = np.zeros(len(NODES))
        self.coolant[self.index["bearing"]] = coolant_conductance_W_per_K
        self._matrices = lru_cache(maxsize=256)(self._compute_matrices)

    def convection(self, speed_rpm: float) -> np.ndarray:
        krpm = speed_rpm / 1000.0
        return np.array(
            [
                self.params.convection_W_per_K[n].base
                + self.params.convection_W_per_K[n].per_krpm * krpm
                for n in NODES
            ]
        )

    def heat_W(self, speed_rpm: float) -> np.ndarray:
        """Heat generated at each node, W."""
        q = np.zeros(len(NODES))
        if speed_rpm > 0:
            krpm = speed_rpm / 1000.0
            bearing = self.params.bearing_heat
            motor = self.params.motor_heat
            q[self.index["bearing"]] = bearing.coefficient_W * krpm**bearing.exponent
            q[self.index["motor"]] = motor.idle_W + motor.per_krpm_W * krpm
        return q

    def _compute_matrices(self, speed_rpm: float) -> tuple[np.ndarray, np.ndarray]:
        losses = self.conduction + np.diag(self.convection(speed_rpm) + self.coolant)
        a = -losses / self.capacity[:, None]
        return _transition(a.tobytes(), len(NODES), self.step_s)

    def step(
        self, temps_C: np.ndarray, speed_rpm: float, ambient_C: np.ndarray | float, coolant_C: float
    ) -> np.ndarray:
        """Node temperatures one sub-step later (``ambient_C``: the air each node sees)."""
        phi, gamma = self._matrices(float(speed_rpm))
        drive = (
            self.heat_W(speed_rpm)
            + self.convection(speed_rpm) * ambient_C
            + self.coolant * coolant_C
        ) / self.capacity
        return phi @ temps_C + gamma @ drive

    def steady_state(self, speed_rpm: float, ambient_C: float) -> np.ndarray:
        """Temperatures the network settles to at a constant speed (no cooler)."""
        losses = self.conduction + np.diag(self.convection(speed_rpm) + self.coolant)
        drive = self.heat_W(speed_rpm) + self.convection(speed_rpm) * ambient_C
        drive = drive + self.coolant * ambient_C
        return np.linalg.solve(losses, drive)


@lru_cache(maxsize=1024)
def _transition(a_bytes: bytes, size: int, step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Φ and Γ of one A (its bytes) and step: shared by every network of the process.

    Recordings with the same parameters meet the same speeds; ``expm`` is most of a
    short recording's cost. The arrays are read-only, as they are shared.
    """
    a = np.frombuffer(a_bytes).reshape(size, size)
    phi = expm(a * step_s)
    gamma = np.linalg.solve(a, phi - np.eye(size))
    phi.setflags(write=False)
    gamma.setflags(write=False)
    return phi, gamma
