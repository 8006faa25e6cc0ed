"""Measurement noise as a function of (seed, machine time, channel), not of call order.

The served simulator publishes its readings on a wall-clock period, and every
endpoint asks for a snapshot whenever it likes; a generator drawn at each call
would give a test different noise on every run, depending on how many
publishes happened to fall between two cycles. Here the noise of a reading is
fixed by *what* is read and *when*, in machine time:

    noise(seed, stream, sample index) → one normal draw per channel of the stream

computed with a counter-based generator (Philox 4×64, numpy's
:class:`numpy.random.Philox`): the key is (seed, stream), the counter holds the
sample index (machine time in sub-steps) in its second word, so the draws for
one sample (which advance the first word) never overlap another sample's. Asking
twice for the same sample gives the same values; the offline recorder and the
served machine read the same function, so a recording and a served run with the
same seed and programme see the same noise.

Streams: ``SENSORS`` gives one value per transmitter channel, in the machine's
channel order (the sensors of ``machine.yaml``, then the ambient sensor);
``PROBE`` gives the probe's measurement noise in Z, :func:`axis_probe_stream` in
X or Y (a stream of its own per axis, so adding an axis leaves Z's noise alone).
"""

from __future__ import annotations

import numpy as np

SENSORS = 0
PROBE = 1

_WORD = (1 << 64) - 1
_AXIS_PROBES = 0x100


def axis_probe_stream(axis: str) -> int:
    """The probe-noise stream of axis ``axis`` (one letter): fixed by its name."""
    return _AXIS_PROBES + ord(axis)


class MachineNoise:
    """Standard-normal draws keyed by (seed, stream, sample index)."""

    def __init__(self, seed: int) -> None:
        self.seed = int(seed)
        self._bits = np.random.Philox(key=np.array([self.seed & _WORD, SENSORS], dtype=np.uint64))
        self._generator = np.random.Generator(self._bits)

    def normal(self, stream: int, index: int, count: int) -> np.ndarray:
        """``count`` standard-normal values for sample ``index`` of ``stream``."""
        state = self._bits.state
        state["state"] = {
            "counter": np.array([0, int(index) & _WORD, 0, 0], dtype=np.uint64),
            "key": np.array([self.seed & _WORD, stream], dtype=np.uint64),
        }
        state["buffer_pos"] = 4  # nothing buffered from an earlier sample
        state["has_uint32"] = 0
        self._bits.state = state
        return self._generator.standard_normal(count)
