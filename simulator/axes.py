"""Growth across the machine, X and Y: a temperature difference between two faces.

The Z growth sums the nodes' rises; a growth in X or Y comes from the head tilting
or bending, i.e. from one face of the head being warmer than the opposite one. Each
face is a first-order lag (its own time constant) of a mix of the network's nodes:

    τ_f dT_f/dt = Σ_i w_f,i T_i − T_f,       growth = k · (T_hot − T_cold)

e.g. the spindle motor on one side of the headstock warms that side's face before
the heat has crossed the casting: the head tilts and the tool moves in X, then part
of it comes back as the far face warms. The faces are thin layers of the castings:
they take too little heat to change the network, so they are driven by it one way
and the Z growth, the temperatures and every recording's Z column are unchanged.
Each face is integrated exactly over a sub-step with the nodes held (as the sensors
are), so the result does not depend on how often the machine is read.
"""

from __future__ import annotations

import numpy as np

from simulator.params import NODES, AxisGrowth


class AxisFaces:
    """The hot and cold face temperatures of every X/Y axis of a machine, °C."""

    def __init__(self, axes: dict[str, AxisGrowth], step_s: float, start_C: float) -> None:
        self.names = tuple(axes)
        faces = [face for axis in axes.values() for face in (axis.hot_face, axis.cold_face)]
        self.mix = np.array([[f.mix.get(n, 0.0) for n in NODES] for f in faces]).reshape(
            len(faces), len(NODES)
        )
        self.decay = np.exp(-step_s / np.array([f.tau_s for f in faces], dtype=float))
        self.gain_um_per_K = np.array([a.um_per_K for a in axes.values()], dtype=float)
        self.faces_C = np.full(len(faces), float(start_C))

    def step(self, nodes_C: np.ndarray) -> None:
        """One sub-step later, the nodes held at ``nodes_C`` over it."""
        if self.faces_C.size:
            self.faces_C = self.decay * self.faces_C + (1 - self.decay) * (self.mix @ nodes_C)

    def growth_um(self) -> dict[str, float]:
        """Each axis's growth now, µm: gain × (hot face − cold face)."""
        difference = self.faces_C[0::2] - self.faces_C[1::2]
        grown = self.gain_um_per_K * difference
        return {name: float(v) for name, v in zip(self.names, grown, strict=True)}
