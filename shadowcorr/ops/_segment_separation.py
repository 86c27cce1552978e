"""Keep neighbour searches inside their segment: move the segments far apart along x.

One k-d tree over all segments at once answers per-segment nearest-neighbour queries
when segment s is shifted by s * gap and the gap exceeds every distance in the data:
no query can then reach another segment.
"""

from __future__ import annotations

import numpy as np


def separation_gap(*point_sets: np.ndarray) -> float:
    """A shift larger than any distance within or between the given point sets."""
    # Column by column: a column's min is ~20x faster than numpy's axis-0 reduction of (N, 3).
    present = [p for p in point_sets if p.shape[0]]
    extent = [max(float(p[:, i].max()) for p in present) - min(float(p[:, i].min()) for p in present) for i in range(3)]
    return 4.0 * max(extent) + 1.0


def separated(points: np.ndarray, segment: np.ndarray, gap: float) -> np.ndarray:
    """Move segment s by s * gap along x so that no neighbour search crosses segments."""
    out = points.copy()
    out[:, 0] += segment * gap
    return out
