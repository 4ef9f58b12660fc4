"""Argument checks of the GP expert (flightstack/paper/gp.py, Saito et al., IFAC 2023, "Distributed GP").

The data set D^{(j)} = {X^{(j)}, Y^{(j)}} of one expert: X (M, Din) inputs x = [x, y, z, θ] (m, rad), Y (M, D)
outputs (body velocity of the target, m/s and rad/s); the fixed noise variance σ_n² (scalar or (D,), output
units squared) and the natural-log bounds of the hyperparameter search. Every check raises ValueError with
the offending shape or value; arrays are returned as float64 (read-only copies from :func:`readonly`).
"""

from __future__ import annotations

import math

import numpy as np


def as_finite_2d(a: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    return arr


def validate_training_data(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    X = as_finite_2d(X, "X")
    Y = as_finite_2d(Y, "Y")
    if X.shape[0] != Y.shape[0]:
        raise ValueError(f"X and Y must have the same number of rows (M), got X {X.shape} and Y {Y.shape}")
    if X.shape[0] < 2:
        raise ValueError(f"need at least M = 2 training points, got M = {X.shape[0]}")
    if X.shape[1] < 1 or Y.shape[1] < 1:
        raise ValueError(f"X and Y need at least one column, got X {X.shape} and Y {Y.shape}")
    return X, Y


def validate_noise_var(noise_var: float | np.ndarray, n_outputs: int) -> np.ndarray:
    nv = np.asarray(noise_var, dtype=float)
    if nv.ndim == 0:
        nv = np.full(n_outputs, float(nv))
    if nv.shape != (n_outputs,):
        raise ValueError(f"noise_var must be a scalar or have shape ({n_outputs},), got shape {nv.shape}")
    if not np.all(np.isfinite(nv)) or np.any(nv <= 0.0):
        raise ValueError(f"noise_var (σ_n²) must be finite and > 0, got {nv}")
    return nv


def validate_log_bounds(bounds: tuple[float, float], name: str) -> tuple[float, float]:
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a pair (lo, hi) of floats, got {bounds!r}") from exc
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"{name} must be finite with lo < hi, got {(lo, hi)}")
    return lo, hi


def readonly(a: np.ndarray) -> np.ndarray:
    out = np.array(a, dtype=float, copy=True)
    out.setflags(write=False)
    return out
