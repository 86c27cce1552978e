"""Sorting int64 keys: by runs where they come nearly sorted, else by 16-bit digits where that is faster.

NumPy's default sort of int64 keys compares them (introsort, about 40 ns a key on the 2-core
x86-64 machine of the benchmarks, ``benchmarks/bench_engine.py``), whatever it knows about them.
The stages' keys say more:

* Keys that arrive as a few sorted runs (points sorted by segment and, within each, by cell,
  regrouped by object) are merged by a stable sort (timsort finds the runs and merges them):
  60 thousand keys in 6 runs take 0.6 ms against 2.7 ms.
* Keys that span at most :data:`_RADIX_MAX_BITS` bits (a voxel cell and a segment index take
  25-35) are sorted least significant 16-bit digit first: NumPy sorts 16-bit integers stably
  by counting (radix sort), so each pass is linear; up to :data:`_RADIX_MAX_KEYS` keys the
  gathers between passes stay in cache: 1.5-3.5 times faster at 10-300 thousand keys, no
  faster at a million (gathers out of cache).

Otherwise :func:`argsort_keys` sorts the keys with each one's row in its low bits (where they
fit): a value sort, about half the time of an argsort.  All ways give the same sorted values;
:func:`argsort_keys` is stable in every case, so its order is the same too.
"""

from __future__ import annotations

import numpy as np

#: Widest key span sorted by 16-bit digits (three passes).
_RADIX_MAX_BITS = 48
#: Most keys sorted by 16-bit digits.
_RADIX_MAX_KEYS = 1 << 18
#: Keys per descent (a key below its predecessor) from which the keys count as a few sorted runs.
_KEYS_PER_RUN = 64


def sort_keys(keys: np.ndarray) -> np.ndarray:
    """``np.sort(keys)`` of 1-D int64 keys, by the fastest of the ways in the module docstring."""
    passes = _radix_passes(keys)
    if not passes:  # nearly sorted (0: a stable sort merges the runs), or too many or too wide keys (None)
        return np.sort(keys, kind="stable" if passes == 0 else "quicksort")
    low = int(keys.min())
    shifted = keys - low
    for shift in range(0, 16 * passes, 16):
        shifted = shifted[np.argsort(_digit(shifted, shift), kind="stable")]
    return shifted + low


def argsort_keys(keys: np.ndarray) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` of 1-D int64 keys, by the fastest of the ways in the module docstring."""
    passes = _radix_passes(keys)
    if passes == 0 or keys.size < 2:
        return np.argsort(keys, kind="stable")
    shifted = keys - int(keys.min())
    if passes is None:
        # Each key carries its row in its low bits, where they fit: one value sort then replaces
        # the (slower) argsort, and ties keep their rows' order.
        row_bits = int(keys.size - 1).bit_length()
        if int(shifted.max()).bit_length() + row_bits > 63:
            return np.argsort(keys, kind="stable")
        return np.sort((shifted << row_bits) | np.arange(keys.size, dtype=np.int64)) & ((1 << row_bits) - 1)
    order = np.argsort(_digit(shifted, 0), kind="stable")
    for shift in range(16, 16 * passes, 16):
        order = order[np.argsort(_digit(shifted[order], shift), kind="stable")]
    return order


def _radix_passes(keys: np.ndarray) -> int | None:
    """How many 16-bit digits sort ``keys``: 0 where they come as a few sorted runs, None where the
    default sort is faster (see the module docstring)."""
    if keys.size < 2:
        return None
    if int(np.count_nonzero(keys[1:] < keys[:-1])) * _KEYS_PER_RUN < keys.size:
        return 0
    if keys.size > _RADIX_MAX_KEYS:
        return None
    span = int(keys.max()) - int(keys.min())
    if span.bit_length() > _RADIX_MAX_BITS:
        return None
    return max(1, -(-span.bit_length() // 16))


def _digit(keys: np.ndarray, shift: int) -> np.ndarray:
    return ((keys >> shift) & 0xFFFF).astype(np.uint16)
