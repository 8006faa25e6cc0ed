"""Is the spindle temperature field speed-dependent? One-way MANOVA and ANOVA.

Source: paper 000 (Wang & Wu, spindle thermal error under variable speed, §2.1).
The paper groups 561 samples of 9 temperature sensors by spindle speed
(0/2000/4000/6000/8000 r/min, g = 5) and runs MATLAB ``manova1`` at α = 0.05,
getting d = 4, p = [0, 0, 0, 6.828e-7]; then a one-way ANOVA per sensor
(T1 p = 0.2629 … T5 p = 0). A sensor whose mean moves with speed is worth
feeding to a speed-aware model; one that does not is a candidate to drop.

MANOVA, exactly as MATLAB ``manova1`` computes it
(n samples, p variables, g groups, x̄_k the mean of group k, x̄ the grand mean):

- W = Σ_k Σ_{i∈k} (x_i − x̄_k)(x_i − x̄_k)ᵀ        within-group SSCP
- B = Σ_k n_k (x̄_k − x̄)(x̄_k − x̄)ᵀ                between-group SSCP
- T = W + B
- λ_1 ≥ λ_2 ≥ … eigenvalues of W⁻¹B, solved as the generalized symmetric
  problem B v = λ W v (``scipy.linalg.eigh(B, W)``); keep s = min(p, g − 1).
  B has rank ≤ g − 1, so the rest are zero.
- for j = 0 … s − 1:
    Λ_j  = ∏_{i>j} 1 / (1 + λ_i)     Wilks' Λ for "the group means lie in a
                                       j-dimensional space"; Λ_0 = det W / det T
    χ²_j = −(n − 1 − (p + g)/2) · ln Λ_j     (Bartlett's approximation)
    dof_j = (p − j)(g − 1 − j)
    p_j  = P(χ²(dof_j) > χ²_j)
- d = smallest j with p_j > α (the means cannot be shown to need more than
  j dimensions); d = s when every p_j ≤ α.

d = 0 means speed has no detectable effect on the mean temperature vector.

ANOVA per sensor is ``scipy.stats.f_oneway``:
F = [SS_between / (g − 1)] / [SS_within / (n − g)], p = P(F(g−1, n−g) > F).

Refused (ValueError): non-2-D or non-finite values, NaN labels, shape mismatch,
no samples, fewer than 2 groups, n − g < p or a singular W (constant or
collinear sensors) for MANOVA, n − g < 1 or a constant sensor for ANOVA.
Groups are built from the labels present, so every group has ≥ 1 sample.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import linalg, stats


@dataclass(frozen=True)
class ManovaResult:
    """One-way MANOVA outcome in MATLAB ``manova1`` terms (see module docstring)."""

    wilks_lambda: float  # Λ_0 = det W / det(W + B)
    eigenvalues: tuple[float, ...]  # λ_1 ≥ … ≥ λ_s of W⁻¹B
    d: int  # dimension of the space the group means span, at alpha
    p_values: tuple[float, ...]  # p_0 … p_{s−1}
    chi2: tuple[float, ...]  # Bartlett χ²_0 … χ²_{s−1}
    dof: tuple[int, ...]  # (p − j)(g − 1 − j)
    n_samples: int
    n_groups: int
    n_variables: int
    alpha: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: tuples become lists."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass(frozen=True)
class AnovaResult:
    """One-way ANOVA of one sensor against the speed groups."""

    variable: str
    f_stat: float
    p_value: float
    df_between: int  # g − 1
    df_within: int  # n − g
    significant: bool  # p_value <= alpha: the sensor's mean depends on speed

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def speed_groups(speed_rpm: np.ndarray, band_rpm: float = 100.0) -> np.ndarray:
    """Label each sample by its speed rounded to the nearest multiple of ``band_rpm``.

    Measured spindle speed jitters around the commanded value (1998, 2003 r/min
    for a 2000 r/min step); rounding puts those samples in the same group, so
    the MANOVA sees the paper's 5 speed levels instead of hundreds of groups.
    Halves round up (2050 → 2100 with band 100): floor(speed / band + 0.5) · band.
    Returns a float array of the same shape, in r/min.
    """
    speed = np.asarray(speed_rpm, dtype=float)
    if not math.isfinite(band_rpm) or band_rpm <= 0:
        raise ValueError(f"band_rpm must be a positive finite number, got {band_rpm}")
    if not np.all(np.isfinite(speed)):
        raise ValueError("speed_rpm contains NaN or inf")
    return np.floor(speed / band_rpm + 0.5) * band_rpm + 0.0  # + 0.0 turns −0 into 0


def _check_inputs(
    values: np.ndarray, groups: np.ndarray, alpha: float
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Validate and return (values as float (n, p), list of per-group row arrays)."""
    x = np.asarray(values, dtype=float)
    labels = np.asarray(groups)
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    if x.ndim != 2:
        raise ValueError(f"values must be 2-D (n samples, p variables), got shape {x.shape}")
    if labels.ndim != 1 or labels.shape[0] != x.shape[0]:
        raise ValueError(
            f"shape mismatch: groups {labels.shape} must be 1-D with one label per row "
            f"of values {x.shape}"
        )
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"no samples or no variables: values shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("values contain NaN or inf")
    rows: dict[Hashable, list[int]] = {}
    for i, label in enumerate(labels.tolist()):
        if isinstance(label, float | complex) and not np.isfinite(label):
            raise ValueError("groups contain NaN or inf labels")  # NaN != NaN: no group
        rows.setdefault(label, []).append(i)
    if len(rows) < 2:
        raise ValueError(f"need at least 2 groups to compare, got {len(rows)}")
    return x, [x[idx] for idx in rows.values()]


