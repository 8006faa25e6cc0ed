"""The offline commands on several targets: the file read and prepared once, then each
target's work in turn (``--target`` repeated, or ``--target all``).

Each target gets exactly the rows and preparation a run on that target alone would
(:mod:`models.data.targets`): the temperature rises, recordings and reference rows are
taken once and shared by every target whose rows are the file's; only the error and its
origins are taken per target. Targets run one after another: the work of each already
uses the cores (:mod:`models.fit.crossval`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

from models.data.dataset import MeasuredRuns
from models.data.features import Prepared, prepare, retarget
from models.data.targets import view


@dataclass(frozen=True)
class TargetRuns:
    """One target's runs (its sensors' readings kept) and their preparation (without)."""

    target: str
    data: MeasuredRuns
    prepared: Prepared


def each_target(
    data: MeasuredRuns,
    targets: Sequence[str],
    sensors: Sequence[str] | None,
    reference: str = "auto",
    progress: bool = False,
    sparse_target: bool = False,
    readings: bool = False,
) -> Iterator[TargetRuns]:
    """Every target's runs and preparation, the rises taken once for the targets whose
    rows are the whole file (a target with empty cells of its own is prepared alone).
    ``readings``: the preparation keeps the sensors' readings (replay reads them);
    ``progress``: a bar over the targets (several only), each named as it starts."""
    from tqdm import tqdm

    shared: Prepared | None = None
    bar = tqdm(
        total=len(targets),
        desc=f"target {targets[0]}" if targets else None,
        unit="target",
        disable=not progress or len(targets) < 2,
    )
    for target in targets:
        bar.set_description(f"target {target}")
        runs = view(data, target, sensors, sparse_target)
        if shared is not None and runs.n_samples == data.n_samples:
            prepared = retarget(shared, runs if readings else replace(shared.data, target=target))
        else:
            prepared = prepare(runs, sensors, reference)
            prepared = prepared if readings else prepared.without_sensor_readings()
            if runs.n_samples == data.n_samples:
                shared = prepared
        yield TargetRuns(target, runs, prepared)
        bar.update(1)
    bar.close()


def say_heading(
    one: TargetRuns,
    data: MeasuredRuns,
    targets: Sequence[str],
    say: Callable[[str], None],
    note: Callable[[str], None],
) -> None:
    """The line that opens a target's section of the text report (several targets only),
    and the rows it leaves out when they are more than the file's (an empty cell of its own)."""
    if len(targets) < 2:
        return
    say(f"\n=== target {one.target} ({targets.index(one.target) + 1} of {len(targets)}) ===")
    if one.data.n_samples != data.n_samples:
        for skipped in one.data.skipped:
            note(f"note: {one.target}: {skipped.describe()}")


def combined(
    results: dict[str, dict[str, Any]], shared: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The command's JSON: one target's object as it is; several keyed by target under
    ``targets``, with the fields that do not depend on the target beside it."""
    if len(results) == 1:
        return next(iter(results.values()))
    return {**(shared or {}), "targets": results}
