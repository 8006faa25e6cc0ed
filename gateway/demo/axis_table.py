"""The demo's table per axis: the error at the tool without and with compensation, µm.

Every axis the simulated machine grows in gets a row, compensated or not (an axis
the gateway does not compensate shows the same figures twice, and says so), so the
gain of each compensated axis is read against the error it started from.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

HEADER = (
    f"    {'axis':4s}  {'RMS without':>11s}  {'RMS with':>9s}  "
    f"{'max without':>11s}  {'max with':>9s}  {'RMS reduced':>11s}"
)


def axis_table(
    figures: Mapping[str, Mapping[str, float]], compensated: Collection[str]
) -> list[str]:
    """The table's lines: a header, then one row per axis of ``figures``.

    ``figures`` maps an axis to its peak and RMS error without and with compensation
    (:func:`simulator.closed_loop.error_figures`); ``compensated`` names the axes the
    gateway wrote a compensation for.
    """
    lines = [HEADER]
    for axis, f in figures.items():
        without, with_ = f["uncompensated_rmse_um"], f["compensated_rmse_um"]
        reduced = (
            f"{100.0 * (1.0 - with_ / without):10.1f}%"
            if axis in compensated and without > 0
            else f"{'not compensated':>11s}"
        )
        lines.append(
            f"    {axis:4s}  {without:11.2f}  {with_:9.2f}  "
            f"{f['uncompensated_peak_um']:11.2f}  {f['compensated_peak_um']:9.2f}  {reduced}"
        )
    return lines
