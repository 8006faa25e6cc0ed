"""Plain-text tables for the command line (units in every header)."""

from __future__ import annotations

from collections.abc import Sequence

from models.fit.crossval import Validation
from models.fit.forward import Forward
from models.fit.ranking import SigmaRow, sigma_matrix


def render(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Left-aligned first column, right-aligned numbers, two spaces apart."""
    table = [list(header), *[list(r) for r in rows]]
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    lines = []
    for row in table:
        cells = [row[0].ljust(widths[0])] + [
            c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)
        ]
        lines.append("  ".join(cells).rstrip())
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def accuracy_table(validation: Validation | Forward) -> str:
    rows = [
        [fold, f"{a.rmse_um:.2f}", f"{a.sigma_um:.2f}", f"{a.max_abs_um:.2f}", str(a.n_samples)]
        for fold, a in validation.per_fold.items()
    ]
    p = validation.pooled
    rows.append(
        ["pooled", f"{p.rmse_um:.2f}", f"{p.sigma_um:.2f}", f"{p.max_abs_um:.2f}", str(p.n_samples)]
    )
    return render(["held-out", "RMSE µm", "σ µm", "max|e| µm", "n"], rows)


def sigma_matrix_table(rows: list[SigmaRow]) -> str:
    models, runs, sigma = sigma_matrix(rows)
    body = [[m, *[f"{s:.2f}" for s in sigma[i]]] for i, m in enumerate(models)]
    return render(["model \\ data", *runs], body)
