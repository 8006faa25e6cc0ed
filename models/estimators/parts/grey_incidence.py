"""Grey absolute degree of incidence between the thermal error and a sensor.

Liu, S. & Lin, Y. (2010), *Grey Systems: Theory and Applications*, Springer,
§3.3 "absolute degree of grey incidence". For equal-interval sequences X0 (the
reference, here the thermal error) and Xi (a sensor) of the same length n ≥ 2:

    zero-starting images   x⁰(k) = x(k) − x(1)
    s  = Σ_{k=2}^{n−1} x⁰(k) + ½ x⁰(n)       (trapezoid area of the image)
    ε0i = (1 + |s0| + |si|) / (1 + |s0| + |si| + |si − s0|)

where |si − s0| = |Σ_{k=2}^{n−1} (xi⁰(k) − x0⁰(k)) + ½ (xi⁰(n) − x0⁰(n))|.

Properties: ε0i = εi0 (symmetric); adding a constant to either sequence leaves
ε unchanged (zero-starting images); ε = 1 iff si = s0. Because
|si − s0| ≤ |s0| + |si| = a, ε ≥ (1 + a) / (1 + 2a) > ½, so ε ∈ (0.5, 1].

Paper 002 (Miao et al. 2015, §3) prints grades of 0.38–0.43, all below 0.5;
they therefore cannot come from this textbook formula, and the paper does not
print the variant it used. The project reproduces the paper's *selection
structure* (rank the sensors by grade within each cluster, the highest wins),
not its printed grade values.

The grade is unit-sensitive by design: "absolute" means the sequences are not
initialised or normalised, so s0 and si are compared as areas in their own
units. Here the reference is the thermal error in µm and the sequences are
temperature rises in °C; a sensor ranks high when the area under its rise (°C)
is close to the area under the error (µm). The areas are sums over samples, so
they also scale with the number of samples.
"""

from __future__ import annotations

import numpy as np


def _area(x: np.ndarray) -> np.ndarray:
    """Signed s = Σ_{k=2}^{n−1} x⁰(k) + ½ x⁰(n) along axis 0 (x⁰ = x − x(1))."""
    zero_start = x - x[0]
    return zero_start[1:-1].sum(axis=0) + 0.5 * zero_start[-1]


def _degrees(reference: np.ndarray, sequences: np.ndarray) -> np.ndarray:
    """ε of each column of ``sequences`` (n, p) against ``reference`` (n,); no checks."""
    s0 = _area(reference)
    si = _area(sequences)
    a = 1 + abs(s0) + np.abs(si)
    return a / (a + np.abs(si - s0))


def absolute_degree(reference: np.ndarray, sequence: np.ndarray) -> float:
    """Grey absolute degree of incidence ε0i of ``sequence`` to ``reference``.

    Both 1-D, same length n ≥ 2, finite, equally spaced (Liu & Lin 2010, §3.3;
    formula in the module docstring). Returns a value in (0.5, 1].
    """
    x0 = np.asarray(reference, dtype=float)
    xi = np.asarray(sequence, dtype=float)
    if x0.ndim != 1 or xi.shape != x0.shape:
        raise ValueError(
            f"reference and sequence must be 1-D of the same length, got {x0.shape} and {xi.shape}"
        )
    return float(absolute_degrees(x0, xi[:, None])[0])


def _segment_bounds(segments: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each contiguous block of equal segment numbers."""
    change = np.flatnonzero(np.diff(segments) != 0) + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [segments.size]))
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def absolute_degrees(
    reference: np.ndarray, sequences: np.ndarray, segments: np.ndarray | None = None
) -> np.ndarray:
    """Absolute degree of every column of ``sequences`` (n, p) to ``reference`` (n,).

    With ``segments`` (n,) integer run numbers, each contiguous block of equal
    numbers is its own pair of sequences (a run starts its own zero-starting
    image); the result is the mean of the per-block degrees weighted by block
    length. Blocks shorter than 2 samples are skipped. A run number that comes
    back after another run counts as a new block.

    Returns a (p,) array.
    """
    x0 = np.asarray(reference, dtype=float)
    xs = np.asarray(sequences, dtype=float)
    if x0.ndim != 1:
        raise ValueError(f"reference must be 1-D (n,), got shape {x0.shape}")
    if xs.ndim != 2 or xs.shape[0] != x0.shape[0]:
        raise ValueError(f"sequences must be ({x0.shape[0]}, p), got shape {xs.shape}")
    if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(xs))):
        raise ValueError("reference and sequences must be finite (found NaN or inf)")
    if segments is None:
        bounds = [(0, x0.shape[0])]
    else:
        seg = np.asarray(segments)
        if seg.shape != x0.shape or not np.issubdtype(seg.dtype, np.integer):
            raise ValueError(
                f"segments must be ({x0.shape[0]},) integer run numbers, "
                f"got shape {seg.shape} dtype {seg.dtype}"
            )
        bounds = _segment_bounds(seg)
    bounds = [(start, stop) for start, stop in bounds if stop - start >= 2]
    if not bounds:
        raise ValueError("need a sequence (or segment) of at least 2 samples")
    total = np.zeros(xs.shape[1])
    weight = 0
    for start, stop in bounds:
        total += (stop - start) * _degrees(x0[start:stop], xs[start:stop])
        weight += stop - start
    return total / weight
