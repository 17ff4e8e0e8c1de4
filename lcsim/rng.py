"""Counter-based random numbers: a pure function of (key, step, index).

The draw for vehicle ``i`` of an environment at step ``k`` does not depend on how many environments
share the batch, so a batch of E environments and E single environments with the same seeds produce
bit-identical results, with no per-environment Python loop in the hot path.
"""

from __future__ import annotations

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _mix(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on a uint64 array (wrapping arithmetic)."""
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def uniform(key: np.ndarray, step: np.ndarray, n: int, stream: int = 0) -> np.ndarray:
    """Uniform draws in [0, 1).

    Args:
        key: ``(E,)`` uint64 per-environment key (from the episode seed).
        step: ``(E,)`` int64 simulation step of each environment.
        n: number of draws per environment (one per vehicle).
        stream: separates independent uses at the same step.

    Returns:
        ``(E, n)`` float64.
    """
    with np.errstate(over="ignore"):
        base = _mix(key.astype(np.uint64) ^ (np.uint64(stream) * _M2))
        ctr = step.astype(np.uint64)[:, None] * np.uint64(1 << 20) + np.arange(n, dtype=np.uint64)[None, :]
        z = _mix(base[:, None] + ctr * _GOLDEN)
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))
