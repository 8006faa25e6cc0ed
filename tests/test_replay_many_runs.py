"""``replay`` over many runs: each base fit made once, on every core, with a progress bar,
and the same figures as fitting each one on demand."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from models.data.dataset import load_runs
from models.data.features import prepare
from models.online import declared_fits
from models.online.replay import offline_accuracy, replay_interval
from tests.cli import gateway
from tests.many_runs import write_campaign_csv


def campaign_csv(folder: Path, n_runs: int = 12) -> Path:
    return write_campaign_csv(folder / "campaign.csv", n_runs=n_runs, hours=(1.5, 2.5), seed=3)


def assert_same(a, b, path: str = "") -> None:
    """Equal structure; every number within 1e-9."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for key in a:
            assert_same(a[key], b[key], f"{path}/{key}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert math.isclose(a, b, rel_tol=0, abs_tol=1e-9), (path, a, b)
    else:
        assert a == b, path


def test_prefilled_fits_give_the_figures_of_fits_made_on_demand(tmp_path: Path) -> None:
    """The model fitted does not matter to what is kept (mlr: fast); the benchmark
    benchmarks/replay_speed.py compares lag-ridge's figures before and after."""
    prepared = prepare(load_runs(campaign_csv(tmp_path)))
    declared_fits.clear()
    on_demand = [
        replay_interval(prepared, m, base="declared", method="mlr").as_dict() for m in (30.0, 60.0)
    ]
    offline = offline_accuracy(prepared, "mlr", None)
    assert declared_fits.kept_on_demand() > 0
    declared_fits.clear()
    # 12 runs: each left out (12 sets), and in each the 11 others in 5 inner folds
    # (60), of which 11 leave the same runs out as another held-out run's fold.
    sets = declared_fits.training_sets(prepared)
    assert len(sets) == 61 and len({m.tobytes() for m in sets}) == 61
    assert declared_fits.prefill(prepared, "mlr", None) == 61
    prefilled = [
        replay_interval(prepared, m, base="declared", method="mlr").as_dict() for m in (30.0, 60.0)
    ]
    assert_same(on_demand, prefilled)
    assert_same(offline, offline_accuracy(prepared, "mlr", None))
    assert declared_fits.kept_on_demand() == 0  # every fit the replay needed was prefilled
    declared_fits.clear()


def test_replay_shows_progress_over_twelve_runs_on_stderr(tmp_path: Path) -> None:
    out = tmp_path / "replay.json"
    done = gateway(
        "replay", campaign_csv(tmp_path), "--model", "mlr", "--probe-interval-min", "60",
        "--json", out, "--progress",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    # The bars count up as the fits end (in worker processes) and the runs are replayed.
    assert re.search(r"base fits: .*\b[1-9]\d*/61 ", done.stderr)
    assert re.search(r"held-out runs, probe every 60 min: .*\b[1-9]\d*/12 ", done.stderr)
    assert "base fits" not in done.stdout
    assert len(json.loads(out.read_text())["online"][0]["per_run"]) == 12
