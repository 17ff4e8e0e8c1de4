"""Counter-based random numbers: a pure function of (key, step, index).

The draw for vehicle ``i`` of an environment at step ``k`` does not depend on how many environments
share the batch, so a batch of E environments and E single environments with the same seeds produce
bit-identical results, with no per-environment Python loop in the hot path.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

_MASK = (1 << 64) - 1
_M2_INT = 0x94D049BB133111EB  # (also folded into the stream constant as a Python int)
_GOLDEN, _M1, _M2 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(_M2_INT)
_S11, _S27, _S30, _S31 = np.uint64(11), np.uint64(27), np.uint64(30), np.uint64(31)
_STEP_STRIDE = np.uint64(1 << 20)


def _mix(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on a uint64 array (array arithmetic wraps silently)."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@lru_cache(maxsize=8)
def _counters(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.uint64)[None, :]


def stream_base(key: np.ndarray, stream: int = 0) -> np.ndarray:
    """``(E,)`` uint64: the part of :func:`uniform` that depends on the key and stream only (a caller that
    draws from one stream many times with fixed keys computes it once)."""
    # Only arrays take part in the wrapping arithmetic (numpy warns on overflowing scalar operations,
    # and an errstate context costs more than the draws): the stream constant is a Python int.
    return _mix(key.astype(np.uint64) ^ np.uint64((stream * _M2_INT) & _MASK))


def uniform(key: np.ndarray, step: np.ndarray, n: int, stream: int = 0, *, base: np.ndarray | None = None,
            ) -> np.ndarray:
    """Uniform draws in [0, 1).

    Args:
        key: ``(E,)`` uint64 per-environment key (from the episode seed).
        step: ``(E,)`` int64 simulation step of each environment.
        n: number of draws per environment (one per vehicle).
        stream: separates independent uses at the same step.
        base: ``stream_base(key, stream)`` when the caller keeps it (the same draws, fewer operations).

    Returns:
        ``(E, n)`` float64.
    """
    if base is None:
        base = stream_base(key, stream)
    ctr = step.astype(np.uint64)[:, None] * _STEP_STRIDE
    ctr = ctr + _counters(n)
    ctr *= _GOLDEN
    ctr += base[:, None]
    z = _mix(ctr)
    return (z >> _S11).astype(np.float64) * (1.0 / (1 << 53))
