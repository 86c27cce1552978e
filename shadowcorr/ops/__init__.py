"""Array operations the stages share, one op per module, on ragged batches of segments.

Every stage holds all segments of a scene in flat arrays sorted by segment index, with
the number of segments given explicitly (segments may be empty):

- :func:`pack_cell_keys`, :func:`unique_keys` - (segment, voxel cell) pairs packed into one
  sortable int64 key, and their unique values;
- :func:`sort_keys`, :func:`argsort_keys` - int64 keys sorted by runs or by 16-bit digits where
  their order or span allow;
- :func:`segment_max`, :func:`segment_min`, :func:`segment_range` - per-segment reductions;
- :func:`segment_chunks` - row ranges of whole segments, to bound the memory of expansions;
- :func:`separation_gap`, :func:`separated` - segments moved apart so that one k-d tree
  answers per-segment neighbour queries;
- :func:`relative_depth_noise` - a depth image's noise (``sigma = a z^2``), estimated from itself;
- :func:`thread_map`, :func:`resolve_threads` - independent chunks or views of a stage on
  ``num_threads`` threads.
"""

from __future__ import annotations

from ._depth_noise import NOISE_ROW_STEP, relative_depth_noise
from ._grid_keys import pack_cell_keys, unique_keys
from ._segment_chunks import segment_chunks
from ._segment_reduce import segment_max, segment_min, segment_range, segment_starts
from ._segment_separation import separated, separation_gap
from ._sort_keys import argsort_keys, sort_keys
from ._thread_map import resolve_threads, thread_map

__all__ = [
    "NOISE_ROW_STEP", "argsort_keys", "pack_cell_keys", "relative_depth_noise", "segment_chunks", "segment_max", "segment_min", "segment_range", "segment_starts", "separated",
    "separation_gap", "resolve_threads", "sort_keys", "thread_map", "unique_keys",
]
