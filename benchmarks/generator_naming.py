"""What `analyze` names first, and how much it removes, on the two independent generators.

For every hidden effect of ``tests/independent_shaft.py`` (logging gaps, runs that
open at speed) and ``tests/independent_machine.py`` (every run opening at speed) and
each seed, the mlr model's residual analysis is run once; the table gives, per
effect, on how many seeds the hidden effect was named first, the mean held-out RMSE
before and after, and the worst after/before ratio. The README's generator table
comes from here; run it on two commits for an A/B.

    .venv/bin/python benchmarks/generator_naming.py [--seeds 8]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from models.analysis.search import analyze  # noqa: E402
from models.data.dataset import load_runs  # noqa: E402
from models.data.features import prepare  # noqa: E402
from tests import independent_machine, independent_shaft  # noqa: E402

NETWORK_PROGRAMS = ("const-6000", "staircase", "spectrum", "rest-cycles", "warmup-production")


def write(generator: str, effect: str, seed: int, workdir: Path) -> Path:
    path = workdir / f"{generator}-{effect}-{seed}.csv"
    if generator == "shaft":
        return independent_shaft.write_csv(path, effect, seed)
    return independent_machine.write_csv(path, effect, seed, programs=NETWORK_PROGRAMS)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    args = parser.parse_args()
    columns = ("generator", "effect", "named first", "other names", "before µm", "after µm")
    print("| " + " | ".join(columns) + " | worst after/before |")
    print("|---|---|---|---|---:|---:|---:|")
    cases = [("shaft", e) for e in independent_shaft.EFFECTS]
    cases += [("network", e) for e in independent_machine.EFFECTS]
    with tempfile.TemporaryDirectory() as tmp:
        for generator, effect in cases:
            named: Counter[str] = Counter()
            before, after, ratios = [], [], []
            for seed in range(args.seeds):
                prepared = prepare(load_runs(write(generator, effect, seed, Path(tmp))))
                result, _, _ = analyze(prepared, "mlr", progress=False)
                named[result.effect] += 1
                before.append(result.before.rmse_um)
                after.append(result.after.rmse_um)
                ratios.append(result.after.rmse_um / result.before.rmse_um)
            others = ", ".join(f"{k} {v}" for k, v in named.most_common() if k != effect)
            print(
                f"| {generator} | {effect} | {named[effect]}/{args.seeds} | {others or '–'} | "
                f"{sum(before) / len(before):.2f} | {sum(after) / len(after):.2f} | "
                f"{max(ratios):.2f} |"
            )


if __name__ == "__main__":
    main()