def manova_oneway(values: np.ndarray, groups: np.ndarray, alpha: float = 0.05) -> ManovaResult:
    """One-way MANOVA of ``values`` (n, p), °C, grouped by ``groups`` (n,) labels.

    Labels may be any hashable (e.g. speed in r/min from :func:`speed_groups`).
    Implements MATLAB ``manova1``'s d / p / Wilks' Λ; formulas in the module docstring.
    """
    x, parts = _check_inputs(values, groups, alpha)
    n, p = x.shape
    g = len(parts)
    if n - g < p:
        raise ValueError(
            f"too few samples: n - g = {n} - {g} = {n - g} < p = {p} variables, "
            "so the within-group matrix W is singular"
        )
    grand = x.mean(axis=0)
    W = np.zeros((p, p))
    B = np.zeros((p, p))
    for part in parts:
        mean = part.mean(axis=0)
        dev = part - mean
        W += dev.T @ dev
        B += len(part) * np.outer(mean - grand, mean - grand)
    # Rank of W scaled to unit diagonal, so sensors in different units weigh alike;
    # eigh alone may "succeed" on a W that is singular up to round-off.
    scale = np.sqrt(np.diag(W))
    if np.any(scale == 0) or np.linalg.matrix_rank(W / np.outer(scale, scale)) < p:
        raise ValueError(
            "within-group matrix W is singular (a sensor constant within every group, or "
            "sensors that are exact linear combinations of each other)"
        )
    lam = linalg.eigh(B, W, eigvals_only=True)
    s = min(p, g - 1)
    lam = np.clip(lam[::-1][:s], 0.0, None)  # descending; clip round-off below 0

    bartlett = n - 1 - (p + g) / 2
    log1p = np.log1p(lam)
    log_lambdas = [-float(np.sum(log1p[j:])) for j in range(s)]  # ln Λ_j
    chi2 = tuple(-bartlett * ll for ll in log_lambdas)
    dof = tuple((p - j) * (g - 1 - j) for j in range(s))
    p_values = tuple(float(stats.chi2.sf(c, k)) for c, k in zip(chi2, dof, strict=True))
    d = next((j for j, pv in enumerate(p_values) if pv > alpha), s)
    return ManovaResult(
        wilks_lambda=math.exp(log_lambdas[0]),
        eigenvalues=tuple(float(v) for v in lam),
        d=d,
        p_values=p_values,
        chi2=chi2,
        dof=dof,
        n_samples=n,
        n_groups=g,
        n_variables=p,
        alpha=alpha,
    )


def anova_oneway(
    values: np.ndarray, groups: np.ndarray, names: Sequence[str], alpha: float = 0.05
) -> list[AnovaResult]:
    """One-way ANOVA (``scipy.stats.f_oneway``) of each column of ``values`` by group.

    ``names`` labels the columns (e.g. "T1" … "T9") in the result and the table.
    """
    x, parts = _check_inputs(values, groups, alpha)
    n, p = x.shape
    g = len(parts)
    if len(names) != p:
        raise ValueError(f"shape mismatch: {len(names)} names for {p} value columns")
    if n - g < 1:
        raise ValueError(f"too few samples: n - g = {n - g}, no within-group degrees of freedom")
    out = []
    for col, name in enumerate(names):
        if np.all(x[:, col] == x[0, col]):
            raise ValueError(f"sensor {name!r} is constant; F is undefined")
        res = stats.f_oneway(*(part[:, col] for part in parts))
        pv = float(res.pvalue)
        out.append(
            AnovaResult(
                variable=str(name),
                f_stat=float(res.statistic),
                p_value=pv,
                df_between=g - 1,
                df_within=n - g,
                significant=pv <= alpha,
            )
        )
    return out


def format_table(manova: ManovaResult, anova: list[AnovaResult]) -> str:
    """Plain-text report: MANOVA summary, one line per dimension test, one per sensor."""
    lines = [
        f"MANOVA by spindle speed: n = {manova.n_samples} samples, "
        f"g = {manova.n_groups} speed groups, p = {manova.n_variables} sensors, "
        f"alpha = {manova.alpha:g}",
        f"Wilks' lambda = {manova.wilks_lambda:.4g}",
        f"d = {manova.d} (group means span {manova.d} dimension(s); 0 = no speed effect)",
        f"{'j':>3} {'chi2':>12} {'dof':>5} {'p':>12}",
    ]
    for j, (c, k, pv) in enumerate(zip(manova.chi2, manova.dof, manova.p_values, strict=True)):
        lines.append(f"{j:>3} {c:>12.4g} {k:>5d} {pv:>12.4g}")
    lines += ["", "ANOVA per sensor (speed-dependent: p <= alpha)"]
    width = max([len("sensor"), *(len(a.variable) for a in anova)])
    lines.append(f"{'sensor':<{width}} {'F':>12} {'p':>12}  speed-dependent")
    for a in anova:
        verdict = "speed-dependent" if a.significant else "no"
        lines.append(f"{a.variable:<{width}} {a.f_stat:>12.4g} {a.p_value:>12.4g}  {verdict}")
    return "\n".join(lines)
