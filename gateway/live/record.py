"""What one cycle measured and decided, and where it goes: the record every output reads.

Apart from the loop (:mod:`gateway.live.loop`) so that the outputs, the SCADA server,
the Sparkplug node and the web console can take a record without importing the loop.

A record carries two times: ``time_s``, machine time (monotonic on the wall clock: what
the loop schedules and computes rates on), and ``stamp_s``, the wall time taken once
at the cycle's start, which every output stamps the cycle with (see
:mod:`drivers.clock`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class AxisRecord:
    """What one cycle decided for one axis of a multi-axis machine (units in the names).

    A machine configured with ``compensation.axes`` predicts and writes every axis from
    the cycle's one poll; each axis's outcome is one of these, in
    :attr:`CycleRecord.axes`. The fields mean what the same-named fields of
    :class:`CycleRecord` mean, for this axis's model and macro.
    """

    axis: str  # "X", "Y", "Z", ...
    macro: int  # the macro variable this axis's compensation is written to
    model_id: str | None = None
    predicted_um: float | None = None
    target_um: float | None = None
    applied_um: float | None = None
    written_cnc: float | None = None
    write_status: str = ""
    correction_um: float | None = None
    interval_um: float | None = None
    training_span: str | None = None
    outside_inputs: list[str] = field(default_factory=list)
    uncertain: bool = False


@dataclass
class CycleRecord:
    """Everything one cycle measured and decided (units in the names)."""

    machine: str
    time_s: float
    temperatures_C: dict[str, float | None]
    quality: dict[str, str]
    quality_reasons: dict[str, str]
    speed_rpm: float | None
    regime: str | None
    model_id: str | None
    predicted_um: float | None
    target_um: float | None
    applied_um: float | None
    written_cnc: float | None
    write_status: str
    link_errors: list[str] = field(default_factory=list)
    probe_error_um: float | None = None  # a new probe measurement of the real error, µm
    correction_um: float | None = None  # online correction added to predicted_um, µm
    probe_refused: bool = False  # the online correction refused this cycle's probe value
    #: half-width of the calibrated interval around predicted_um, µm (None: unknown);
    #: see gateway/live/interval.py
    interval_um: float | None = None
    #: "inside" / "outside" the model's training span, None when unknown
    training_span: str | None = None
    outside_inputs: list[str] = field(default_factory=list)  # inputs outside the span
    #: compensation.when_uncertain held or scaled this cycle's aim
    uncertain: bool = False
    #: The wall time of the cycle's start (Unix s, :meth:`drivers.clock.Clock.stamp`), taken
    #: once: every output stamps the cycle with it. None: a record made without one, whose
    #: outputs take ``time_s``.
    stamp_s: float | None = None
    #: Every axis of a machine configured with ``compensation.axes``, by axis name, in
    #: the configured order (empty for the single-axis form). The per-axis fields above
    #: (model_id, predicted_um, ..., uncertain) then repeat the first axis's, so a reader
    #: that knows one axis sees the first.
    axes: dict[str, AxisRecord] = field(default_factory=dict)

    @property
    def stamped_s(self) -> float:
        """The time every output gives this cycle: its wall stamp, else its machine time."""
        return self.time_s if self.stamp_s is None else self.stamp_s


Sink = Callable[[CycleRecord], None]


def sink_name(sink: Sink) -> str:
    """A readable name for a sink (its qualified name; a bound method names its class)."""
    return str(getattr(sink, "__qualname__", None) or type(sink).__name__)
