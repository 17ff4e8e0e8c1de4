"""Counter-based random numbers: a pure function of (key, step, index).

The draw for vehicle ``i`` of an environment at step ``k`` does not depend on how many environments
share the batch, so a batch of E environments and E single environments with the same seeds produce
bit-identical results. The draws themselves are the compiled core's (:func:`lcsim.kernel.uniform_one`, a
splitmix64 of the counter ``step * 2**20 + i`` mixed with the stream's base); this module gives them on arrays.
"""

from __future__ import annotations

import numpy as np

from lcsim import kernel

_MASK = (1 << 64) - 1
_M2_INT = 0x94D049BB133111EB


def stream_base(key: np.ndarray, stream: int = 0) -> np.ndarray:
    """``(E,)`` uint64: the part of :func:`uniform` that depends on the key and stream only (a caller that
    draws from one stream many times with fixed keys computes it once)."""
    keys = np.ascontiguousarray(key, dtype=np.uint64).reshape(-1)
    return kernel.stream_bases(keys, np.uint64((stream * _M2_INT) & _MASK))


def uniform(key: np.ndarray, step: np.ndarray, n: int, stream: int = 0, *, base: np.ndarray | None = None,
            ) -> np.ndarray:
    """Uniform draws in [0, 1).

    Args:
        key: ``(E,)`` uint64 per-environment key (from the episode seed).
        step: ``(E,)`` int64 simulation step of each environment.
        n: number of draws per environment (one per vehicle).
        stream: separates independent uses at the same step.
        base: ``stream_base(key, stream)`` when the caller keeps it (the same draws).

    Returns:
        ``(E, n)`` float64.
    """
    if base is None:
        base = stream_base(key, stream)
    return kernel.uniform_draws(np.ascontiguousarray(base, dtype=np.uint64),
                                np.ascontiguousarray(step, dtype=np.int64), int(n))
