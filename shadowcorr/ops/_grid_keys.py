"""Integer keys for (group, x, y, z) cells, so grouping is one sort instead of a row-wise unique."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ._sort_keys import argsort_keys, sort_keys


def pack_cell_keys(group: np.ndarray, cells: np.ndarray | Sequence[np.ndarray]) -> tuple[np.ndarray, callable]:
    """Pack ``(group, cells[:, 0], cells[:, 1], cells[:, 2])`` into one int64 per row.

    ``cells`` is an (N, 3) integer array or its three columns as 1-D arrays (which saves
    stacking them when they were computed axis by axis).

    Sorting the keys sorts by group first, then x, y, z.  Returns the keys and a function
    that unpacks keys back into ``(group, cells)``.  Raises ``ValueError`` if the ranges do
    not fit 63 bits (a scene of about a million cells per axis and group count combined).
    """
    group = np.asarray(group, dtype=np.int64)
    # Column by column: reductions and shifts on contiguous 1-D arrays are several times
    # faster than along axis 0 of an (N, 3) array.
    if isinstance(cells, np.ndarray):
        cols = [np.ascontiguousarray(cells[:, i], dtype=np.int64) for i in range(3)]
    else:
        cols = [np.asarray(c, dtype=np.int64) for c in cells]
    if cols[0].shape[0] == 0:
        lo = np.zeros(3, dtype=np.int64)
        return np.zeros(0, dtype=np.int64), _unpacker(lo, [1, 1, 1])
    lo = np.array([c.min() for c in cols], dtype=np.int64)
    span = [int(c.max()) - int(m) + 1 for c, m in zip(cols, lo)]
    bits = [max(int(s - 1).bit_length(), 1) for s in span]
    group_bits = max(int(group.max(initial=0)).bit_length(), 1)
    if group_bits + sum(bits) > 63:
        raise ValueError("cell coordinates span too large a range to pack into 64-bit keys")
    key = group << (bits[0] + bits[1] + bits[2])
    key |= (cols[0] - lo[0]) << (bits[1] + bits[2])
    key |= (cols[1] - lo[1]) << bits[2]
    key |= cols[2] - lo[2]
    return key, _unpacker(lo, bits)


def _unpacker(lo: np.ndarray, bits: list[int]):
    def unpack(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.asarray(key, dtype=np.int64)
        z = key & ((1 << bits[2]) - 1)
        y = (key >> bits[2]) & ((1 << bits[1]) - 1)
        x = (key >> (bits[1] + bits[2])) & ((1 << bits[0]) - 1)
        group = key >> (bits[0] + bits[1] + bits[2])
        return group, np.stack([x, y, z], axis=1) + lo

    return unpack


def unique_keys(keys: np.ndarray, return_inverse: bool = False, return_counts: bool = False):
    """Sorted unique int64 keys (and optionally the inverse map or the counts), by sorting or counting.

    NumPy >= 2.3 answers ``np.unique`` on integers with a hash table, which is many
    times slower than one sort when most of a million keys are distinct.  Non-negative keys
    below ``_DENSE_KEYS_PER_ROW`` times their number (pairs of a few hundred segments) are
    counted in a table instead, in linear time; others are sorted by :func:`sort_keys` (or
    ordered by :func:`argsort_keys` for the inverse), which use what the keys' order and span
    allow.  ``return_inverse`` and ``return_counts`` are not offered together (no caller needs both).
    """
    if return_inverse and return_counts:
        raise ValueError("unique_keys returns the inverse or the counts, not both")
    n = keys.size
    low, high = (int(keys.min()), int(keys.max())) if n else (0, 0)
    if n and low >= 0 and high < _DENSE_KEYS_PER_ROW * n:
        count = np.bincount(keys, minlength=high + 1)
        unique = np.flatnonzero(count)
        if return_counts:
            return unique, count[unique]
        if return_inverse:
            rank = np.cumsum(count > 0) - 1
            return unique, rank[keys]
        return unique
    if not return_inverse:
        s = sort_keys(keys)
        first = np.flatnonzero(np.r_[True, s[1:] != s[:-1]]) if s.size else np.zeros(0, dtype=np.int64)
        return (s[first], np.diff(np.r_[first, s.size])) if return_counts else s[first]
    order = argsort_keys(keys)
    s = keys[order]
    new = np.r_[True, s[1:] != s[:-1]] if s.size else np.zeros(0, dtype=bool)
    inverse = np.empty(n, dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return s[new], inverse


#: Keys per row up to which :func:`unique_keys` counts in a table instead of sorting (the table's
#: int64 counts then take at most this many times the keys' own memory).
_DENSE_KEYS_PER_ROW = 4
