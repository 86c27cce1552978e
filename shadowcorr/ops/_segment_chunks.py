"""Whole-segment chunks of a ragged batch: bounded working memory for per-row expansions."""

from __future__ import annotations

import math

import numpy as np


def segment_chunks(segment: np.ndarray, size: int, weight: np.ndarray | None = None,
                   min_chunks: int = 1) -> list[tuple[int, int]]:
    """``[lo, hi)`` row ranges of a segment-sorted array, each holding whole segments and
    about ``size`` rows (or ``size`` total ``weight``, e.g. the rows a step expands each row
    into); a segment larger than ``size`` is a chunk of its own.  With ``min_chunks`` the
    size shrinks so that there are at least that many chunks where the segments allow (one
    per thread of a pool).

    Rows of one chunk never share a segment with another chunk's, so per-segment work done
    chunk by chunk gives the same result as on the whole batch.
    """
    if segment.size == 0:
        return []
    starts = np.flatnonzero(np.r_[True, segment[1:] != segment[:-1]])
    if weight is None:
        before = starts.astype(np.float64)  # rows before each segment's start
    else:
        before = np.r_[0.0, np.cumsum(weight, dtype=np.float64)][starts]
    total = float(segment.size if weight is None else np.sum(weight, dtype=np.float64))
    size = min(size, math.ceil(total / max(min_chunks, 1)))
    cuts = np.unique(np.searchsorted(before, np.arange(0.0, max(total, 1.0), max(size, 1)), side="right") - 1)
    bounds = np.r_[starts[cuts], segment.size]
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))
