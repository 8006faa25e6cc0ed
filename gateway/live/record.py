"""What one cycle measured and decided, and where it goes: the record every output reads.

Apart from the loop (:mod:`gateway.live.loop`) so that the outputs, the SCADA server,
the Sparkplug node and the web console can take a record without importing the loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field


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


Sink = Callable[[CycleRecord], None]


def sink_name(sink: Sink) -> str:
    """A readable name for a sink (its qualified name; a bound method names its class)."""
    return str(getattr(sink, "__qualname__", None) or type(sink).__name__)
